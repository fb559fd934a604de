"""Ports on a shared machine: a port in use is one line naming the flag to change, and a `sitl` whose links
move off PX4's ports leaves PX4's source ports (14580, 18570) alone."""

import socket
import subprocess
import sys

from uavsearch.paths import MISSIONS_DIR
from uavsearch.testing.clean_env import clean_env


def _uavsearch(*args, timeout=120):
    return subprocess.run([sys.executable, "-m", "uavsearch", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, env=clean_env())


def _held_port():
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    return sock, sock.getsockname()[1]


def test_fly_on_an_api_port_in_use_is_one_line_naming_the_flag(tmp_path):
    sock, port = _held_port()
    with sock:
        r = _uavsearch("fly", "--mission", MISSIONS_DIR / "default.yaml", "--api-port", port, "--out", tmp_path / "run")
    err = r.stderr.strip()
    assert r.returncode == 2 and "\n" not in err and "Traceback" not in err, r.stdout + r.stderr
    assert f"UDP port {port}" in err and "--api-port" in err
    assert not (tmp_path / "run").exists()  # refused before anything started


def test_sitl_on_a_source_port_in_use_is_one_line_naming_the_flag():
    sock, port = _held_port()
    with sock:
        r = _uavsearch("sitl", "--api-local-port", port, "--no-camera-scene", "--no-ulog", "--duration", "0.2")
    err = r.stderr.strip()
    assert r.returncode == 2 and "\n" not in err and "Traceback" not in err, r.stdout + r.stderr
    assert f"{port} (--api-local-port)" in err


def test_sitl_source_ports_follow_moved_links():
    sock, port = _held_port()
    sock.close()  # a free pair of remote ports: nobody needs to listen for the vehicle to send
    r = _uavsearch("sitl", "--api-port", port, "--gcs-port", port + 1 if port < 65535 else port - 1,
                   "--no-camera-scene", "--no-ulog", "--duration", "0.2")
    assert r.returncode == 0, r.stdout + r.stderr
    links = [ln for ln in r.stdout.splitlines() if " link  sends to udp" in ln]
    assert len(links) == 2 and not any(f"from 127.0.0.1:{p} " in ln for ln in links for p in (14580, 18570)), links
