"""Step responses of the simulated quadrotor (simulated time): climb 0 -> 70 m, four 10 m moves at 70 m,
hover hold under sensor noise, landing, and the EKF's error over the whole flight.

    python tools/flight_step_response.py [--seeds 0 1 2] [--alt 70] [--png runs/flight_step_response.png]

Prints one table (a column per seed) and writes a PNG of the first seed's flight.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from uavsearch.flight.step_response import SETTLE_POS_M, SETTLE_SPEED_M_S, mission_profile

ROWS = [
    ("climb_time_to_90pct_s", "climb 0->alt: time to 90 % [s]"),
    ("climb_settle_s", "climb: settle within 0.5 m [s]"),
    ("climb_overshoot_m", "climb: overshoot [m]"),
    ("hover_err_h_rms_m", "hover hold: horizontal error RMS (truth) [m]"),
    ("hover_err_h_max_m", "hover hold: horizontal error max (truth) [m]"),
    ("hover_err_v_rms_m", "hover hold: vertical error RMS (truth) [m]"),
    ("hover_err_h_rms_est_m", "hover hold: horizontal error RMS (estimate) [m]"),
    ("move_settle_est_s", "10 m move: settle, estimate [s] (N,E,S,W)"),
    ("move_settle_s", "10 m move: settle, truth [s] (N,E,S,W)"),
    ("move_overshoot_est_m", "10 m move: overshoot, estimate [m]"),
    ("move_overshoot_m", "10 m move: overshoot, truth [m]"),
    ("touchdown_speed_m_s", "landing: touchdown speed [m/s]"),
    ("land_detect_s", "landing: descent from 5 m to land detected [s]"),
    ("ekf_pos_err_h_rms_m", "EKF horizontal position error RMS [m]"),
    ("ekf_pos_err_h_max_m", "EKF horizontal position error max [m]"),
    ("ekf_pos_err_v_rms_m", "EKF vertical position error RMS [m]"),
    ("ekf_pos_err_v_max_m", "EKF vertical position error max [m]"),
    ("ekf_vel_err_rms_m_s", "EKF velocity error RMS [m/s]"),
    ("ekf_tilt_err_rms_deg", "EKF tilt error RMS [deg]"),
    ("ekf_yaw_err_rms_deg", "EKF yaw error RMS [deg]"),
    ("battery_used_mah", "battery used [mAh]"),
    ("sim_time_s", "simulated time [s]"),
    ("wall_s", "wall time [s]"),
]


def _fmt(v) -> str:
    if isinstance(v, (list, tuple)):
        return " ".join(_fmt(x) for x in v)
    if isinstance(v, float) and math.isinf(v):
        return "never"
    return f"{v:.2f}"


def plot(flight, seed: int, alt_m: float, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    a = flight.trace.arrays()
    t = a["t"]
    fig, ax = plt.subplots(3, 1, figsize=(10, 10), sharex=True)
    ax[0].plot(t, -a["true_pos"][:, 2], label="altitude (truth)")
    ax[0].plot(t, -a["est_pos"][:, 2], "--", label="altitude (EKF)")
    ax[0].plot(t, -a["sp_pos"][:, 2], ":", color="k", label="setpoint")
    ax[0].set_ylabel("altitude [m]")
    ax[0].legend(loc="upper right")
    for i, name in enumerate(("north", "east")):
        ax[1].plot(t, a["true_pos"][:, i], label=f"{name} (truth)")
        ax[1].plot(t, a["est_pos"][:, i], "--", label=f"{name} (EKF)")
        ax[1].plot(t, a["sp_pos"][:, i], ":", color="k")
    ax[1].set_ylabel("position [m]")
    ax[1].legend(loc="upper right", ncol=2)
    dp = a["est_pos"] - a["true_pos"]
    ax[2].plot(t, np.hypot(dp[:, 0], dp[:, 1]), label="horizontal")
    ax[2].plot(t, np.abs(dp[:, 2]), label="vertical")
    ax[2].set_ylabel("EKF position error [m]")
    ax[2].set_xlabel("simulated time [s]")
    ax[2].legend(loc="upper right")
    fig.suptitle(f"quadx: climb to {alt_m:g} m, four 10 m moves, landing (seed {seed})")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--alt", type=float, default=70.0, help="climb altitude [m]")
    ap.add_argument("--png", type=Path, default=Path("runs/flight_step_response.png"))
    args = ap.parse_args(argv)
    results, first = [], None
    for seed in tqdm(args.seeds, desc="flights", unit="flight"):
        t0 = time.perf_counter()
        res, flight = mission_profile(seed=seed, alt_m=args.alt)
        res["wall_s"] = time.perf_counter() - t0
        results.append(res)
        first = first or flight
    plot(first, args.seeds[0], args.alt, args.png)
    w = max(len(label) for _, label in ROWS)
    print(f"\nsettle = within {SETTLE_POS_M} m of the target and below {SETTLE_SPEED_M_S} m/s for good")
    print(f"{'':{w}}  " + "  ".join(f"seed {s:<22d}" for s in args.seeds))
    for key, label in ROWS:
        print(f"{label:{w}}  " + "  ".join(f"{_fmt(r[key]):27s}" for r in results))
    print(f"\nplot: {args.png}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
