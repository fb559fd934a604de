"""Wall time of flown search missions: `uavsearch fly` end to end (vehicle process start, take-off, T views,
landing) at a speed factor, over a few scenes. Prints one row per flight and the mean.

    python tools/bench_fly.py [--mission missions/default.yaml] [--scenes 3 4 5] [--speed max] [--T 5]

Columns: start = `uavsearch sitl` process start until ready (scene build included); flight = link up ->
landed and disarmed (wall); sim = the vehicle's clock over the same span; views = captures taken; the
search's own per-step wall time (goto + settle + photo + perception + fusion + policy) is in `per view`.
"""

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from uavsearch.missions import load_mission  # noqa: E402
from uavsearch.search.mission_controller import fly  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mission", default=None, help="mission file (default missions/default.yaml)")
    ap.add_argument("--scenes", type=int, nargs="+", default=[3, 4, 5], help="scene seeds (default 3 4 5)")
    ap.add_argument("--speed", default="max", help="speed factor: max (default) or N")
    ap.add_argument("--T", type=int, default=None, help="override the mission's budget T")
    ap.add_argument("--perception", default=None, help="override the mission's perception checkpoint")
    ap.add_argument("--fusion", default=None, help="override the mission's fusion")
    ap.add_argument("--policy", default=None, help="override the mission's policy")
    ap.add_argument("--free-running", action="store_true",
                    help="vehicle without lockstep (not reproducible; shows what lockstep costs)")
    args = ap.parse_args()
    base = load_mission(args.mission).with_overrides(**{
        "flight.speed": args.speed if args.speed == "max" else float(args.speed), "search.budget_T": args.T,
        "perception": args.perception, "fusion": args.fusion, "policy": args.policy,
        "flight.lockstep": False if args.free_running else None})
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in tqdm(args.scenes, desc="flying", file=sys.stderr):
            m = base.with_overrides(**{"scene.seed": seed})
            t0 = time.monotonic()
            r = fly(m, out=Path(tmp) / f"run{seed}", progress=lambda s: None, gcs_port=0)
            total = time.monotonic() - t0
            per_view = [s for s in _step_walls(Path(tmp) / f"run{seed}")]
            rows.append(dict(scene=seed, status=r.status.split(":")[0], views=r.steps, start=r.wall_s - r.flight_wall_s,
                             flight=r.flight_wall_s, sim=r.sim_time_s or float("nan"), total=total,
                             per_view=statistics.mean(per_view) if per_view else float("nan"),
                             acc=r.acc if r.acc is not None else float("nan"), f1=r.f1 if r.f1 is not None else float("nan")))
    print(f"\nflown missions: {base.name}, T = {base.search.budget_T}, speed {base.flight.speed}, "
          f"{base.fusion} fusion + {base.policy} policy")
    hdr = f"{'scene':>5} {'status':>9} {'views':>5} {'start s':>8} {'flight s':>9} {'sim s':>7} {'total s':>8} " \
          f"{'per view s':>10} {'acc':>6} {'F1':>6}"
    print(hdr)
    print("-" * len(hdr))
    for r in rows:
        print(f"{r['scene']:>5} {r['status']:>9} {r['views']:>5} {r['start']:8.1f} {r['flight']:9.1f} {r['sim']:7.1f} "
              f"{r['total']:8.1f} {r['per_view']:10.2f} {r['acc']:6.3f} {r['f1']:6.3f}")
    mean = {k: statistics.mean(r[k] for r in rows) for k in ("start", "flight", "sim", "total", "per_view")}
    print(f"{'mean':>5} {'':>9} {'':>5} {mean['start']:8.1f} {mean['flight']:9.1f} {mean['sim']:7.1f} "
          f"{mean['total']:8.1f} {mean['per_view']:10.2f}")
    return 0


def _step_walls(run_dir: Path):
    import json

    for line in (run_dir / "search.jsonl").read_text().splitlines():
        rec = json.loads(line)
        if rec.get("type") == "step":
            yield rec["wall_s"]


if __name__ == "__main__":
    sys.exit(main())
