"""MAVProxy as a user runs it, and a pymavlink observer of what the vehicle really did: the tests' ground station
sessions for MAVProxy (one vehicle, or one of a team by `vehicle N`)."""

from __future__ import annotations

import importlib.util
import queue
import re
import subprocess
import sys
import threading
import time

import pytest

from .clean_env import clean_env
from .mavlink_client import Client

needs_mavproxy = pytest.mark.skipif(importlib.util.find_spec("MAVProxy") is None,
                                    reason="MAVProxy not installed (make setup installs mavproxy==1.8.75 --no-deps)")


class MavProxy:
    """MAVProxy as a user runs it, reading commands on stdin; its output collected line by line."""

    def __init__(self, port: int, workdir):
        cmd = [sys.executable, "-m", "MAVProxy.mavproxy", f"--master=udpin:127.0.0.1:{port}",
               f"--state-basedir={workdir}", f"--logfile={workdir}/mavproxy.tlog", "--default-modules",
               "link,signing,log,wp,param,arm,mode,misc,cmdlong,rally,fence,output,battery",
               "--load-module=uavsearch.mavproxy_px4"]
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     text=True, bufsize=1, cwd=workdir,
                                     env=clean_env(TERM="dumb"))
        self.lines: list[str] = []
        self._q: queue.Queue = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self):
        for line in self.proc.stdout:
            self._q.put(line.rstrip("\n"))

    def _drain(self):
        while True:
            try:
                self.lines.append(self._q.get_nowait())
            except queue.Empty:
                return

    def send(self, line: str) -> int:
        """Type a command; returns the output position to expect() from."""
        self._drain()
        mark = len(self.lines)
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()
        return mark

    def expect(self, pattern: str, since: int = 0, timeout_s: float = 20.0, pump=None) -> str:
        end = time.monotonic() + timeout_s
        rx = re.compile(pattern)
        while time.monotonic() < end:
            self._drain()
            for line in self.lines[since:]:
                if rx.search(line):
                    return line
            if pump:
                pump()
            time.sleep(0.05)
        raise AssertionError(f"MAVProxy never printed /{pattern}/ within {timeout_s} s; it printed:\n"
                             + "\n".join(self.lines[-40:]))

    def output(self, since: int = 0) -> str:
        self._drain()
        return "\n".join(self.lines[since:])

    def stop(self):
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


class Observer:
    """The vehicle as seen on its API link: mode, armed, altitude, mission progress."""

    def __init__(self, port: int):
        self.c = Client(port, sysid=254, compid=191)
        self.mode, self.armed, self.rel_alt, self.reached, self.current = None, False, 0.0, set(), None

    def pump(self):
        while (m := self.c.recv(None, 0)) is not None:
            t = m.get_type()
            if t == "HEARTBEAT" and m.get_srcComponent() == 1:
                self.mode = ((m.custom_mode >> 16) & 0xFF, (m.custom_mode >> 24) & 0xFF)
                self.armed = bool(m.base_mode & 128)
            elif t == "GLOBAL_POSITION_INT":
                self.rel_alt = m.relative_alt * 1e-3
            elif t == "MISSION_ITEM_REACHED":
                self.reached.add(m.seq)
            elif t == "MISSION_CURRENT":
                self.current = m.seq

    def wait(self, cond, what: str, timeout_s: float = 30.0):
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            self.pump()
            if cond():
                return
            time.sleep(0.02)
        raise AssertionError(f"vehicle: {what} not seen within {timeout_s} s (mode {self.mode}, armed {self.armed}, "
                             f"alt {self.rel_alt:.1f} m, reached {sorted(self.reached)})")


__all__ = ["MavProxy", "Observer", "needs_mavproxy"]
