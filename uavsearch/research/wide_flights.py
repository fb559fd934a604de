"""Flown wide-area missions against teleport: a scene family's mission (default missions/wide.yaml, the learned
wide-area policy on one vehicle for 240 s; missions/wide_team.yaml: a team of 3 for 80 s) flown over MAVLink on
the first K test scenes of its family, each beside `run_team` on the same scene's cached views (the same policy
or planner, fusion and perception): final AF1, views, the routes compared (viewpoints in common, how many first
views agree, views at 40 m), and each flight's wall and simulated time at --speed max. Prints the table and
writes it (markdown) with the per-scene rows as JSON beside it.

    python tools/wide_flights.py --scenes 10 --out results/map_policy/flights.md
    python tools/wide_flights.py --mission missions/wide_team.yaml --scenes 5 --out results/team_wide/flights.md
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from ..fly.mission_controller import fly
from ..fly.missions import load_mission
from ..logs.flight_log import read_flight_log
from ..paths import MISSIONS_DIR, display_path
from ..search.metrics import bootstrap_ci
from ..search.data.view_cache import get_view_cache
from ..search.metrics import map_f1
from ..search.perception import load_perception
from ..search.search_loop import CachedViews
from ..search.team import run_team
from ..world.settings import scene_seeds, setting_params


def teleport(cache, row: int, mission, config) -> tuple[float, list[int]]:
    """(final AF1, viewpoints in the order taken) of the mission in teleport mode on one cached scene."""
    method = mission.team_method(config)
    t = float(config.budget_s)
    ep = run_team(CachedViews(cache, [row], config), method.fusion, method.planner, mission.vehicles, t,
                  max_views=mission.team.max_views if mission.team is not None else None)
    f1 = float(map_f1(ep.map_at(t).numpy(), cache.occupancy[[row]].numpy())[0])
    return f1, ep.lattice_idx[0, ep.taken[0]].tolist()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mission", default=str(MISSIONS_DIR / "wide.yaml"))
    ap.add_argument("--scenes", type=int, default=10, help="the first K test scenes of the family (default 10)")
    ap.add_argument("--out", type=Path, default=None, help="markdown table to write")
    args = ap.parse_args()
    mission = load_mission(args.mission)
    config = mission.search_config()
    seeds = scene_seeds(mission.family, part="test")[: args.scenes]
    net, _ = load_perception(mission.perception_path)
    cache = get_view_cache(net, mission.family, setting_params(mission.family).split, "test", features=False,
                           limit=args.scenes, progress=False)
    torch.set_num_threads(1)
    low = config.lattice.positions_enu[:, 2] < config.lattice.positions_enu[:, 2].max() - 1.0
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, seed in enumerate(tqdm(seeds, desc=f"{mission.name} flights", unit="flight")):
            m = mission.with_overrides(**{"scene.seed": seed})
            r = fly(m, out=Path(tmp) / f"run{seed}", progress=lambda line: None, gcs_port=0)
            flown = [s.lattice_idx for s in read_flight_log(r.run_dir).steps]
            mission_s = json.loads((r.run_dir / "summary.json").read_text()).get("mission_time_s") or float("nan")
            tf1, tele = teleport(cache, i, mission, config)
            same = next((k for k, (a, b) in enumerate(zip(flown, tele)) if a != b), min(len(flown), len(tele)))
            rows.append(dict(seed=int(seed), status=r.status, f1=r.f1 or 0.0, tf1=tf1, views=len(flown),
                             tviews=len(tele), low=int(low[flown].sum()), tlow=int(low[tele].sum()),
                             common=len(set(flown) & set(tele)), same_prefix=same, wall=r.wall_s,
                             flight_wall=r.flight_wall_s, sim=r.sim_time_s or float("nan"), mission_s=mission_s,
                             flown=flown, teleport=tele))
    d = np.array([r["f1"] - r["tf1"] for r in rows])
    mean, lo, hi = bootstrap_ci(d)
    method = mission.team_method(config).description
    cmd = f"python tools/wide_flights.py --mission {display_path(Path(args.mission))} --scenes {args.scenes}" + \
        (f" --out {display_path(args.out)}" if args.out else "")
    budget = f"{config.budget_s:g} s" + (f", at most {mission.team.max_views} views" if mission.team and
                                          mission.team.max_views else "")
    lines = [f"# Flown against teleport: {mission.name} ({mission.vehicles} vehicle{'s' if mission.vehicles > 1 else ''}, "
             f"{budget}, {method})", "",
             f"The first {len(rows)} {mission.family} test scenes, flown over MAVLink at --speed {mission.flight.speed} "
             "in lockstep (vehicle seed 0) against `run_team` on the same scenes' cached views (teleport: the "
             "nominal poses, the lattice's flight times). Mission time flown: the last view's time since the start "
             "view on the vehicle's clock, which the flight counts its budget in (simulated: the whole flight, "
             f"take-off and landing included). Regenerate: `{cmd}`.", "",
             "| scene | status | flown AF1 | teleport AF1 | views flown / teleport | of them at 40 m | viewpoints in "
             "common | same first views | mission time flown (s) | wall (s) | of it flying (s) | simulated (s) |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['seed']} | {r['status']} | {r['f1']:.3f} | {r['tf1']:.3f} | {r['views']} / {r['tviews']} | "
                     f"{r['low']} / {r['tlow']} | {r['common']} | {r['same_prefix']} | {r['mission_s']:.1f} | "
                     f"{r['wall']:.1f} | "
                     f"{r['flight_wall']:.1f} | {r['sim']:.1f} |")
    walls = np.array([r["wall"] for r in rows])
    lines += ["", f"Flown AF1 {np.mean([r['f1'] for r in rows]):.3f}, teleport {np.mean([r['tf1'] for r in rows]):.3f}: "
              f"flown − teleport **{mean:+.3f} [{lo:+.3f}, {hi:+.3f}]** (95% bootstrap interval over scenes; max |Δ| "
              f"{np.abs(d).max():.3f}). Same route in both modes: {sum(r['flown'] == r['teleport'] for r in rows)}/"
              f"{len(rows)} scenes. Wall time per flown mission (vehicle start, take-off, search, landing): mean "
              f"{walls.mean():.1f} s, max {walls.max():.1f} s."]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)
        args.out.with_suffix(".json").write_text(json.dumps(dict(mission=display_path(Path(args.mission)),
                                                                 flown_minus_teleport=[mean, lo, hi], rows=rows),
                                                            indent=1) + "\n")
    return 0 if all(r["status"] == "completed" for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
