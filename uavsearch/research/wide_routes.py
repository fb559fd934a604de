"""What the learned wide-area policy does that the rule does not: both run on the wide test scenes (the shipped map
checkpoints with their fusion; the rule's variant chosen on the validation scenes with that same fusion, as
Table III does), route by route, under the view budget and the time budget. Per scene:

- the routes: identical or not, viewpoints in common (share of the union), views at 40 m, seconds of flight;
- following a find: the share of views (after the start view) taken within one lattice step (25 m) of the
  centre of a group that was already found (a cell of the group held fused p > 0.5 before the view);
- leaving empty areas: the share of 40 m views that added no true positive to the map;
- final F1, and the learned policy minus the rule, paired per scene (95% bootstrap interval over scenes).

Prints the table and writes it (markdown) beside a JSON of the per-scene rows.

    python tools/wide_routes.py --out results/map_policy/routes.md
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from ..paths import display_path
from ..search.agents import load_wide_agent
from ..search.config import wide_budgets
from ..search.data.view_cache import get_view_cache
from ..search.metrics import bootstrap_ci
from ..search.evaluate.wide import flight_seconds
from ..search.map_policy import BUDGETS, wide_checkpoint
from ..search.metrics import map_f1
from ..search.perception import load_perception, shipped_perception
from ..search.search_loop import Agent, CachedViews, run_search
from ..search.wide_policies import choose_rule, rule_policy
from ..world.settings import generate_setting_scene, setting_params

FAMILY = "wide"
FOUND_P = 0.5


def groups_of(seed: int, n_cells: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """(group centres (G, 2) in metres, the occupied cells of each group) of a clustered scene."""
    spec = generate_setting_scene(FAMILY, int(seed))
    centres = np.asarray(spec.group_centres_m, float).reshape(-1, 2)
    cells = [np.unique([p.cell for p in spec.people if p.group == g and 0 <= p.cell < n_cells]).astype(int)
             for g in range(len(centres))]
    return centres, cells


def route_stats(config, idx: np.ndarray, maps: np.ndarray, labels: np.ndarray, centres, cells) -> dict:
    """One episode's route measures (module docstring); idx (T,) viewpoints with an ended episode's repeats cut."""
    pos = config.lattice.positions_enu
    low = pos[:, 2] < pos[:, 2].max() - 1.0
    spacing = config.lattice.spacing_m
    near, empty_low = [], []
    tp = ((maps > FOUND_P) & labels[None]).sum(1)  # (T,) true positives after each view
    for t in range(1, len(idx)):
        found = [g for g, cs in enumerate(cells) if len(cs) and (maps[t - 1, cs] > FOUND_P).any()]
        d = [np.hypot(*(pos[idx[t], :2] - centres[g])) for g in found]
        near.append(bool(d) and min(d) <= spacing + 1e-6)
        if low[idx[t]]:
            empty_low.append(tp[t] <= tp[t - 1])
    return dict(views=len(idx), low=int(low[idx].sum()), flight_s=float(flight_seconds(config, idx[None])[0]),
                near_found=float(np.mean(near)) if near else 0.0,
                empty_low=float(np.mean(empty_low)) if empty_low else float("nan"),
                f1=float(map_f1(maps[-1:], labels[None])[0]))


def episodes(cache, agent: Agent, config) -> list[tuple[np.ndarray, np.ndarray]]:
    """(viewpoints, maps) of one greedy episode per scene, an ended episode's repeated columns cut."""
    with torch.no_grad():
        ep = run_search(CachedViews(cache, np.arange(cache.num_scenes), config), agent)
    out = []
    for b in range(cache.num_scenes):
        n = int(ep.taken[b].sum()) if ep.taken is not None else ep.lattice_idx.shape[1]
        out.append((ep.lattice_idx[b, :n].numpy(), ep.maps[b, :n].numpy()))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=None, help="the first N wide test scenes (default all 100)")
    ap.add_argument("--val-scenes", type=int, default=None,
                    help="the first N validation scenes, where the rule's variant is chosen (default all 50)")
    ap.add_argument("--policy-dir", type=Path, default=None, help="where the map checkpoints are (default models/)")
    ap.add_argument("--out", type=Path, default=None, help="markdown table to write")
    args = ap.parse_args()
    torch.set_num_threads(1)
    net, _ = load_perception(shipped_perception(FAMILY))
    split = setting_params(FAMILY).split
    test = get_view_cache(net, FAMILY, split, "test", features=False, limit=args.scenes, progress=True)
    val = get_view_cache(net, FAMILY, split, "val", features=False, limit=args.val_scenes, progress=True)
    labels = test.occupancy.numpy()
    scene_groups = [groups_of(s, labels.shape[1]) for s in tqdm(test.scene_seed, desc="scene groups", leave=False)]
    results, lines = {}, []
    for budget, (name, cfg) in zip(BUDGETS, wide_budgets(test.config).items()):
        path = wide_checkpoint(budget, args.policy_dir)
        ours = load_wide_agent(path, cfg)
        variant, _ = choose_rule(val, cfg, ours.fusion)
        rows = {}
        for key, agent in (("rule", Agent(ours.fusion, rule_policy(cfg, variant))), ("ours", ours)):
            eps = episodes(test, agent, cfg)
            rows[key] = [route_stats(cfg, i, m, labels[b], *scene_groups[b]) for b, (i, m) in enumerate(eps)]
            for r, (i, _) in zip(rows[key], eps):
                r["route"] = i.tolist()
        same = [a["route"] == b["route"] for a, b in zip(rows["rule"], rows["ours"])]
        common = [len(set(a["route"]) & set(b["route"])) / len(set(a["route"]) | set(b["route"]))
                  for a, b in zip(rows["rule"], rows["ours"])]
        diff = bootstrap_ci([b["f1"] - a["f1"] for a, b in zip(rows["rule"], rows["ours"])])
        results[name] = dict(rule_variant=variant, checkpoint=display_path(path), same_route=int(sum(same)),
                             common=float(np.mean(common)), ours_minus_rule=list(diff), rows=rows)

        def m(key, field):
            v = np.array([r[field] for r in rows[key]], float)
            return float(np.nanmean(v))

        lines += [f"### {name}: {display_path(path)} against the rule ({variant})", "",
                  f"{test.num_scenes} wide test scenes, one greedy episode each, both with the checkpoint's fusion. "
                  f"Identical routes: {sum(same)} of {test.num_scenes} scenes; viewpoints in common: "
                  f"{np.mean(common):.0%} of the two routes' union (mean over scenes).", "",
                  "| | views | of them at 40 m | flight (s) | views within 25 m of a found group | 40 m views that "
                  "found nothing new | AF1 |", "|---|---|---|---|---|---|---|"]
        for key, label in (("rule", "the rule"), ("ours", "ours (learned)")):
            lines.append(f"| {label} | {m(key, 'views'):.1f} | {m(key, 'low'):.1f} | {m(key, 'flight_s'):.0f} | "
                         f"{m(key, 'near_found'):.0%} | {m(key, 'empty_low'):.0%} | {m(key, 'f1'):.3f} |")
        lines += ["", f"Ours − the rule, final F1 per scene: {diff[0]:+.3f} [{diff[1]:+.3f}, {diff[2]:+.3f}].", ""]
    cmd = "python tools/wide_routes.py" + (f" --out {display_path(args.out)}" if args.out else "")
    text = "\n".join(["# The learned wide-area policy's routes against the rule's", "",
                      f"Regenerate: `{cmd}`. A group counts as found once one of its occupied cells holds fused p > "
                      f"{FOUND_P}; a view is near it when its viewpoint lies within one lattice step (25 m) of the "
                      "group's centre.", "", *lines])
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)
        args.out.with_suffix(".json").write_text(json.dumps(results, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
