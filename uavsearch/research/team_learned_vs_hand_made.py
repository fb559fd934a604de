"""What the learned aggregation adds to a team: the team table's choices with it among the candidate fusions
against the hand-made table's, paired per scene.

Per team size and mission time, the team planner and fusion each table chose on the validation scenes (the
rows marked team_planner in its team.csv) fly the same test scenes again (search/evaluate/team.team_scores,
deterministic: the tables' own AF1 comes back); the difference of each scene's final AF1 gets a 95% bootstrap
interval over the scenes. Nothing is chosen here.

    python tools/team_learned_vs_hand_made.py --out results/team_wide/learned_vs_hand_made.md
"""

from __future__ import annotations

import argparse
import csv
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..errors import UavsearchError, run_command
from ..paths import display_path
from ..search.evaluate.team import TeamEvalArgs, team_scores
from ..search.evaluate.wide import family_caches
from ..search.metrics import RESAMPLES, bootstrap_ci
from .wide_policy_probes import write_markdown


def team_choices(path: Path) -> dict[tuple[int, float], tuple[str, str, float]]:
    """{(vehicles, time_s): (planner spec, fusion, test AF1)} of a team table's team planners."""
    if not path.is_file():
        raise UavsearchError(f"{path} not found (uavsearch eval team writes it)")
    rows = [r for r in csv.DictReader(path.open()) if r.get("team_planner") == "True"]
    if not rows:
        raise UavsearchError(f"{path} has no team planner rows (is it a team.csv of uavsearch eval team?)")
    return {(int(r["vehicles"]), float(r["time_s"])): (r["planner"], r["fusion"], float(r["af1"])) for r in rows}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python tools/team_learned_vs_hand_made.py", description=__doc__.split("\n")[0])
    ap.add_argument("--learned", default="results/team_wide/team.csv", help="the table with the learned aggregation")
    ap.add_argument("--hand-made", default="results/team_wide/hand_made/team.csv", help="the hand-made table")
    ap.add_argument("--setting", default="wide")
    ap.add_argument("--out", default="results/team_wide/learned_vs_hand_made.md")
    ap.add_argument("--bootstrap", type=int, default=RESAMPLES)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    learned, hand = team_choices(Path(args.learned)), team_choices(Path(args.hand_made))
    conds = sorted(set(learned) & set(hand))
    if not conds:
        raise UavsearchError("the two tables share no (team size, mission time)")
    test = family_caches(TeamEvalArgs(out=".", setting=args.setting, progress=False), args.setting)["test"]
    lines = [f"# What the learned aggregation adds to a team ({args.setting}, {test.num_scenes} test scenes)", "",
             f"Team planner and fusion as each table chose them on validation ({display_path(Path(args.learned))} "
             f"against {display_path(Path(args.hand_made))}), both flown again on the same {test.num_scenes} test "
             f"scenes. Δ: per-scene final AF1, learned minus hand-made, mean [95% bootstrap interval over scenes, "
             f"{args.bootstrap} resamples]. `python tools/team_learned_vs_hand_made.py --out {args.out}`", "",
             "| vehicles | mission time | hand-made: planner, fusion | AF1 | learned: planner, fusion | AF1 | Δ [95% CI] |",
             "|---|---|---|---|---|---|---|"]
    for v, t in tqdm(conds, desc="conditions", unit="cond"):
        f1 = {}
        for name, table in (("hand", hand), ("learned", learned)):
            spec, fusion, want = table[(v, t)]
            f1[name] = team_scores(test, spec, fusion, v, t)["f1"]
            if abs(float(f1[name].mean()) - want) > 1e-6:
                raise UavsearchError(f"{spec} with {fusion} at {v} vehicles, {t:g} s: AF1 {f1[name].mean():.4f}, "
                                     f"not its table's {want:.4f} (other caches or perception?)")
        m, lo, hi = bootstrap_ci(f1["learned"] - f1["hand"], args.bootstrap, 0)
        lines.append(f"| {v} | {t:g} s | {hand[(v, t)][0]}, {hand[(v, t)][1]} | {f1['hand'].mean():.3f} | "
                     f"{learned[(v, t)][0]}, {learned[(v, t)][1]} | {f1['learned'].mean():.3f} | "
                     f"{m:+.3f} [{lo:+.3f}, {hi:+.3f}] |")
    lines += ["", f"{time.perf_counter() - t0:.0f} s."]
    write_markdown(args.out, lines)
    return 0


def cli() -> int:
    """The command line: bad input is one line and exit 2."""
    return run_command(main, None, "team_learned_vs_hand_made.py")
