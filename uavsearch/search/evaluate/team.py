"""The team table: AF1 against mission time for teams of 1, 2 and 3 vehicles on a scene family's test scenes.

Every team searches one shared map (search/team.py: `run_team`, the same planner `fly --vehicles N` flies).
A condition is (team size, mission time); for each, every planner row gets its fusion chosen on the validation
scenes (TEAM_FUSIONS, by mean AF1), and "the team planner" is the planner row with the best validation AF1
(the rule, the rule per second of flight, the fixed partition, entropy per second, or entropy per second with
the cells other vehicles are about to see discounted, its discount chosen with the fusion). Test
AF1 is the final map's, per scene; differences are paired per scene with a 95% scene-bootstrap interval against
one vehicle's team planner at the longest mission time (the question a team answers: as good, sooner?).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from uavsearch.cli_args import add_dataclass_args, dataclass_from_args, opt
from uavsearch.devices import resolve_device, to_device
from uavsearch.errors import UavsearchError, run_command
from uavsearch.parallel import ScaleOutArgs
from uavsearch.paths import display_path
from uavsearch.viz import pyplot, save_figure

from ..agents import PLANNERS, make_fusion, make_planner
from ..data.view_cache import ViewCache
from ..map_policy import BUDGETS
from ..metrics import map_f1
from ..search_loop import CachedViews
from ..team import run_team
from ..metrics import RESAMPLES, bootstrap_ci
from .tables import write_csv
from .wide import FUSION_CANDIDATES, family_caches

CHOSEN = tuple(PLANNERS)  # what "the team planner" is chosen among on validation
# The hand-made candidates: Table III's and two higher Bayes priors (with many views per map validation's best
# prior sat at Table III's highest, 0.5), less the three lowest priors, which no row chose on validation in a search
# over all eight (100 test / 50 validation wide scenes): their runs pay for the learned candidate's
TEAM_FUSIONS = tuple(f for f in (*FUSION_CANDIDATES, "bayes:0.6", "bayes:0.7")
                     if f not in ("bayes:0.05", "bayes:0.1", "bayes:0.2"))
# The shipped learned stacks whose aggregation (search/neighbour_fusion.py) is a candidate too, by budget: the
# 240 s stack's; on the 50 validation scenes (team_entropy:1; 1 and 3 vehicles at 240 s, 2 at 80 s) it led the
# T = 8 stack's by +0.06, +0.14, +0.03 AF1 and costs as much (`--learned 8,240` makes both candidates)
LEARNED_BUDGETS = ("240",)
# a planner's variants, chosen on validation with its fusion: team_entropy's discount of cells others will see
VARIANTS = {"team_entropy": ("team_entropy:0.5", "team_entropy:0.8", "team_entropy:1")}


def learned_aggregations(perception_tag: str, family: str = "wide", models_dir=None,
                         budgets=LEARNED_BUDGETS) -> list[str]:
    """Fusion specs of the shipped learned stacks' aggregations ("neighbour:PATH") fitted on the perception the
    caches hold (another net's features and scores mean nothing to them)."""
    from ..checkpoints import wide_checkpoint
    from ..neighbour_fusion import NeighbourFusion
    from ..policy import load_search_model

    specs = []
    for budget in budgets:
        path = wide_checkpoint(budget, models_dir, family)
        if not path.is_file():
            continue
        model = load_search_model(path, "cpu")
        if isinstance(model.fusion, NeighbourFusion) and model.extra.get("perception_tag") == perception_tag:
            specs.append(f"neighbour:{display_path(path)}")
    return specs


def team_scores(cache: ViewCache, planner: str, fusion_spec: str, vehicles: int, budget_s: float) -> dict:
    """Per-scene final AF1 and Aacc, views and flight of one team on every scene of `cache`."""
    config = dataclasses.replace(cache.config, budget_T=cache.config.lattice.num_positions)
    ep = run_team(CachedViews(cache, np.arange(cache.num_scenes), config), make_fusion(fusion_spec),
                  make_planner(planner, config), vehicles, budget_s)
    final = ep.map_at(budget_s).cpu().numpy()
    y = cache.occupancy.cpu().numpy()
    return {"f1": map_f1(final, y), "acc": ((final > 0.5) == y).mean(1), "views": ep.views().cpu().numpy()}


def choose_fusion(val: ViewCache, planner: str, vehicles: int, budget_s: float,
                  candidates=FUSION_CANDIDATES) -> tuple[str, str, float]:
    """(planner variant, fusion, validation AF1): the pair of the planner's variants (VARIANTS) and the candidate
    fusions with the best mean validation AF1 in this condition."""
    pairs = [(v, c) for v in VARIANTS.get(planner, (planner,)) for c in candidates]
    scores = {pc: float(team_scores(val, pc[0], pc[1], vehicles, budget_s)["f1"].mean()) for pc in pairs}
    best = max(pairs, key=lambda pc: (scores[pc], -pairs.index(pc)))
    return best[0], best[1], scores[best]


def evaluate_teams(caches: dict[str, ViewCache], sizes, times, resamples: int = RESAMPLES, seed: int = 0,
                   progress=print, fusions=TEAM_FUSIONS) -> dict:
    """{(size, time): {planner: {...per-scene test scores, "fusion", "val_af1"}, "chosen": planner}} and the
    paired rows against one vehicle's chosen planner at the longest time."""
    out: dict = {}
    t0 = time.perf_counter()
    for v in sizes:
        for t in times:
            cond = {}
            for key in PLANNERS:
                spec, fusion, val_af1 = choose_fusion(caches["val"], key, v, t, tuple(fusions))
                cond[key] = {**team_scores(caches["test"], spec, fusion, v, t), "fusion": fusion, "spec": spec,
                             "val_af1": val_af1}
            cond["chosen"] = max(CHOSEN, key=lambda k: (cond[k]["val_af1"], -CHOSEN.index(k)))
            out[(v, t)] = cond
            progress(f"uavsearch: team of {v}, {t:g} s: done ({time.perf_counter() - t0:.0f} s)")
    ref_key = (1, max(times))
    ref = out[ref_key][out[ref_key]["chosen"]]["f1"]
    paired = []
    for (v, t), cond in out.items():
        for key in PLANNERS:
            d = cond[key]["f1"] - ref
            m, lo, hi = bootstrap_ci(d, resamples, seed)
            paired.append({"vehicles": v, "time_s": t, "planner": cond[key]["spec"],
                           "team_planner": key == cond["chosen"],
                           "fusion": cond[key]["fusion"], "af1": float(cond[key]["f1"].mean()),
                           "reference_af1": float(ref.mean()), "diff": m, "ci_low": lo, "ci_high": hi,
                           "scenes": len(d), "resamples": resamples, "bootstrap_seed": seed})
    return {"conditions": out, "paired": paired, "reference": ref_key, "fusions": list(fusions)}


def team_figure(res: dict, sizes, times):
    """AF1 against mission time per team size (the team planner; 95% scene-bootstrap bands)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for v in sizes:
        means, lows, highs = [], [], []
        for t in times:
            cond = res["conditions"][(v, t)]
            f1 = cond[cond["chosen"]]["f1"]
            m, lo, hi = bootstrap_ci(f1, 2000, 0)
            means.append(m), lows.append(lo), highs.append(hi)
        line, = ax.plot(times, means, marker="o", label=f"{v} vehicle{'s' if v > 1 else ''}")
        ax.fill_between(times, lows, highs, color=line.get_color(), alpha=0.2)
    ref = res["conditions"][res["reference"]]
    ax.axhline(ref[ref["chosen"]]["f1"].mean(), color="gray", ls="--", lw=1,
               label=f"1 vehicle at {res['reference'][1]:g} s")
    ax.set_xlabel("mission time (simulated seconds of flight)")
    ax.set_ylabel("AF1 of the shared map")
    ax.set_title("Teams on one shared map (test scenes; team planner chosen on validation)")
    ax.grid(alpha=0.3)
    ax.legend()
    return fig


def table_lines(res: dict, sizes, times, family: str, scenes: dict) -> list[str]:
    conds, ref = res["conditions"], res["reference"]
    lines = [f"# Teams: AF1 against mission time ({family}, test scenes)", "",
             f"{scenes['test']} test scenes; each planner's fusion chosen on {scenes['val']} validation scenes per "
             f"team size and mission time among {', '.join(res.get('fusions', []))}; **bold**: the team planner "
             "(chosen on validation among "
             f"{', '.join(CHOSEN)}). Δ: per-scene AF1 minus one vehicle's team planner at {ref[1]:g} s [95% "
             "bootstrap interval over scenes]. Regenerate: `tools/reproduce.sh --only team`.", "",
             "| vehicles | planner | " + " | ".join(f"{t:g} s" for t in times) + " |",
             "|---|---|" + "---|" * len(times)]
    for v in sizes:
        for key in PLANNERS:
            cells = []
            for t in times:
                c = conds[(v, t)]
                a = f"{c[key]['f1'].mean():.3f}"
                cells.append(f"**{a}**" if c["chosen"] == key else a)
            lines.append(f"| {v} | {PLANNERS[key].description} | " + " | ".join(cells) + " |")
    lines += ["", f"Team planner against one vehicle at {ref[1]:g} s (Δ AF1 [95% CI]; fusion; views per episode):", "",
              "| vehicles | mission time | planner | fusion | AF1 | views | Δ vs 1 vehicle at "
              f"{ref[1]:g} s |", "|---|---|---|---|---|---|---|"]
    for p in res["paired"]:
        if not p["team_planner"]:
            continue
        c = conds[(p["vehicles"], p["time_s"])][p["planner"].partition(":")[0]]
        lines.append(f"| {p['vehicles']} | {p['time_s']:g} s | {p['planner']} | {p['fusion']} | {p['af1']:.3f} | "
                     f"{c['views'].mean():.1f} | {p['diff']:+.3f} [{p['ci_low']:+.3f}, {p['ci_high']:+.3f}] |")
    return lines + [""]


@dataclass
class TeamEvalArgs(ScaleOutArgs):
    setting: str = opt("wide", "scene family (wide | wide-uniform)")
    out: str = opt("results/team_wide", "output folder: team.md, team.csv, team_paired.csv, team.png", required=True)
    vehicles: str = opt("1,2,3", "team sizes, comma-separated")
    times: str = opt("40,80,120,160,240", "mission times in simulated seconds, comma-separated (the longest is the "
                                          "reference of one vehicle)")
    split: str | None = opt(None, "scene split (default: the family's own)")
    perception: str | None = opt(None, "frozen perception checkpoint (default: the family's shipped one)")
    cache_dir: str | None = opt(None, "view caches: a folder or an fsspec URL (default cache/)")
    wide_test_scenes: int | None = opt(None, "test scenes (the first N; default all 100)")
    wide_val_scenes: int | None = opt(None, "validation scenes choosing fusions and the team planner (first N; all)")
    wide_train_scenes: int = opt(1, "training scenes (unused by these planners; the cache of the first N is made)")
    fusions: str = opt(",".join(TEAM_FUSIONS), "fusions each planner's is chosen among on validation "
                                               "(comma-separated name or name:prior, or neighbour:PATH)")
    learned: str = opt(",".join(LEARNED_BUDGETS), "the shipped learned stacks (budgets, comma-separated: 8, 240; "
                                                  "or none) whose aggregation is a candidate too, where fitted on "
                                                  "the caches' perception (neighbour:models/search_wide_*_map.pt)")
    bootstrap: int = opt(RESAMPLES, "bootstrap resamples over scenes")
    bootstrap_seed: int = opt(0, "seed of the bootstrap resamples")
    progress: bool = opt(True, "progress bars")


def _numbers(text: str, flag: str, kind=float) -> list:
    try:
        out = [kind(x) for x in text.split(",") if x.strip()]
    except ValueError:
        out = []
    if not out or any(x <= 0 for x in out):
        raise UavsearchError(f"{flag} takes positive comma-separated numbers, not {text!r}")
    return sorted(set(out))


def _learned_budgets(text: str) -> tuple[str, ...]:
    budgets = tuple(b.strip() for b in str(text).split(",") if b.strip() and b.strip() != "none")
    if any(b not in BUDGETS for b in budgets):
        raise UavsearchError(f"--learned takes the budgets {' and '.join(BUDGETS)} (comma-separated) or none, "
                             f"not {text!r}")
    return budgets


def _fusion_specs(text: str) -> list[str]:
    """The comma-separated candidates; "neighbour:A.pt,B.pt" (an ensemble) keeps its .pt paths together."""
    out: list[str] = []
    for part in (x.strip() for x in text.split(",")):
        if not part:
            continue
        if out and out[-1].startswith("neighbour:") and ":" not in part and part.endswith(".pt"):
            out[-1] += f",{part}"
        else:
            out.append(part)
    return out


def eval_team(args: TeamEvalArgs, caches: dict | None = None) -> dict:
    """The team table into args.out; `caches` ({part: ViewCache}) skips building the family's caches."""
    sizes = _numbers(args.vehicles, "--vehicles", int)
    times = _numbers(args.times, "--times")
    if max(sizes) > 16:
        raise UavsearchError("--vehicles: at most 16")
    learned = _learned_budgets(args.learned)
    t0 = time.perf_counter()
    caches = caches if caches is not None else family_caches(args, args.setting)
    caches = {part: to_device(c, resolve_device(getattr(args, "device", "auto"))) for part, c in caches.items()}
    fusions = _fusion_specs(args.fusions)
    fusions += [f for f in learned_aggregations(caches["test"].perception_tag, args.setting, budgets=learned)
                if f not in fusions]
    for f in fusions:
        make_fusion(f)  # a bad name is a one-line error before any work
    res = evaluate_teams(caches, sizes, times, args.bootstrap, args.bootstrap_seed, fusions=fusions)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = [{"vehicles": v, "time_s": t, "planner": c[k]["spec"], "team_planner": c["chosen"] == k,
             "fusion": c[k]["fusion"],
             "val_af1": c[k]["val_af1"], "af1": float(c[k]["f1"].mean()), "aacc": float(c[k]["acc"].mean() * 100),
             "views": float(c[k]["views"].mean()), "scenes": len(c[k]["f1"])}
            for (v, t), c in res["conditions"].items() for k in PLANNERS]
    write_csv(out / "team.csv", rows)
    write_csv(out / "team_paired.csv", res["paired"])
    save_figure(team_figure(res, sizes, times), out / "team.png")
    scenes = {k: c.num_scenes for k, c in caches.items()}
    md = out / "team.md"
    md.write_text("\n".join(table_lines(res, sizes, times, args.setting, scenes)
                            + [f"{time.perf_counter() - t0:.0f} s; figure: {display_path(out / 'team.png')}"]) + "\n")
    print(md.read_text())
    return res


def add_eval_team_parser(subparsers) -> None:
    p = subparsers.add_parser("team", help="teams of vehicles on one shared map: AF1 against mission time")
    add_dataclass_args(p, TeamEvalArgs)
    p.set_defaults(func=cmd_eval_team)


def cmd_eval_team(args) -> int:
    eval_team(dataclass_from_args(TeamEvalArgs, args))
    return 0


if __name__ == "__main__":  # python -m uavsearch.search.evaluate.team [flags] = uavsearch eval team [flags]
    raise SystemExit(run_command(cmd_eval_team, add_dataclass_args(argparse.ArgumentParser(
        prog="python -m uavsearch.search.evaluate.team"), TeamEvalArgs).parse_args()))


__all__ = ["PLANNERS", "eval_team", "evaluate_teams", "make_planner", "team_scores"]
