"""The MAVLink section of tools/bench_flight.py: the whole vehicle as a MAVLink system.

    python tools/bench_mavlink.py [--seconds 60]      (or python tools/bench_flight.py for every section)

- real-time factor of the whole vehicle (Multicopter + commander/navigator + camera + MAVLink streams on
  two links) hovering, in process, `--speed max`;
- COMMAND_LONG -> COMMAND_ACK latency seen by a pymavlink client against a `uavsearch sitl` process,
  at --speed max and at --speed 1 (median, p90);
- wall time of takeoff to 70 m + four 10 m moves (DO_REPOSITION) + land, flown over MAVLink with
  pymavlink against `uavsearch sitl --speed max`.
"""

from __future__ import annotations

import argparse
import socket
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_table import print_table  # noqa: E402  (tools/ is on sys.path when run as a script)
from pymavlink import mavutil

from uavsearch.flight.commander import VehicleCommand
from uavsearch.flight.mavlink.wire_units import deg_to_e7
from uavsearch.flight.sitl import Sitl, SitlConfig
from uavsearch.flight.sitl_process import SitlProcess
from uavsearch.geometry import GeodeticOrigin
from uavsearch.testing.mavlink_client import NAN, Client

M = mavutil.mavlink


def _hover_rtf(seconds: float, links: bool, ulog: bool = True) -> tuple[float, float, int]:
    """(wall RTF, CPU RTF, packets sent) of the in-process vehicle hovering at 20 m (writing its flight.ulg, or not)."""
    sinks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(2)]
    for s in sinks:
        s.bind(("127.0.0.1", 0))
    with tempfile.TemporaryDirectory() as tmp:
        ports = [s.getsockname()[1] for s in sinks] if links else [0, 0]
        cfg = SitlConfig(scene_seed=None, speed=float("inf"), api_port=ports[0], gcs_port=ports[1], api_local_port=0,
                         gcs_local_port=0, run_dir=Path(tmp), params={"MIS_TAKEOFF_ALT": 20.0}, ulog=ulog)
        sitl = Sitl(cfg)
        sitl.run(1.0)
        sitl.commander.handle_command(VehicleCommand(400, 1.0))
        sitl.commander.handle_command(VehicleCommand(22))
        sitl.run(15.0)
        w0, c0 = time.perf_counter(), time.process_time()
        sitl.run(seconds)
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        tx = sum(link.tx_packets for link in sitl.endpoint.links)
        sitl.close()
    for s in sinks:
        s.close()
    return seconds / wall, seconds / cpu, tx


def _rtf_in_process(seconds: float) -> list[tuple[str, float, str]]:
    w0, c0, _ = _hover_rtf(seconds, links=False)
    w1, c1, _ = _hover_rtf(seconds, links=False, ulog=False)
    w2, c2, tx = _hover_rtf(seconds, links=True)
    return [
        ("vehicle + autopilot, no MAVLink links, hover: real-time factor (wall)", w0, "x"),
        ("vehicle + autopilot, no MAVLink links, hover: real-time factor (CPU)", c0, "x"),
        ("vehicle + autopilot, no links, no flight.ulg (--no-ulog), hover: real-time factor (CPU)", c1, "x"),
        ("flight.ulg: cost per simulated second (CPU)", (1.0 / c0 - 1.0 / c1) * 1e3, "ms"),
        ("whole vehicle + MAVLink (2 links), hover: real-time factor (wall)", w2, "x"),
        ("whole vehicle + MAVLink (2 links), hover: real-time factor (CPU)", c2, "x"),
        ("whole vehicle + MAVLink: messages sent per simulated second", tx / (seconds + 16.0), "msg"),
    ]


def _ack_latency(speed: str, n: int = 200) -> tuple[float, float]:
    with tempfile.TemporaryDirectory() as tmp:
        p = SitlProcess(Path(tmp), speed=speed, camera=False)
        try:
            c = Client(p.gcs_port)
            lat = []
            for _ in range(n):
                t0 = time.perf_counter()
                ack = c.command(M.MAV_CMD_DO_SET_MODE, 1, 4, 3)  # to Hold: a command the commander handles
                if ack is not None:
                    lat.append(time.perf_counter() - t0)
            c.close()
        finally:
            p.stop()
    a = np.array(lat) * 1e3
    return float(np.median(a)), float(np.percentile(a, 90))


def _episode() -> tuple[float, float, bool]:
    """Takeoff 70 m + four 10 m moves + land over MAVLink at --speed max: (sim s, wall s, landed)."""
    origin = GeodeticOrigin()
    with tempfile.TemporaryDirectory() as tmp:
        p = SitlProcess(Path(tmp), speed="max", camera=False)
        try:
            c = Client(p.gcs_port)
            c.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 50_000)
            t_sim0 = c.recv("LOCAL_POSITION_NED").time_boot_ms
            w0 = time.perf_counter()
            assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == 0
            assert c.command(M.MAV_CMD_NAV_TAKEOFF, NAN, NAN, NAN, NAN, NAN, NAN, origin.alt_m + 70.0).result == 0
            c.recv("LOCAL_POSITION_NED", timeout=120, cond=lambda m: m.z < -69.5)
            pos = np.zeros(2)
            for d in ((1, 0), (0, 1), (-1, 0), (0, -1)):
                pos = pos + 10.0 * np.array(d)
                lla = origin.enu_to_geodetic([pos[1], pos[0], 0.0])
                c.mav.command_int_send(1, 1, M.MAV_FRAME_GLOBAL_INT, M.MAV_CMD_DO_REPOSITION, 0, 0, -1, 1, 0, NAN,
                                       deg_to_e7(lla[0]), deg_to_e7(lla[1]), origin.alt_m + 70.0)
                c.recv("LOCAL_POSITION_NED", timeout=60, cond=lambda m: np.hypot(m.x - pos[0], m.y - pos[1]) < 0.5
                       and np.hypot(m.vx, m.vy) < 0.3)
            c.command(M.MAV_CMD_NAV_LAND)
            hb = None
            deadline = time.perf_counter() + 120
            while time.perf_counter() < deadline:
                hb = c.wait_heartbeat(1.0)
                if hb is not None and not hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED:
                    break
            wall = time.perf_counter() - w0
            t_sim1 = c.recv("LOCAL_POSITION_NED").time_boot_ms
            c.close()
        finally:
            p.stop()
    return (t_sim1 - t_sim0) / 1e3, wall, hb is not None and not hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED


def bench_mavlink(seconds: float = 60.0) -> list[tuple[str, float, str]]:
    rows = _rtf_in_process(seconds)
    for speed in ("max", "1"):
        med, p90 = _ack_latency(speed)
        rows += [
            (f"COMMAND_LONG -> ACK (pymavlink, sitl --speed {speed}): median", med, "ms"),
            (f"COMMAND_LONG -> ACK (pymavlink, sitl --speed {speed}): p90", p90, "ms"),
        ]
    sim_s, wall_s, landed = _episode()
    rows += [
        ("MAVLink episode (takeoff 70 m, 4 x 10 m, land; --speed max): simulated", sim_s, "s"),
        ("MAVLink episode: wall time", wall_s, "s"),
        ("MAVLink episode: real-time factor", sim_s / wall_s, "x"),
        ("MAVLink episode: landed and disarmed", float(landed), "bool"),
    ]
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=60.0, help="simulated seconds of the hover measurement")
    args = ap.parse_args(argv)
    print_table(bench_mavlink(args.seconds))
    return 0


if __name__ == "__main__":
    sys.exit(main())
