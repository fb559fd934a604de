"""Start `uavsearch sitl` as a real process on free loopback ports, and a pymavlink client for it."""

from __future__ import annotations

import math
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from pymavlink import mavutil

NAN = math.nan


def free_udp_port() -> int:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


class SitlProcess:
    """`python -m uavsearch.flight.sitl` with the given arguments; stopped with SIGINT (Ctrl-C)."""

    def __init__(self, run_dir: Path, *args: str, api_port: int | None = None, gcs_port: int | None = None,
                 speed: str = "max", camera: bool = False):
        self.api_port = api_port or free_udp_port()
        self.gcs_port = gcs_port or free_udp_port()
        cmd = [sys.executable, "-m", "uavsearch.flight.sitl", "--speed", speed, "--out", str(run_dir),
               "--api-port", str(self.api_port), "--gcs-port", str(self.gcs_port),
               "--api-local-port", "0", "--gcs-local-port", "0", *args]
        if not camera:
            cmd.append("--no-camera-scene")
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                     env={**os.environ, "PYTHONUNBUFFERED": "1"})
        self.banner = []
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            line = self.proc.stdout.readline()
            if not line:
                raise RuntimeError("sitl exited early:\n" + "".join(self.banner))
            self.banner.append(line)
            if line.startswith("ready"):
                return
        raise RuntimeError("sitl did not get ready:\n" + "".join(self.banner))

    def stop(self) -> tuple[int, str]:
        """Ctrl-C, then the exit code and the rest of the output."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        try:
            out, _ = self.proc.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, _ = self.proc.communicate()
        return self.proc.returncode, out


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
