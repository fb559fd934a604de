"""One MAVLink connection: it owns the socket, reads every frame, and hands each vehicle its own `System`.

As in MAVSDK, the connection demultiplexes by system id: a `System` is created on the first heartbeat of
its system id and sees only that system's frames, so a second vehicle on the link is a second object and
never takes over the first one's state. `wait_system(sysid)` or `first_autopilot()` gives a user the
vehicle they want; `systems()` lists what is on the link.

The wire protocol is MAVLink 2 with the `common` dialect (dialect.py), chosen here and not from the
environment (pymavlink otherwise picks MAVLink 1 unless MAVLINK20 is set before it is imported).
"""

from __future__ import annotations

import contextlib
import io
import time

from pymavlink import mavutil

from .dialect import AUTOPILOT_COMPID, CAMERA_COMPID, M, command_name, result_name
from .errors import FlightError
from .system import System

class MavlinkConnection:
    """The socket of one MAVLink link (`udpin:HOST:PORT`, `udpout:...`, `tcp:...`) and the systems on it.

    `heartbeat`: send a GCS heartbeat once a second while pumping (a ground station's duty; tests that
    study link loss turn it off). Frames of a system id not seen in a heartbeat yet are dropped."""

    def __init__(self, url: str, source_system: int = 245, source_component: int = 190, tlog=None,
                 heartbeat: bool = True):
        self.url = url
        self.source_system, self.source_component = source_system, source_component
        try:
            # pymavlink prints its own retries ("... sleeping") to stdout; the error below says it once
            with contextlib.redirect_stdout(io.StringIO()):
                self.mavfile = mavutil.mavlink_connection(url, source_system=source_system,
                                                          source_component=source_component, dialect="common")
        except Exception as e:  # noqa: BLE001 - any bad URL / port is one line
            raise FlightError(f"cannot open MAVLink connection {url!r}: {e}") from None
        f = self.mavfile
        # MAVLink 2 from the first packet, whatever dialect pymavlink's import picked from the environment
        f.mav = M.MAVLink(f, srcSystem=source_system, srcComponent=source_component)
        f.mav.robust_parsing = f.robust_parsing  # a bad frame (CRC, signature) is BAD_DATA, not an exception
        f.WIRE_PROTOCOL_VERSION, f.first_byte = "2.0", False
        if tlog is not None:
            tlog.attach(f)
        self.heartbeat = heartbeat
        self._systems: dict = {}
        self._listeners: list = []
        self._last_hb_sent = 0.0
        self.closed = False

    @property
    def mav(self):
        """pymavlink's encoder for this link (`mav.command_long_send(...)`)."""
        return self.mavfile.mav

    @property
    def port(self):
        """The UDP socket (None for other transports)."""
        return getattr(self.mavfile, "port", None)

    @property
    def link_text(self) -> str:
        """The URL with the port this client really listens on (`udpin:HOST:0` binds a free one)."""
        scheme, _, rest = self.url.partition(":")
        if scheme != "udpin":
            return self.url
        try:
            port = self.mavfile.port.getsockname()[1]
        except (AttributeError, OSError):
            return self.url
        return f"udpin:{rest.rpartition(':')[0]}:{port}"

    # ------------------------------------------------------------------ systems
    def systems(self) -> list:
        """Every system seen on the link so far, by system id."""
        return [self._systems[k] for k in sorted(self._systems)]

    def wait_system(self, sysid: int | None = None, timeout_s: float = 10.0):
        """The `System` of `sysid` (None: the first autopilot) once its autopilot's heartbeat arrived (a camera's
        is not enough); None after timeout_s."""
        end = time.monotonic() + timeout_s
        while True:
            for s in self.systems():
                if s.is_autopilot and (sysid is None or s.sysid == sysid):
                    return s
            if time.monotonic() >= end:
                return None
            self.pump(min(0.05, max(0.0, end - time.monotonic())))

    def first_autopilot(self, timeout_s: float = 10.0):
        return self.wait_system(None, timeout_s)

    def add_listener(self, fn) -> None:
        """fn(msg) for every routed frame (any system), after its System has seen it."""
        self._listeners.append(fn)

    # ------------------------------------------------------------------ the pump
    def send_heartbeat(self, force: bool = False) -> None:
        now = time.monotonic()
        if force or now - self._last_hb_sent >= 1.0:
            self._last_hb_sent = now
            self.mav.heartbeat_send(M.MAV_TYPE_GCS, M.MAV_AUTOPILOT_INVALID, 0, 0, M.MAV_STATE_ACTIVE)

    def send_bytes(self, data: bytes) -> None:
        """Raw bytes to the peer(s), as they are (tests of malformed input)."""
        self.mavfile.write(data)

    def _route(self, m):
        """Hand the frame to its system (creating it on a first heartbeat); the frame, or None if dropped."""
        if m.get_type() == "BAD_DATA":
            return None
        sysid = m.get_srcSystem()
        system = self._systems.get(sysid)
        if system is None:
            if m.get_type() != "HEARTBEAT":
                return None
            system = self._systems[sysid] = System(self, sysid)
        system.dispatch(m)
        for fn in self._listeners:
            fn(m)
        return m

    def recv(self, timeout_s: float = 0.05):
        """Route frames until one is kept (returned) or timeout_s passes (None)."""
        if self.heartbeat:
            self.send_heartbeat()
        end = time.monotonic() + timeout_s
        while True:
            left = end - time.monotonic()
            # pymavlink's recv_match reads nothing when given a timeout of 0: ask it not to block instead
            m = self.mavfile.recv_match(blocking=True, timeout=left) if left > 0 else \
                self.mavfile.recv_match(blocking=False)
            if m is not None and self._route(m) is not None:
                return m
            if m is None and time.monotonic() >= end:
                return None

    def pump(self, timeout_s: float = 0.05) -> None:
        """Route every frame that is waiting (block up to timeout_s for the first one)."""
        if self.heartbeat:
            self.send_heartbeat()
        m = self.mavfile.recv_match(blocking=True, timeout=timeout_s)
        while m is not None:
            self._route(m)
            m = self.mavfile.recv_match(blocking=False)

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self.mavfile.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


__all__ = ["AUTOPILOT_COMPID", "CAMERA_COMPID", "M", "MavlinkConnection", "command_name", "result_name"]
