"""COMMAND_LONG / COMMAND_INT: decode, route to the component and capability that serves them, ACK the sender.

Camera commands go to the camera component (compid 100); the protocol modules register the autopilot
commands they serve (message intervals, lockstep); everything else becomes a VehicleCommand for the
commander, which reuses MAV_CMD numbers. COMMAND_INT's degE7 coordinates become degrees here, so the
commander sees one form of every command.
"""

from __future__ import annotations

import math

from pymavlink.dialects.v20 import common as M

from ..camera import CAMERA_COMPID
from ..commander import Result, VehicleCommand
from ..lockstep import MAV_CMD_SIM_ADVANCE
from .camera import CAMERA_COMMANDS
from .links import AUTOPILOT_COMPID, Link

_GLOBAL_FRAMES = (M.MAV_FRAME_GLOBAL, M.MAV_FRAME_GLOBAL_INT, M.MAV_FRAME_GLOBAL_RELATIVE_ALT,
                  M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT)
_FLOAT_FRAME = {M.MAV_FRAME_GLOBAL_INT: M.MAV_FRAME_GLOBAL,
                M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT: M.MAV_FRAME_GLOBAL_RELATIVE_ALT}


class Commands:
    """The command router. `handlers`: MAV_CMD -> fn(link, m, command, params) for autopilot commands served
    outside the commander; `camera`: the camera protocol, or None when the vehicle has no camera."""

    def __init__(self, ep, handlers: dict, camera=None):
        self.ep = ep
        self.handlers = {**handlers, MAV_CMD_SIM_ADVANCE: self._on_sim_advance}
        self.camera = camera
        self.messages = {"COMMAND_LONG": self._on_command_long, "COMMAND_INT": self._on_command_int}

    def _on_command_long(self, link: Link, m) -> None:
        if not self.ep.for_me(m.target_system):
            return
        p = [m.param1, m.param2, m.param3, m.param4, m.param5, m.param6, m.param7]
        self._command(link, m, m.command, p, M.MAV_FRAME_GLOBAL, m.target_component)

    def _on_command_int(self, link: Link, m) -> None:
        if not self.ep.for_me(m.target_system):
            return
        p = [m.param1, m.param2, m.param3, m.param4, float(m.x), float(m.y), m.z]
        if m.frame in _GLOBAL_FRAMES:
            p[4] = m.x * 1e-7 if m.x != 0 or m.y != 0 else math.nan
            p[5] = m.y * 1e-7 if m.x != 0 or m.y != 0 else math.nan
        self._command(link, m, m.command, p, _FLOAT_FRAME.get(m.frame, m.frame), m.target_component)

    def _command(self, link: Link, m, command: int, p: list, frame: int, target_comp: int) -> None:
        try:
            self._dispatch(link, m, command, p, frame, target_comp)
        except (ValueError, OverflowError):  # e.g. a message id or count of NaN / inf
            self.ep.ack(link, m, command, Result.DENIED,
                        CAMERA_COMPID if target_comp == CAMERA_COMPID else AUTOPILOT_COMPID)

    def _dispatch(self, link: Link, m, command: int, p: list, frame: int, target_comp: int) -> None:
        to_camera = target_comp == CAMERA_COMPID or (target_comp == 0 and command in CAMERA_COMMANDS)
        if to_camera:
            if self.camera is not None:
                self.camera.command(link, m, command, p)
            return
        if target_comp not in (0, AUTOPILOT_COMPID):
            return  # addressed to a component that does not exist here
        handler = self.handlers.get(command)
        if handler is not None:
            return handler(link, m, command, p)
        vc = VehicleCommand(command, *(float(x) for x in p), frame=frame, source_system=m.get_srcSystem(),
                            source_component=m.get_srcComponent())
        result = self.ep.cmd.handle_command(vc)
        self.ep.ack(link, m, command, result)
        self.ep.flush_events()
        self.ep.send_state_if_changed()

    def _on_sim_advance(self, link: Link, m, command: int, p: list) -> None:
        """Lockstep (see lockstep.py): run to time_boot_ms = param5 / x, ACK once the clock is there."""
        until_ms = p[4]
        if self.ep.lockstep is None:
            return self.ep.ack(link, m, command, Result.UNSUPPORTED)
        if not (math.isfinite(until_ms) and 0 <= until_ms < 2**31):
            return self.ep.ack(link, m, command, Result.DENIED)
        self.ep.lockstep.grant(int(until_ms) * 1000,
                               lambda now_ms: self.ep.ack(link, m, command, Result.ACCEPTED, result_param2=now_ms))
