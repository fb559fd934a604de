"""The ground station the tests and benchmarks fly `uavsearch sitl` with: the product's client, thinly wrapped.

`Client(port)` is a `MavlinkConnection` on `udpin:127.0.0.1:PORT` and the `System` of the first autopilot
that heartbeats, with the raw calls tests need (send any message, receive the next one of a type). It
sends no heartbeats of its own (tests of link loss send them with `send_heartbeat`), and `command` sends
once and returns the COMMAND_ACK itself, so a test sees exactly what the vehicle answered.
"""

from __future__ import annotations

import math
import socket
import time
from collections import deque

from pymavlink import mavutil

from uavsearch.fly.connection import MavlinkConnection
from uavsearch.fly.dialect import AUTOPILOT_COMPID, M
from uavsearch.fly.errors import CommandError

NAN = math.nan


class Client:
    """A ground station bound to the port the vehicle sends to, flying the first autopilot it hears."""

    def __init__(self, port: int, sysid: int = 255, compid: int = 190, system_id: int | None = None,
                 timeout: float = 10.0):
        self.connection = MavlinkConnection(f"udpin:127.0.0.1:{port}", sysid, compid, heartbeat=False)
        # At --speed max the vehicle streams telemetry tens of times faster than real time: a big receive
        # buffer keeps a busy test process from losing an ACK behind the telemetry backlog.
        self.connection.port.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        # Every routed frame of the vehicle waits here for recv, as it would in the socket for pymavlink's
        # recv_match: what a command's wait read after its COMMAND_ACK is still there for the test.
        self.inbox: deque = deque(maxlen=100_000)
        self.system = None
        self.connection.add_listener(self._keep)
        self.system = self.connection.wait_system(system_id, timeout)
        assert self.system is not None and self.system.is_autopilot, "no heartbeat from the vehicle"
        self.inbox.clear()

    def _keep(self, m) -> None:
        if self.system is None or m.get_srcSystem() == self.system.sysid:
            self.inbox.append(m)

    @property
    def mav(self):
        return self.connection.mav

    @property
    def sysid(self) -> int:
        """The system id of the vehicle this client flies."""
        return self.system.sysid

    def setup_signing(self, key: bytes) -> None:
        """Sign everything this client sends with `key` (MAVLink 2 signing)."""
        self.connection.mavfile.setup_signing(key, sign_outgoing=True)

    def send_raw(self, data: bytes) -> None:
        """Bytes to the vehicle as they are, not framed by this client (malformed-input tests)."""
        self.connection.send_bytes(data)

    def recv(self, types=None, timeout: float = 5.0, cond=None):
        """The next frame from the vehicle (any component) of `types` (a name, a list, None: any) with cond(msg);
        the frames before it are consumed."""
        want = {types} if isinstance(types, str) else None if types is None else set(types)
        deadline = time.monotonic() + timeout
        while True:
            while self.inbox:
                m = self.inbox.popleft()
                if (want is None or m.get_type() in want) and (cond is None or cond(m)):
                    return m
            # timeout 0 still reads what is waiting, as pymavlink's recv_match(blocking=False) does
            got = self.connection.recv(max(0.0, min(0.2, deadline - time.monotonic())))
            if got is None and not self.inbox and time.monotonic() >= deadline:
                return None

    def wait_heartbeat(self, timeout: float = 10.0):
        """The next autopilot heartbeat (compid 1), skipping the camera's."""
        return self.recv("HEARTBEAT", timeout, cond=lambda m: m.get_srcComponent() == AUTOPILOT_COMPID)

    def command(self, command: int, *params: float, target_component: int = AUTOPILOT_COMPID, timeout: float = 3.0):
        """COMMAND_LONG, sent once; the matching COMMAND_ACK (or None). Frames up to the ack are consumed."""
        commands = self.system.commands
        try:
            commands.long(command, *params, compid=target_component, timeout_s=timeout, retries=1)
        except CommandError:
            self.inbox.clear()
            return None
        ack = commands.last_ack
        while self.inbox and self.inbox.popleft() is not ack:
            pass
        return ack

    def mode(self, timeout: float = 5.0) -> tuple[int, int, bool]:
        hb = self.wait_heartbeat(timeout)
        return (hb.custom_mode >> 16) & 0xFF, (hb.custom_mode >> 24) & 0xFF, bool(hb.base_mode & 128)

    def wait_mode(self, main: int, sub: int, timeout: float = 30.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.wait_heartbeat(1.0)
            if self.system.telemetry.mode() == (main, sub):
                return True
        return False

    def send_heartbeat(self) -> None:
        self.connection.send_heartbeat(force=True)

    def close(self) -> None:
        self.connection.close()


class PeerClient:
    """Someone else's plain pymavlink script, not this project's client: its own UDP socket that talks first
    (udpout), as a script beside a ground station does; the vehicle learns its address from its first frame
    and answers it there (the vehicle side's per-peer replies are tested against it)."""

    def __init__(self, addr: tuple[str, int], sysid: int, compid: int = 190, signing_key: bytes | None = None):
        from pymavlink.dialects.v20 import common as v20

        self.conn = mavutil.mavlink_connection(f"udpout:{addr[0]}:{addr[1]}", source_system=sysid,
                                               source_component=compid, dialect="common")
        self.conn.mav = v20.MAVLink(self.conn, srcSystem=sysid, srcComponent=compid)  # MAVLink 2 from the first frame
        self.conn.mav.robust_parsing = True
        self.conn.WIRE_PROTOCOL_VERSION = v20.WIRE_PROTOCOL_VERSION
        self.conn.port.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        if signing_key is not None:
            self.conn.setup_signing(signing_key, sign_outgoing=True)
        self.sysid = sysid
        self.send_heartbeat()

    @property
    def mav(self):
        return self.conn.mav

    def send_heartbeat(self) -> None:
        self.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)

    def drain(self) -> list:
        """Every message waiting now (non-blocking)."""
        out = []
        while True:
            m = self.conn.recv_msg()
            if m is None:
                return out
            if m.get_type() != "BAD_DATA":
                out.append(m)

    def wait(self, cond, timeout: float = 3.0):
        """The first message for which cond(m) holds within `timeout` wall seconds, or None."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for m in self.drain():
                if cond(m):
                    return m
            time.sleep(0.005)
        return None

    def close(self) -> None:
        self.conn.close()


__all__ = ["NAN", "Client", "M", "PeerClient"]
