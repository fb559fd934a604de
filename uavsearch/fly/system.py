"""One vehicle on a MAVLink connection (MAVSDK's `System`): its frames only, split into plugins by capability.

`system.telemetry` (position, mode, armed, health, clock), `system.commands` (COMMAND_LONG/INT with acks),
`system.camera`, `system.params`, `system.mission`, `system.lockstep` (MAV_CMD_SIM_ADVANCE grants). Each
plugin subscribes to the message types it reads; the System only routes. `wait_until` is the one wait
every plugin and the vehicle use: simulation time for things that need the vehicle to move (granted in
lockstep), wall clock for answers, a wall-clock backstop for a vehicle that stopped talking.
"""

from __future__ import annotations

import time
from collections import defaultdict

from .camera import Camera
from .commands import Commands
from .dialect import M
from .errors import FlightError, StepFailed
from .lockstep import Lockstep
from .mission_transfer import Mission
from .params import Params
from .telemetry import Telemetry

# A wait that lasts longer than PROGRESS_FIRST_S (wall clock) says what it waits for and how far it is, then
# again every PROGRESS_EVERY_S, so a real-time take-off or landing or a silent link never looks like a hang.
PROGRESS_FIRST_S = 2.0
PROGRESS_EVERY_S = 5.0


class System:
    """The vehicle with system id `sysid` on `connection`; created by the connection on its first heartbeat."""

    def __init__(self, connection, sysid: int):
        self.connection = connection
        self.sysid = sysid
        self._handlers: dict = defaultdict(list)
        self.status_texts: list[str] = []  # the last 20 STATUSTEXTs
        self.subscribe("STATUSTEXT", self._on_text)
        self.telemetry = Telemetry(self)
        self.commands = Commands(self)
        self.lockstep = Lockstep(self)
        self.camera = Camera(self)
        self.params = Params(self)
        self.mission = Mission(self)
        self.watchdog = None  # callable() raising FlightError when the vehicle is known dead (a process it runs in)

    def __repr__(self) -> str:
        return f"System({self.sysid})"

    @property
    def is_autopilot(self) -> bool:
        """Its autopilot (component 1) has sent a heartbeat (not a ground station's)."""
        return self.telemetry.heartbeat is not None

    @property
    def mav(self):
        return self.connection.mav

    def subscribe(self, msg_type: str, fn) -> None:
        """fn(msg) for each `msg_type` frame from this system."""
        self._handlers[msg_type].append(fn)

    def unsubscribe(self, msg_type: str, fn) -> None:
        self._handlers[msg_type].remove(fn)

    def dispatch(self, m) -> None:
        for fn in tuple(self._handlers.get(m.get_type(), ())):
            fn(m)

    def _on_text(self, m) -> None:
        self.status_texts = (self.status_texts + [m.text])[-20:]

    def last_texts(self, n: int) -> str:
        """The last n STATUSTEXTs joined, '' if none (for error messages)."""
        return "; ".join(self.status_texts[-n:]) if n else ""

    # ------------------------------------------------------------------ time
    def pump(self, timeout_s: float = 0.05) -> None:
        """Read the link (every system's frames are routed); FlightError if the vehicle is known dead."""
        if self.watchdog is not None:
            self.watchdog()
        self.connection.pump(timeout_s)

    def advance(self, sim_s: float | None = None) -> None:
        """Let the vehicle fly on: grant it sim_s (lockstep) or read its telemetry for up to that long."""
        if self.lockstep.enabled:
            self.lockstep.advance(sim_s)
        else:
            self.pump(0.05 if sim_s is None else sim_s)

    def wait_until(self, cond, wall_timeout_s: float, what: str, sim_timeout_s: float | None = None,
                   moving: bool = True, tick_s: float | None = None, status=None, say=None):
        """Until cond() is truthy (returned); FlightError (StepFailed for sim-time outs) naming `what` otherwise.

        `moving`: the condition needs simulation time (lockstep grants it, `tick_s` at a time, or as much as a
        callable `tick_s()` says before each grant); otherwise it
        is an answer the vehicle sends at once, and in lockstep no time may pass while waiting for it.
        `status(elapsed)` (simulation seconds when moving, else wall seconds) is a progress line given to
        `say` while the wait lasts (PROGRESS_FIRST_S, then every PROGRESS_EVERY_S of wall clock)."""
        wall0 = time.monotonic()
        wall_end = wall0 + wall_timeout_s
        next_note = wall0 + PROGRESS_FIRST_S
        if self.lockstep.enabled and moving:
            self.lockstep.barrier()
        clock = self.telemetry
        sim0 = clock.sim_time_s
        while True:
            r = cond()
            if r:
                return r
            now = time.monotonic()
            if status is not None and say is not None and now >= next_note:
                next_note = now + PROGRESS_EVERY_S
                sim_now = clock.sim_time_s
                elapsed = sim_now - sim0 if moving and sim0 is not None and sim_now is not None else now - wall0
                say(status(elapsed))
            if time.monotonic() > wall_end:
                raise FlightError(f"{what}: no answer from the vehicle within {wall_timeout_s:.0f} s (wall clock)")
            if sim_timeout_s is not None and sim0 is not None and clock.sim_time_s is not None \
                    and clock.sim_time_s - sim0 > sim_timeout_s:
                raise StepFailed(f"{what}: not done after {sim_timeout_s:g} s of flight")
            if moving:
                self.advance((tick_s() if callable(tick_s) else tick_s) if self.lockstep.enabled else None)
            else:
                self.pump()

    def request(self, msg_type: str, send, cond=None, timeout_s: float = 2.0, retries: int = 3):
        """send() until a `msg_type` frame with cond(msg) answers (returned), `retries` times; None if none did."""
        got: list = []

        def keep(m):
            if cond is None or cond(m):
                got.append(m)

        self.subscribe(msg_type, keep)
        try:
            for _ in range(retries):
                got.clear()
                send()
                end = time.monotonic() + timeout_s
                while time.monotonic() < end:
                    if got:
                        return got[0]
                    self.pump(0.02)
            return None
        finally:
            self.unsubscribe(msg_type, keep)


__all__ = ["M", "PROGRESS_EVERY_S", "PROGRESS_FIRST_S", "System"]
