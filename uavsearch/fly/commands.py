"""Commands to one System: COMMAND_LONG / COMMAND_INT, each matched to its COMMAND_ACK, resent if none came.

An ack counts when it names the command and is addressed to this client (or to everyone): another
ground station's acks on a shared link are not ours. `long`/`int` return the MAV_RESULT (callers decide
what a refusal means); `require_long`/`require_int` raise CommandError for anything but ACCEPTED.
"""

from __future__ import annotations

import time

from .dialect import AUTOPILOT_COMPID, M, command_name, result_name
from .errors import CommandError


class Commands:
    def __init__(self, system):
        self.system = system
        self._acks: list = []
        self.last_ack = None  # the COMMAND_ACK of the last command; `.sim_s`: the vehicle clock when it came
        system.subscribe("COMMAND_ACK", self._on_ack)

    def _on_ack(self, m) -> None:
        c = self.system.connection
        if m.target_system in (0, c.source_system) and m.target_component in (0, c.source_component):
            m.sim_s = self.system.telemetry.sim_time_s  # the last position report before it
            self._acks.append(m)

    def long(self, command: int, *params: float, compid: int = AUTOPILOT_COMPID, timeout_s: float = 3.0,
             retries: int = 3) -> int:
        """COMMAND_LONG with retries (as MAVSDK does; `confirmation` counts the sends); its MAV_RESULT."""
        p = list(params) + [0.0] * (7 - len(params))
        sysid = self.system.sysid
        return self._send(command, lambda attempt: self.system.mav.command_long_send(
            sysid, compid, command, attempt, *p), timeout_s, retries)

    def int(self, command: int, frame: int, p1, p2, p3, p4, x: int, y: int, z: float,
            compid: int = AUTOPILOT_COMPID, timeout_s: float = 3.0, retries: int = 3) -> int:
        """COMMAND_INT (x, y: degE7 in global frames) with retries; its MAV_RESULT."""
        sysid = self.system.sysid
        return self._send(command, lambda _attempt: self.system.mav.command_int_send(
            sysid, compid, frame, command, 0, 0, p1, p2, p3, p4, x, y, z), timeout_s, retries)

    def require_long(self, command: int, *params: float, what: str | None = None, **kw) -> None:
        self._require(command, self.long(command, *params, **kw), what)

    def require_int(self, command: int, *args, what: str | None = None, **kw) -> None:
        self._require(command, self.int(command, *args, **kw), what)

    def _require(self, command: int, result: int, what: str | None) -> None:
        if result != M.MAV_RESULT_ACCEPTED:
            texts = self.system.last_texts(2)
            raise CommandError(f"{what or command_name(command)} refused ({texts or result_name(result)})",
                               command, result)

    def _send(self, command: int, send, timeout_s: float, retries: int) -> int:
        for attempt in range(retries):
            self._acks.clear()
            send(attempt)
            result = self._await_ack(command, timeout_s)
            if result is not None:
                return result
        raise CommandError(f"{command_name(command)} not acknowledged by the vehicle", command, None)

    def _await_ack(self, command: int, timeout_s: float) -> int | None:
        """The MAV_RESULT of the first COMMAND_ACK for `command` within the timeout, else None (resend)."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            for a in self._acks:
                if a.command == command:
                    self.last_ack = a
                    return int(a.result)
            self.system.pump(0.02)
        return None


__all__ = ["Commands"]
