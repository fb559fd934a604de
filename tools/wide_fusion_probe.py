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

    python tools/wide_fusion_probe.py --budget 8 --out results/map_policy/fusion_probe_T8.md
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from uavsearch.paths import display_path  # noqa: E402
from uavsearch.search.data.view_cache import get_view_cache  # noqa: E402
from uavsearch.search.evaluate.bounds import bootstrap_ci  # noqa: E402
from uavsearch.search.fusion import calibrated_logit, make_fusion  # noqa: E402
from uavsearch.search.metrics import map_f1  # noqa: E402
from uavsearch.search.perception import load_perception, shipped_perception  # noqa: E402
from uavsearch.search.search_loop import Agent, CachedViews, run_search  # noqa: E402
from uavsearch.search.train.map_policy import budget_config  # noqa: E402
from uavsearch.search.wide_policies import candidates, choose_rule, rule_policy  # noqa: E402

FUSION = {"8": "calibrated:0.25", "240": "calibrated:0.75"}  # the learned policy's (docs/learning.md)
SHIFTS = np.arange(-2.0, 2.01, 0.25)  # decision thresholds tried, as log-odds shifts


class NoisyRule:
    """The rule, with a share of its moves replaced by random allowed ones (varied states to fit on)."""

    def __init__(self, rule, eps: float, gen: torch.Generator):
        self.rule, self.eps, self.gen = rule, eps, gen

    def act(self, inp, generator=None):
        a = self.rule.act(inp)[0]
        if not self.eps:
            return a, None, None
        w = candidates(inp).float()
        w[w.sum(1) == 0] = 1
        rnd = torch.multinomial(w, 1, generator=self.gen)[:, 0]
        return torch.where(torch.rand(len(a), generator=self.gen) < self.eps, rnd, a), None, None


def cell_planes(cache, rows, episode, fusion, config) -> torch.Tensor:
    """(B, 11, rows, cols): the calibrated fusion's final log-odds, then per altitude layer (lowest first) the
    cell's views: count (capped at 4, / 4), highest, mean and lowest calibrated log-odds, mean log pixel area."""
    r = torch.as_tensor(rows)[:, None]
    idx = episode.lattice_idx
    taken = episode.taken if episode.taken is not None else torch.ones_like(idx, dtype=torch.bool)
    p = cache.log_probs[r, idx, :, 1].exp().float()
    v = cache.valid[r, idx] & taken[..., None]
    area = cache.cell_area_px[r, idx].float()
    c = calibrated_logit(p, area, fusion.coef)
    alts = torch.tensor(config.lattice.positions_enu[:, 2])
    low = alts == alts.min()
    planes = [torch.logit(episode.maps[:, -1].float().clamp(1e-5, 1 - 1e-5))]
    for layer in (low, ~low):
        m = v & layer[idx][..., None]
        n = m.sum(1).float()
        seen = (n > 0).float()
        planes += [n.clamp(max=4) / 4,
                   torch.where(m, c, torch.full_like(c, -20.0)).amax(1).clamp(min=-8) * seen,
                   torch.where(m, c, torch.zeros_like(c)).sum(1) / n.clamp(min=1),
                   torch.where(m, c, torch.full_like(c, 20.0)).amin(1).clamp(max=8) * seen,
                   torch.where(m, area.clamp(min=1).log(), torch.zeros_like(area)).sum(1) / n.clamp(min=1)]
    g = config.grid
    return torch.stack(planes, 1).view(len(idx), len(planes), g.n, g.n)


class CorrectionNet(nn.Module):
    """A correction to the calibrated log-odds (plane 0), from each cell's planes (kernel 1) or its neighbours'."""

    def __init__(self, planes: int, kernel: int, hidden: int = 24):
        super().__init__()
        pad = kernel // 2
        self.net = nn.Sequential(nn.Conv2d(planes, hidden, kernel, padding=pad), nn.ReLU(),
                                 nn.Conv2d(hidden, hidden, kernel, padding=pad), nn.ReLU(),
                                 nn.Conv2d(hidden, hidden, 1), nn.ReLU(), nn.Conv2d(hidden, 1, 1))

    def forward(self, x):
        return self.net(x)[:, 0] + x[:, 0]


def dihedral(x: torch.Tensor, k: int) -> torch.Tensor:
    """One of the square's 8 symmetries of (..., rows, cols) maps: a rotation by k % 4 quarter turns, mirrored
    when k >= 4. The lattice and the grid share them, so a rotated map is another plausible search."""
    x = torch.rot90(x, k % 4, dims=(-2, -1))
    return torch.flip(x, dims=(-1,)) if k >= 4 else x


def fit_net(X, Y, kernel: int, seed: int, epochs: int) -> CorrectionNet:
    """Cross-entropy fit, each batch under a random symmetry of the square (the maps of 100 scenes are few
    enough for a net that sees a neighbourhood to learn where each scene's clutter lies)."""
    torch.manual_seed(seed)
    net = CorrectionNet(X.shape[1], kernel)
    opt = torch.optim.Adam(net.parameters(), lr=3e-3, weight_decay=1e-4)
    gen = torch.Generator().manual_seed(seed)
    for _ in range(epochs):
        perm = torch.randperm(len(X), generator=gen)
        for j in range(0, len(X), 64):
            b = perm[j:j + 64]
            k = int(torch.randint(8, (), generator=gen))
            loss = nn.functional.binary_cross_entropy_with_logits(net(dihedral(X[b], k)), dihedral(Y[b], k))
            opt.zero_grad()
            loss.backward()
            opt.step()
    return net.eval()


def best_shift(logits: np.ndarray, labels: np.ndarray) -> float:
    return float(max(SHIFTS, key=lambda s: map_f1(1 / (1 + np.exp(-(logits + s))), labels).mean()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--family", default="wide")
    ap.add_argument("--budget", choices=("8", "240"), default="8", help="T = 8 views, or 240 s of flight")
    ap.add_argument("--train-scenes", type=int, default=100, help="training scenes the rollouts fly")
    ap.add_argument("--rollouts", type=int, default=10, help="rollouts per training scene (the first: the rule)")
    ap.add_argument("--epochs", type=int, default=20)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1], help="seeds of the learned fusions")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", required=True, help="markdown file to write")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    net_p, _ = load_perception(str(shipped_perception(args.family)))
    train = get_view_cache(net_p, args.family, "large", "train", features=False, limit=args.train_scenes,
                           progress=False)
    val = get_view_cache(net_p, args.family, "large", "val", features=False, progress=False)
    config = budget_config(train.config, args.budget)
    fusion = make_fusion(FUSION[args.budget], train.subset(np.arange(min(20, train.num_scenes))))
    variant, _ = choose_rule(val, config, fusion)
    rule = rule_policy(config, variant)

    def final_maps(cache, eps, seed):
        rows = np.arange(cache.num_scenes)
        gen = torch.Generator().manual_seed(seed)
        with torch.no_grad():
            ep = run_search(CachedViews(cache, rows, config), Agent(fusion, NoisyRule(rule, eps, gen)),
                            generator=gen)
        return cell_planes(cache, rows, ep, fusion, config), cache.occupancy.float().view(-1, *X_SHAPE)

    X_SHAPE = (config.grid.n, config.grid.n)
    fits = [(f"{'per cell' if k == 1 else 'with neighbours'}, seed {s}", k, s) for k in (1, 5) for s in args.seeds]
    bar = tqdm(total=args.rollouts + 1 + len(fits), desc="fusion probe", unit="step")
    Xs, Ys = [], []
    for k in range(args.rollouts):
        x, y = final_maps(train, 0.0 if k == 0 else 0.3, k)
        Xs.append(x), Ys.append(y)
        bar.update()
    X, Y = torch.cat(Xs), torch.cat(Ys)
    Xv, Yv = final_maps(val, 0.0, 0)
    bar.update()
    flat = lambda t: t.reshape(len(t), -1).numpy()  # noqa: E731
    yt, yv = flat(Y), flat(Yv)
    base = map_f1(1 / (1 + np.exp(-flat(Xv[:, 0]))), yv)
    rows = []

    def row(name, train_logits, val_logits):
        s = best_shift(train_logits, yt)
        f1 = map_f1(1 / (1 + np.exp(-(val_logits + s))), yv)
        train_f1 = map_f1(1 / (1 + np.exp(-(train_logits + s))), yt).mean()
        rows.append((name, s, float(train_f1), float(f1.mean()), *bootstrap_ci(f1 - base)))

    row("the calibrated fusion, threshold refitted", flat(X[:, 0]), flat(Xv[:, 0]))
    for name, kernel, seed in fits:
        net = fit_net(X, Y, kernel, seed, args.epochs)
        with torch.no_grad():
            row(f"learned correction, {name}", flat(net(X)), flat(net(Xv)))
        bar.update()
    bar.close()
    budget = "T = 8 views" if args.budget == "8" else f"{config.budget_s:g} s of flight"
    lines = [f"# A learned fusion over each cell's views: {args.family}, {budget}", "",
             f"Final maps of the rule ({variant}) on {val.num_scenes} validation scenes, fused by {FUSION[args.budget]} "
             f"(AF1 {base.mean():.3f}) and by learned corrections to it, fitted on {len(X)} final maps of "
             f"{args.rollouts} rollouts of the first {train.num_scenes} training scenes (the rule, then 30% random "
             f"moves; seeds 0-{args.rollouts - 1}). Threshold: the log-odds shift with the best AF1 on those training "
             f"maps. Δ: per-scene final AF1 minus the calibrated fusion's, mean [95% bootstrap interval over scenes]. "
             f"`python tools/wide_fusion_probe.py --budget {args.budget}`", "",
             "| fusion | shift | training AF1 | validation AF1 | Δ vs calibrated [95% CI] |", "|---|---|---|---|---|"]
    lines += [f"| {n} | {s:+.2f} | {tr:.3f} | {a:.3f} | {d:+.3f} [{lo:+.3f}, {hi:+.3f}] |"
              for n, s, tr, a, d, lo, hi in rows]
    lines += ["", f"{time.perf_counter() - t0:.0f} s"]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"wrote {display_path(out)}")


if __name__ == "__main__":
    main()
