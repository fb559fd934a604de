"""Flown teams against teleport: the wide mission (missions/wide.yaml: 3 vehicles, 80 s) flown over MAVLink on the
first K wide test scenes, each beside `run_team` on the same scene's cached views (the same planner, fusion and
perception): final AF1, views, how many viewpoints both visited, and each flight's wall and simulated time at
--speed max. Prints the table and writes it (markdown).

    python tools/team_flights.py --scenes 5 --out results/team_wide/flights.md
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from uavsearch.fly.missions import load_mission
from uavsearch.fly.team_controller import fly_team
from uavsearch.logs.flight_log import read_flight_log
from uavsearch.paths import MISSIONS_DIR
from uavsearch.search.data.view_cache import get_view_cache
from uavsearch.search.evaluate.team import make_planner
from uavsearch.search.fusion import make_fusion
from uavsearch.search.metrics import map_f1
from uavsearch.search.perception import load_perception
from uavsearch.search.search_loop import CachedViews
from uavsearch.search.team import run_team
from uavsearch.world.settings import scene_seeds, setting_params


def teleport(cache, row: int, mission, config) -> tuple[float, list[int]]:
    """(final AF1, viewpoints in the order taken) of the team in teleport mode on one cached scene."""
    n, t = mission.vehicles, float(config.budget_s)
    ep = run_team(CachedViews(cache, [row], config), make_fusion(mission.fusion), make_planner(mission.policy, config),
                  n, t)
    f1 = float(map_f1(ep.map_at(t).numpy(), cache.occupancy[[row]].numpy())[0])
    return f1, ep.lattice_idx[0, ep.taken[0]].tolist()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mission", default=str(MISSIONS_DIR / "wide.yaml"))
    ap.add_argument("--scenes", type=int, default=5, help="the first K wide test scenes (default 5)")
    ap.add_argument("--out", type=Path, default=None, help="markdown table to write")
    args = ap.parse_args()
    mission = load_mission(args.mission)
    config = mission.search_config()
    seeds = scene_seeds(mission.family, part="test")[: args.scenes]
    net, _ = load_perception(mission.perception_path)
    cache = get_view_cache(net, mission.family, setting_params(mission.family).split, "test", features=False,
                           limit=args.scenes, progress=False)
    torch.set_num_threads(1)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, seed in enumerate(tqdm(seeds, desc="team flights", unit="flight")):
            m = mission.with_overrides(**{"scene.seed": seed})
            t0 = time.monotonic()
            r = fly_team(m, out=Path(tmp) / f"run{seed}", progress=lambda line: None, gcs_port=0)
            wall = time.monotonic() - t0
            flown = [s.lattice_idx for s in read_flight_log(r.run_dir).steps]
            tf1, tele = teleport(cache, i, mission, config)
            same = next((k for k, (a, b) in enumerate(zip(flown, tele)) if a != b), min(len(flown), len(tele)))
            rows.append(dict(seed=seed, status=r.status, f1=r.f1 or 0.0, tf1=tf1, views=len(flown), tviews=len(tele),
                             common=len(set(flown) & set(tele)), same_prefix=same, wall=wall,
                             sim=r.sim_time_s or float("nan")))
    d = np.array([r["f1"] - r["tf1"] for r in rows])
    lines = [f"# Flown teams against teleport ({mission.name}: {mission.vehicles} vehicles, {config.budget_s:g} s, "
             f"{mission.policy} planner, {mission.fusion} fusion)", "",
             f"The first {len(rows)} {mission.family} test scenes, flown at --speed {mission.flight.speed} in lockstep "
             "(vehicle seed 0) against `run_team` on the cached views. Regenerate: "
             "`python tools/team_flights.py --scenes 5 --out results/team_wide/flights.md`.", "",
             "| scene | status | flown AF1 | teleport AF1 | views flown / teleport | viewpoints in common | same "
             "first views | wall (s) | simulated (s) |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['seed']} | {r['status']} | {r['f1']:.3f} | {r['tf1']:.3f} | {r['views']} / {r['tviews']} | "
                     f"{r['common']} | {r['same_prefix']} | {r['wall']:.1f} | {r['sim']:.1f} |")
    lines += ["", f"Mean flown − teleport AF1: {d.mean():+.3f} (max |Δ| {np.abs(d).max():.3f}); mean wall time per "
              f"flown mission {np.mean([r['wall'] for r in rows]):.1f} s (start, take-off, search, landing)."]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)
    return 0 if all(r["status"] == "completed" for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
