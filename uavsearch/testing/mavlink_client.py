"""A pymavlink ground station for the tests and benchmarks that fly `uavsearch sitl` (flight/sitl_process.py)."""

from __future__ import annotations

import math
import socket
import time

from pymavlink import mavutil

NAN = math.nan


class Client:
    """A pymavlink ground station bound to the port the vehicle sends to."""

    def __init__(self, port: int, sysid: int = 255, compid: int = 190):
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=sysid, source_component=compid,
                                               dialect="common")
        # At --speed max the vehicle streams telemetry tens of times faster than real time: a big receive
        # buffer keeps a busy test process from losing an ACK behind the telemetry backlog.
        self.conn.port.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
        hb = self.wait_heartbeat()
        assert hb is not None, "no heartbeat from the vehicle"
        self.conn.target_system, self.conn.target_component = hb.get_srcSystem(), 1

    @property
    def mav(self):
        return self.conn.mav

    def wait_heartbeat(self, timeout: float = 10.0):
        """The next autopilot heartbeat (compid 1), skipping the camera's."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            m = self.conn.recv_match(type="HEARTBEAT", blocking=True, timeout=0.5)
            if m is not None and m.get_srcComponent() == 1:
                return m
        return None

    def recv(self, types, timeout: float = 5.0, cond=None):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            m = self.conn.recv_match(type=types, blocking=True, timeout=0.2)
            if m is not None and (cond is None or cond(m)):
                return m
        return None

    def command(self, command: int, *params: float, target_component: int = 1, timeout: float = 3.0):
        """COMMAND_LONG; the matching COMMAND_ACK (or None)."""
        p = list(params) + [0.0] * (7 - len(params))
        self.mav.command_long_send(self.conn.target_system, target_component, command, 0, *p)
        return self.recv("COMMAND_ACK", timeout, cond=lambda m: m.command == command)

    def mode(self, timeout: float = 5.0) -> tuple[int, int, bool]:
        hb = self.wait_heartbeat(timeout)
        return (hb.custom_mode >> 16) & 0xFF, (hb.custom_mode >> 24) & 0xFF, bool(hb.base_mode & 128)

    def wait_mode(self, main: int, sub: int, timeout: float = 30.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            hb = self.wait_heartbeat(1.0)
            if hb is not None and (hb.custom_mode >> 16) & 0xFF == main and (hb.custom_mode >> 24) & 0xFF == sub:
                return True
        return False

    def send_heartbeat(self) -> None:
        self.mav.heartbeat_send(mavutil.mavlink.MAV_TYPE_GCS, mavutil.mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)

    def close(self) -> None:
        self.conn.close()


def clean_env(home) -> dict:
    """An environment built from scratch for a vehicle process: nothing an earlier test exported leaks in."""
    import os
    import sys

    return {"PATH": f"{os.path.dirname(sys.executable)}:/usr/local/bin:/usr/bin:/bin", "HOME": str(home),
            "LANG": "C.UTF-8", "TMPDIR": str(home)}


class PeerClient:
    """A pymavlink client on its own UDP socket that talks first (udpout), as a script beside a ground station
    does: the vehicle learns its address from its first frame and answers it there."""

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

    def close(self) -> None:
        self.conn.close()
