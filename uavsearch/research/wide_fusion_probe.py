"""Would a fusion that learns how the views of one cell go together make better wide maps than the calibrated one?

The calibrated fusion adds each view's evidence as if views were independent (views at the same scale discounted
by n^gamma), while a person perception finds once it mostly finds again. Here learned fusions read, per cell, the
calibrated fusion's log-odds and the cell's views per altitude layer (how many, their highest, mean and lowest
calibrated log-odds, their mean log pixel area) and output a correction to those log-odds:
- per cell: a 1 x 1 convolutional net, so only the cell's own views;
- with neighbours: 5 x 5 convolutions over the 30 x 30 map, so also the views of nearby cells (people come in
  groups);
- the control: the calibrated fusion with only its decision threshold refitted.
Each is fitted by cross-entropy on the final maps of rule rollouts of the first training scenes (one rollout of
the rule, the others with 30% random moves, seeded), its threshold (a log-odds shift) then chosen for AF1 on
those same training maps, and scored on the final maps of the rule's episodes on the validation scenes, paired
against the calibrated fusion's maps of the same episodes (95% bootstrap interval over scenes).

During the search: a net with neighbours, fitted on maps after a few views of the same rollouts as well as
their final ones, corrects the map after every view, so the policy reads the corrected map too. The rule and
the shipped learned policy (trained on the calibrated fusion's maps) fly with it, each paired against the rule
with the calibrated fusion, and against each other with the correction.

With `--features`, per-view cell **features** join the scores: per altitude layer the mean of perception's cell
features (104 per cell: what its classifier reads) over the cell's views, reduced by a learned 1 x 1 convolution
to 8 channels before the same net with neighbours (fitted end to end, the same seeds and maps): does aggregating
what perception saw, not only what it concluded, tell people from clutter better?

    python tools/wide_fusion_probe.py --budget 8 --train-scenes 300 --out results/map_policy/fusion_probe_T8.md
    python tools/wide_fusion_probe.py --budget 8 --train-scenes 300 --features --out results/wide_study/features_T8.md

`--save runs/neighbour_T8.pt` also writes the in-search net as the product's neighbour fusion
(search/neighbour_fusion.py), which `uavsearch eval search --wide-fusion neighbour:runs/neighbour_T8.pt` names.
"""

from __future__ import annotations

import shlex
import sys
import time

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from ..paths import display_path
from ..search.agents import budget_text, load_wide_agent
from ..search.map_policy import wide_checkpoint
from ..search.metrics import bootstrap_ci, map_f1
from ..search.neighbour_fusion import (PLANES, CorrectionNet, FeatureCorrectionNet, NeighbourFusion, episode_planes,
                                       feature_planes, save_neighbour)
from ..search.search_loop import Agent, CachedViews, run_search
from ..search.symmetry import square_symmetry
from ..search.train.fusion import best_shift, net_logits
from ..search.wide_policies import lowest_layer
from .wide_policy_probes import FUSION, NoisyRule, fit_adam, probe_parser, probe_setting, write_markdown


def cell_planes(cache, rows, episode, fusion, config, step: int = -1) -> torch.Tensor:
    return episode_planes(cache, rows, episode, fusion.coef, lowest_layer(config), config.grid.n, step)


def fit_net(X, Y, kernel: int, seed: int, epochs: int, symmetries: bool = True) -> nn.Module:
    """Cross-entropy fit, each batch under a random symmetry of the square (the maps of 100 scenes are few
    enough for a net that sees a neighbourhood to learn where each scene's clutter lies). Planes beyond the score
    planes are mean cell features (FeatureCorrectionNet)."""
    torch.manual_seed(seed)
    net = CorrectionNet(X.shape[1], kernel) if X.shape[1] == PLANES else FeatureCorrectionNet(X.shape[1] - PLANES,
                                                                                              kernel)

    def loss(b, gen):
        k = int(torch.randint(8, (), generator=gen)) if symmetries else 0
        return nn.functional.binary_cross_entropy_with_logits(net(square_symmetry(X[b], k)), square_symmetry(Y[b], k))

    return fit_adam(net, len(X), loss, seed, epochs, lr=3e-3, weight_decay=1e-4)


def main() -> None:
    ap = probe_parser(__doc__)
    ap.add_argument("--train-scenes", type=int, default=100, help="training scenes the rollouts fly")
    ap.add_argument("--rollouts", type=int, default=10, help="rollouts per training scene (the first: the rule)")
    ap.add_argument("--epochs", type=int, default=20)
    ap.add_argument("--no-symmetries", dest="symmetries", action="store_false",
                    help="fit without the square's symmetries (the net with neighbours then memorises scenes)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1], help="seeds of the learned fusions")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--features", action="store_true",
                    help="also fit the net with neighbours on the views' mean cell features (the feature store)")
    ap.add_argument("--save", help="write the in-search neighbour fusion (the rule's) to this checkpoint "
                                   "(a spec then names it: neighbour:PATH)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    _, train, val, config, fusion, variant, rule = probe_setting(args.family, args.budget, args.train_scenes)

    def rollout(cache, agent):
        with torch.no_grad():
            return run_search(CachedViews(cache, np.arange(cache.num_scenes), config), agent,
                              generator=torch.Generator().manual_seed(0))

    rows_tr = np.arange(train.num_scenes)
    fits = [(f"{'per cell' if k == 1 else 'with neighbours'}, seed {s}", k, s, False) for k in (1, 5)
            for s in args.seeds]
    if args.features:
        fits += [(f"with neighbours and cell features, seed {s}", 5, s, True) for s in args.seeds]
    lowest, n = lowest_layer(config), config.grid.n
    bar = tqdm(total=args.rollouts + len(fits) + 6, desc="fusion probe", unit="step")
    X, XS, XF = [], [], []  # final maps; maps after a few steps of each rollout (for the in-search net); features
    for k in range(args.rollouts):
        gen = torch.Generator().manual_seed(k)
        ep = rollout(train, Agent(fusion, NoisyRule(rule, 0.0 if k == 0 else 0.3, gen)))
        last = ep.lattice_idx.shape[1] - 1
        steps = {last} | set(torch.randint(last + 1, (2,), generator=gen).tolist())
        X.append(cell_planes(train, rows_tr, ep, fusion, config))
        if args.features:
            XF.append(feature_planes(train, rows_tr, ep, lowest, n))
        XS += [cell_planes(train, rows_tr, ep, fusion, config, t) for t in sorted(steps)]
        bar.update()
    grid = (config.grid.n, config.grid.n)
    X, XS = torch.cat(X), torch.cat(XS)
    Y = train.occupancy.float().view(-1, *grid).repeat(args.rollouts, 1, 1)
    YS = train.occupancy.float().view(-1, *grid).repeat(len(XS) // train.num_scenes, 1, 1)
    rule_ep = rollout(val, Agent(fusion, rule))
    Xv = cell_planes(val, np.arange(val.num_scenes), rule_ep, fusion, config)
    if args.features:  # score planes in float16 beside the features: 3,000 maps x 219 planes stay near 1 GB
        XF = torch.cat([X.half(), torch.cat(XF)], 1)
        XFv = torch.cat([Xv.half(), feature_planes(val, np.arange(val.num_scenes), rule_ep, lowest, n)], 1)
    bar.update()
    flat = lambda t: t.reshape(len(t), -1).numpy()  # noqa: E731
    yt, yv = flat(Y), val.occupancy.numpy()
    base = map_f1(1 / (1 + np.exp(-flat(Xv[:, 0]))), yv)
    rows = []

    def row(name, train_logits, val_logits):
        s = best_shift(train_logits, yt)
        f1 = map_f1(1 / (1 + np.exp(-(val_logits + s))), yv)
        train_f1 = map_f1(1 / (1 + np.exp(-(train_logits + s))), yt).mean()
        rows.append((name, s, float(train_f1), float(f1.mean()), *bootstrap_ci(f1 - base)))

    row("the calibrated fusion, threshold refitted", flat(X[:, 0]), flat(Xv[:, 0]))
    for name, kernel, seed, features in fits:
        xt, xv = (XF, XFv) if features else (X, Xv)
        net = fit_net(xt, Y, kernel, seed, args.epochs, args.symmetries)
        with torch.no_grad():
            row(f"learned correction, {name}", net_logits(net, xt), flat(net(xv)))
        bar.update()

    # during the search: a net with neighbours fitted on maps after every few views corrects each map the
    # policy reads, the rule and the shipped learned policy alike
    seed = args.seeds[0]
    net = fit_net(XS, YS, 5, seed, args.epochs, args.symmetries)
    with torch.no_grad():
        shift = best_shift(flat(net(X)), yt)
    bar.update()
    if args.save:
        save_neighbour(NeighbourFusion.around(fusion, net, shift, config), args.save,
                       {"budget": args.budget, "family": args.family, "train_scenes": train.num_scenes,
                        "rollouts": args.rollouts, "epochs": args.epochs, "seed": seed, "shift": shift,
                        "fit_s": time.perf_counter() - t0})
    ours = load_wide_agent(wide_checkpoint(args.budget), config)
    agents = {"the rule, calibrated fusion": Agent(fusion, rule),
              "the rule, learned correction during the search": Agent(NeighbourFusion.around(fusion, net, shift,
                                                                                             config), rule),
              "ours (shipped learned policy), its calibrated fusion": ours,
              "ours, learned correction during the search": Agent(NeighbourFusion.around(ours.fusion, net, shift,
                                                                                        config), ours.policy)}
    f1s = {}
    for name, agent in agents.items():
        f1s[name] = map_f1(rollout(val, agent).maps[:, -1].numpy(), yv)
        bar.update()
    bar.close()
    ref = f1s["the rule, calibrated fusion"]
    search_rows = [(n, float(f.mean()), *bootstrap_ci(f - ref)) for n, f in f1s.items()]
    both = bootstrap_ci(f1s["ours, learned correction during the search"]
                        - f1s["the rule, learned correction during the search"])
    lines = [f"# A learned fusion over each cell's views: {args.family}, {budget_text(config)}", "",
             f"Final maps of the rule ({variant}) on {val.num_scenes} validation scenes, fused by {FUSION[args.budget]} "
             f"(AF1 {base.mean():.3f}) and by learned corrections to it, fitted on {len(X)} final maps of "
             f"{args.rollouts} rollouts of the first {train.num_scenes} training scenes (the rule, then 30% random "
             f"moves; seeds 0-{args.rollouts - 1}), {args.epochs} epochs, "
             f"{'every batch under a random symmetry of the square' if args.symmetries else 'no symmetries'}. "
             f"Threshold: the log-odds shift with the best AF1 on those training "
             f"maps. Δ: per-scene final AF1 minus the calibrated fusion's, mean [95% bootstrap interval over scenes]. "
             f"`python tools/wide_fusion_probe.py {shlex.join(sys.argv[1:])}`", "",
             "| fusion | shift | training AF1 | validation AF1 | Δ vs calibrated [95% CI] |", "|---|---|---|---|---|"]
    lines += [f"| {n} | {s:+.2f} | {tr:.3f} | {a:.3f} | {d:+.3f} [{lo:+.3f}, {hi:+.3f}] |"
              for n, s, tr, a, d, lo, hi in rows]
    lines += ["", f"**During the search.** A net with neighbours (seed {seed}) fitted on {len(XS)} maps of the same "
              "rollouts, each after its last view and after two views drawn at random (seeded by the rollout), "
              f"threshold shift {shift:+.2f} chosen on the final training maps, corrects the map after every view, "
              "so the policy reads the corrected map. The shipped learned policy "
              f"(`{display_path(wide_checkpoint(args.budget))}`) was trained on the calibrated fusion's maps. "
              f"Δ: per-scene final AF1 minus the rule's with the calibrated fusion ({val.num_scenes} validation "
              "scenes).", "", "| agent | AF1 | Δ vs the rule, calibrated [95% CI] |", "|---|---|---|"]
    lines += [f"| {n} | {a:.3f} | {d:+.3f} [{lo:+.3f}, {hi:+.3f}] |" for n, a, d, lo, hi in search_rows]
    lines += ["", "Ours against the rule, both with the learned correction during the search: "
              f"{both[0]:+.3f} [{both[1]:+.3f}, {both[2]:+.3f}].", "", f"{time.perf_counter() - t0:.0f} s"]
    write_markdown(args.out, lines)


if __name__ == "__main__":
    main()
