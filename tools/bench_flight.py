"""Flight-stack speed, one core, as fast as it runs (simulated seconds per wall second = real-time factor).

    python tools/bench_flight.py [--seconds 60]

Sections: `bench_fdm()` (JSBSim alone; the whole Multicopter: sensors, EKF, control; a takeoff + four
10 m moves + landing flown on the Multicopter without MAVLink) and `bench_mavlink()` from bench_mavlink.py
(the whole vehicle with MAVLink streams, command latency). Each returns rows (name, value, unit).
CPU time is reported beside wall time because the machine is shared: the CPU figure is the cost.
Every real-time factor is also printed as a fraction of bare JSBSim's, measured in the same run (wall
against wall, CPU against CPU): the limit a flight stack on this FDM cannot pass. The load average is
printed with the table.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np
from tqdm import tqdm

from uavsearch.flight.fdm import QuadFdm
from uavsearch.flight.messages import TrajectorySetpoint
from uavsearch.flight.multicopter import MC_PARAMS, Multicopter
from uavsearch.flight.params import ParamStore
from uavsearch.flight.step_response import Flight
from uavsearch.geometry import GeodeticOrigin

from bench_mavlink import bench_mavlink  # the MAVLink section; tools/ is on sys.path when run as a script
from bench_table import print_table, timed


def bench_fdm(seconds: float = 60.0, physics_hz: int = 100) -> list[tuple[str, float, str]]:
    rows = []
    # JSBSim alone: the airframe at hover thrust, commands written every step as the controller would
    fdm = QuadFdm(GeodeticOrigin(), physics_hz, start_enu=(0.0, 0.0, 20.0))
    n = int(seconds * physics_hz)
    cmd = [0.49] * 4

    def run_fdm():
        for _ in range(n):
            fdm.set_motor_commands(cmd)
            fdm.step()

    wall, cpu = timed(run_fdm)
    rows += [
        (f"JSBSim alone, {physics_hz} Hz: real-time factor (wall)", seconds / wall, "x"),
        (f"JSBSim alone, {physics_hz} Hz: real-time factor (CPU)", seconds / cpu, "x"),
        ("JSBSim alone: per physics step (CPU)", cpu / n * 1e6, "us"),
    ]
    # the whole Multicopter hovering with noise (sensors + EKF + cascade + JSBSim)
    v = Multicopter(ParamStore(MC_PARAMS), GeodeticOrigin(), seed=0)
    v.arm()
    v.set_setpoint(TrajectorySetpoint(0, np.array([0.0, 0.0, -20.0]), yaw_rad=0.0))
    v.run_for(10.0)
    wall, cpu = timed(lambda: v.run_for(seconds))
    rows += [
        (f"Multicopter.step, {v.physics_hz}/{v.ctrl_hz}/{v.ekf_hz} Hz: real-time factor (wall)", seconds / wall, "x"),
        ("Multicopter.step: real-time factor (CPU)", seconds / cpu, "x"),
        ("Multicopter.step: per simulated second (CPU)", cpu / seconds * 1e3, "ms"),
    ]

    # takeoff to 70 m + four 10 m moves + landing, no MAVLink (the flight-time floor of an episode)
    def episode():
        f = Flight(seed=0, sample_hz=10)
        f.vehicle.arm()
        f.goto(0.0, 0.0, -70.0)
        f.run(40.0, until=lambda veh: veh.local_position.position_ned_m[2] < -69.5)
        pos = np.zeros(2)
        for d in ((1, 0), (0, 1), (-1, 0), (0, -1)):
            pos = pos + 10.0 * np.array(d)
            f.goto(pos[0], pos[1], -70.0)
            f.run(15.0, until=lambda veh: np.hypot(*(veh.local_position.position_ned_m[:2] - pos)) < 0.5
                  and np.hypot(*veh.local_position.velocity_ned_m_s[:2]) < 0.3)
        f.descend(0.0, 0.0, 1.5)
        f.run(80.0, until=lambda veh: -veh.local_position.position_ned_m[2] < 5.0)
        f.descend(0.0, 0.0, 0.7)
        f.run(30.0, until=lambda veh: veh.land_detected.landed)
        episode.sim_s = f.vehicle.time_us / 1e6
        episode.landed = f.vehicle.land_detected.landed

    wall, cpu = timed(episode)
    rows += [
        ("episode (takeoff 70 m, 4 x 10 m, land): simulated time", episode.sim_s, "s"),
        ("episode: wall time", wall, "s"),
        ("episode: CPU time", cpu, "s"),
        ("episode: landed", float(episode.landed), "bool"),
    ]
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seconds", type=float, default=60.0, help="simulated seconds per speed measurement")
    args = ap.parse_args(argv)
    sections = [("JSBSim / Multicopter", lambda: bench_fdm(args.seconds)),
                ("MAVLink vehicle", lambda: bench_mavlink(args.seconds))]
    load0 = os.getloadavg()[0]
    rows = []
    for _name, fn in tqdm(sections, desc="bench", unit="section"):
        rows += fn()
    print(f"load average {load0:.2f} at start, {os.getloadavg()[0]:.2f} at end ({os.cpu_count()} CPUs)")
    print_table(against_bare_jsbsim(rows))
    return 0


def against_bare_jsbsim(rows):
    """Each real-time factor with its fraction of bare JSBSim's (the first 'JSBSim alone' rows)."""
    bare = {kind: v for name, v, unit in rows if name.startswith("JSBSim alone") and unit == "x"
            for kind in ("CPU", "wall") if name.endswith(f"({kind})")}
    out = []
    for name, v, unit in rows:
        kind = "CPU" if name.endswith("(CPU)") else "wall"
        ratio = v / bare[kind] if unit == "x" and kind in bare and not name.startswith("JSBSim alone") else None
        out.append((name, v, unit, ratio, f"of bare JSBSim ({kind})"))
    return out


if __name__ == "__main__":
    sys.exit(main())
