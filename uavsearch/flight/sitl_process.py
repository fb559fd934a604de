"""`uavsearch sitl` as its own process: what the mission controller and the tests fly against.

The vehicle runs in a separate process on loopback UDP, sharing nothing with its client but the run
directory, like PX4 SITL. It gets its own session, so a Ctrl-C in the terminal reaches only the client
(which lands first) and the vehicle is stopped after it with SIGINT; on Linux it also dies with its
parent, so a killed client leaves no vehicle running. Its output goes to RUN_DIR/sitl.log.
"""

from __future__ import annotations

import ctypes
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from ..errors import UavsearchError
from ..world import settings


class SitlStartError(UavsearchError):
    """The vehicle process exited or did not get ready."""


EPHEMERAL_FALLBACK = (32768, 60999)  # Linux's default ip_local_port_range, where /proc does not say
RESERVED_FLOOR = 20000  # below: well-known services and MAVLink's own (14540-14580 API/GCS links, 18570 SITL)


def ephemeral_ports() -> tuple[int, int]:
    """The kernel's range for bind(port 0), inclusive (Linux: /proc/sys/net/ipv4/ip_local_port_range)."""
    try:
        low, high = (int(x) for x in Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split())
        return low, high
    except (OSError, ValueError):
        return EPHEMERAL_FALLBACK


def udp_port_in_use(port: int, host: str = "127.0.0.1") -> bool:
    """Whether another socket holds UDP `port` (a bind without SO_REUSEADDR fails): pymavlink binds with it, so
    its own bind would succeed beside another client and the two would split the vehicle's packets."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            sock.bind((host, int(port)))
        except OSError:
            return True
    return False


def free_udp_port() -> int:
    """A free UDP port on 127.0.0.1 for a link whose two ends bind at different moments (a vehicle sends to it,
    its client binds it later): free_udp_ports(1)."""
    return free_udp_ports(1)


def free_udp_ports(n: int) -> int:
    """The first of `n` consecutive free UDP ports on 127.0.0.1 (a team's API links: vehicle I on base + I), drawn
    at random below the kernel's ephemeral range. Between choosing a port and binding it the port is free, and
    any process binding port 0 meanwhile (every vehicle's own end of its links, pymavlink's clients) gets one
    from the ephemeral range: a port from there could go to another vehicle, whose telemetry and command
    answers would then reach this link's client (pymavlink binds with SO_REUSEADDR, so both binds succeed)."""
    import random

    low = ephemeral_ports()[0]
    start, stop = RESERVED_FLOOR, (low if low - RESERVED_FLOOR >= 1000 else 65536)  # no room below: anywhere
    rng = random.Random()  # not the caller's seed: which free ports there are says nothing about a flight
    for _ in range(200):
        base = rng.randrange(start, stop - n)
        socks = []
        try:
            for i in range(n):
                sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                socks.append(sock)
                sock.bind(("127.0.0.1", base + i))
            return base
        except OSError:
            continue
        finally:
            for sock in socks:
                sock.close()
    raise UavsearchError(f"no {n} consecutive free UDP ports on 127.0.0.1")


def _die_with_parent() -> None:
    """In the child: get SIGTERM when the parent dies (PR_SET_PDEATHSIG)."""
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)
        except OSError:
            pass


class SitlProcess:
    """`python -m uavsearch.flight.sitl ARGS` on the given (or free) UDP ports; returns once it is ready.

    `args` are more `uavsearch sitl` options (scene, seed, home, params); `camera=False` skips building
    the scene (faster start; captures fail). A port of None is a free one, 0 turns the link off.
    `wait=False` returns as soon as the process is started, so its start-up (imports, physics) runs
    while the caller does its own; `wait_ready()` then waits for the ready line.
    `progress(line)`, when given, hears every 2 s how long the start has taken and what the vehicle last said.
    `env`, when given, is the vehicle's whole environment (tests pass one built from scratch, so nothing an
    earlier test exported can hide a bug); by default it inherits this process's.
    """

    def __init__(self, run_dir: Path, *args: str, api_port: int | None = None, gcs_port: int | None = None,
                 speed: str = "max", lockstep: bool = False, camera: bool = True, timeout_s: float = 120.0,
                 wait: bool = True, progress=None, env: dict | None = None):
        run_dir = Path(run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
        self.run_dir = run_dir
        self.log_path = run_dir / "sitl.log"
        self.api_port = free_udp_port() if api_port is None else api_port
        self.gcs_port = free_udp_port() if gcs_port is None else gcs_port
        cmd = [sys.executable, "-m", "uavsearch.flight.sitl", "--speed", speed, "--out", str(run_dir),
               "--api-port", str(self.api_port), "--gcs-port", str(self.gcs_port),
               "--api-local-port", "0", "--gcs-local-port", "0", *args]
        if lockstep:
            cmd.append("--lockstep")
        if not camera:
            cmd.append("--no-camera-scene")
        self._out = open(self.log_path, "w")
        self.proc = subprocess.Popen(cmd, stdout=self._out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                     env={**(os.environ if env is None else env), **settings.child_env(), "PYTHONUNBUFFERED": "1"},
                                     preexec_fn=_die_with_parent,
                                     start_new_session=True)  # Ctrl-C reaches the client only: it lands first
        self.banner: list[str] = []  # the lines up to "ready" (ports, signing, run directory)
        self._start = time.monotonic()
        self._end = self._start + timeout_s
        self._timeout_s = timeout_s
        self.progress = progress
        if wait:
            self.wait_ready()

    def _failed(self, why: str) -> SitlStartError:
        self.stop()
        return SitlStartError(why)

    def exit_reason(self) -> str | None:
        """None while the vehicle runs; else how it ended: 'exited with code 3', 'was killed by SIGKILL'."""
        code = self.proc.poll()
        if code is None:
            return None
        if code < 0:
            try:
                return f"was killed by {signal.Signals(-code).name}"
            except ValueError:
                return f"was killed by signal {-code}"
        return f"exited with code {code}"

    def wait_ready(self) -> None:
        """Until the vehicle printed its ready line; SitlStartError if it exited or the start timed out."""
        next_note = max(time.monotonic(), self._start + 2.0)
        while not self.banner:
            text = self.log_path.read_text()
            if "\nready" in text or text.startswith("ready"):
                end_of_banner = 0 if text.startswith("ready") else text.index("\nready") + 1
                self.banner = text[:end_of_banner].splitlines(keepends=True) + ["ready\n"]
                return
            if self.proc.poll() is not None:
                last = [ln for ln in text.strip().splitlines() if ln.strip()][-1:] or ["no output"]
                raise self._failed(f"uavsearch sitl exited at start: {last[0]} (see {self.log_path})")
            if time.monotonic() > self._end:
                raise self._failed(f"uavsearch sitl did not get ready in {self._timeout_s:.0f} s (see {self.log_path})")
            if self.progress is not None and time.monotonic() >= next_note:  # not ready yet: say how far
                next_note += 2.0
                said = [ln.strip() for ln in text.splitlines() if ln.strip()][-1:] or ["starting Python"]
                self.progress(f"vehicle   starting ({said[0]})  {time.monotonic() - self._start:4.0f} s")
            time.sleep(0.02)

    def link_address(self, name: str) -> tuple[str, int]:
        """Where link `name` ("api" or "gcs") listens (its source port): a client that talks first sends here."""
        for line in self.banner:
            words = line.split()
            if words[:2] == [name.upper(), "link"] and "from" in words:
                host, _, port = words[words.index("from") + 1].rpartition(":")
                return host, int(port)
        raise SitlStartError(f"no {name} link in the banner")

    def wait_file(self, name: str) -> Path:
        """A file the vehicle writes into its run directory at start (written whole, by rename)."""
        path = self.run_dir / name
        while not path.is_file():
            if self.proc.poll() is not None:
                self.wait_ready()  # raises with the vehicle's last words
                raise self._failed(f"uavsearch sitl did not write {name} (see {self.log_path})")
            if time.monotonic() > self._end:
                raise self._failed(f"uavsearch sitl did not write {name} in {self._timeout_s:.0f} s "
                                   f"(see {self.log_path})")
            time.sleep(0.02)
        return path

    def stop(self, wait: bool = True) -> tuple[int | None, str]:
        """Ctrl-C (SIGINT), then the exit code and everything it printed. `wait=False` only asks it to stop:
        it closes its links and exits on its own (its last lines still reach the log), and nobody waits
        (exit code None)."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            if not wait:
                if not self._out.closed:
                    self._out.close()
                return None, ""
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if not self._out.closed:
            self._out.close()
        return self.proc.returncode, self.log_path.read_text()
