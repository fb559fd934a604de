"""Why the wide family's rule is hard to beat: policies that choose the rule's descents another way, paired against
the rule on the validation scenes (95% bootstrap interval over scenes), and whether perception's cell features say
more about a person than its p does.

The rule flies a survey (70 m views that cover the area), then descends. Probes of the survey: the rule with
fewer survey views (3 of the 4 covering ones, 2 diagonal ones, none: only its resurvey of the nearest 70 m
viewpoint while no open cell has p 0.4 or more), its other settings as chosen. Every other probe flies the rule's
survey first and differs only in how it picks the views after it:
- the rule's descent score changed: the sum of the open cells' fused p under the footprint instead of their
  maximum, the maximum plus a twentieth of the sum, the sum of p squared;
- expected gain (a one-view value of information): each viewpoint's expected change of N_tp - N_fp of the fused
  map, the fused p taken as each cell's belief and one view's calibrated evidence drawn from its distribution on
  the training views at that pixel area, given the label;
- learned per-cell gains: the same expectation learned from the label teacher instead, per cell and altitude
  layer (the change of the cell's true/false-positive count after a view of that layer, averaged over the
  viewpoints that see it), on rule rollouts of the training scenes (30% random moves), then summed over each
  viewpoint's footprint: by a table over (fused p bin, views of the cell per layer) and by the map policy's
  convolutional trunk (MapPolicyNet) with a two-output head;
- learned viewpoint gains: a ridge regression of the label teacher's gain of every viewpoint on a few
  hand-made sums over its footprint (footprint_features), from the same rollouts: too few weights to memorise;
- bounds that read the labels: the true per-cell gains summed the same way, and the label-peeking greedy.
The feature probe fits a logistic regression of a cell-view's label on its calibrated log-odds and pixel area,
then on those and the perception net's cell features, on training views, and reports the validation AUC.

    python tools/wide_policy_probes.py --budget 8 --out results/map_policy/probes_T8.md
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from ..paths import display_path
from ..search.agents import budget_text
from ..search.data.view_cache import get_view_cache
from ..search.metrics import bootstrap_ci
from ..search.agents import make_fusion
from ..search.fusion import SAME_SCALE, calibrated_logit
from ..search.map_policy import MAP_PLANES, MapPolicyConfig, MapPolicyNet
from ..search.config import config_to_dict
from ..search.perception import load_perception, shipped_perception
from ..search.scoring import evaluate_agent
from ..search.search_loop import Agent, CachedViews, run_search
from ..search.train.map_policy import LabelLookahead, budget_config, repeat_state
from ..search.train.runs import fit_minibatches
from ..search.wide_policies import (RULE_OVERHEAD_S, RULE_VARIANTS, SURVEY_OUTER_M,
                                            DescendRule, NoisyRule, argmax_allowed, candidates, choose_rule, footprints,
                                            lowest_layer, route_views, rule_policy)

FUSION = {"8": "calibrated:0.25", "240": "calibrated:0.75"}  # the learned policy's (docs/learning.md)


class AfterSurvey:
    """The rule's survey, then the viewpoint of the highest score(inp) (under a time budget per second of flight
    plus the rule's overhead, unless the score is per second already)."""

    def __init__(self, rule: DescendRule, score, config, per_second: bool = True):
        self.survey, self.score = rule.survey, score
        self.cost = config.lattice.flight_time_t.float()
        self.timed = per_second and config.budget_s is not None

    @torch.no_grad()
    def act(self, inp, generator=None):
        if inp.step < len(self.survey):
            return torch.full_like(inp.lattice_idx, self.survey[inp.step]), None, None
        s = self.score(inp)
        if self.timed:
            s = s / (self.cost[inp.lattice_idx] + RULE_OVERHEAD_S)
        return argmax_allowed(s - 1e-6 * self.cost[inp.lattice_idx], candidates(inp)), None, None


class DescentScore(DescendRule):
    """The rule with another descent score over the open cells' fused p (module docstring)."""

    def __init__(self, rule: DescendRule, reduce):
        self.__dict__.update(rule.__dict__)
        self.reduce = reduce

    def descend_scores(self, inp):
        _, pick = super().descend_scores(inp)
        low_views = self.low[inp.view_positions][..., None] & inp.view_valid
        p = inp.fused * (~low_views.any(1)).float()
        return self.reduce(p, self.foot), pick


SHORTER_SURVEYS = {"3 covering views": SURVEY_OUTER_M[:3], "2 diagonal covering views": SURVEY_OUTER_M[::2],
                   "no survey": ()}
DESCENT_SCORES = {
    "sum of the open cells' p": lambda p, foot: p @ foot.T,
    "max + 0.05 x sum of the open cells' p": lambda p, foot: (p[:, None] * foot[None]).amax(-1) + 0.05 * (p @ foot.T),
    "sum of the open cells' p squared": lambda p, foot: (p * p) @ foot.T,
}


class ExpectedGain:
    """A view's expected change of N_tp - N_fp under the calibrated fusion (module docstring)."""

    def __init__(self, train, fusion, config, k: int = 32):
        self.fusion = fusion
        self.area = config.lattice.cell_areas.float()
        self.la = self.area.clamp(min=1).log()
        self.foot = footprints(config)
        self.l0 = float(np.log(fusion.prior / (1 - fusion.prior)))
        u = torch.unique(self.area[self.area >= 1].round()).clamp(min=1).log()  # the lattice's pixel areas
        self.edges = (u[1:] + u[:-1]) / 2
        self.bin = torch.bucketize(self.la, self.edges)
        v = train.valid
        y = train.occupancy[:, None, :].expand(v.shape)[v]
        a = train.cell_area_px[v].float()
        c = calibrated_logit(train.log_probs[..., 1].exp()[v].float(), a, fusion.coef)
        b = torch.bucketize(a.clamp(min=1).log(), self.edges)
        q = (torch.arange(k, dtype=torch.float32) + 0.5) / k
        self.table = torch.zeros(len(u), 2, k)  # quantiles of one view's calibrated log-odds given area, label
        gen = torch.Generator().manual_seed(0)
        for i in range(len(u)):
            for label in (0, 1):
                sel = c[(b == i) & (y == bool(label))]
                sel = sel[torch.randperm(len(sel), generator=gen)[:200_000]]
                self.table[i, label] = torch.quantile(sel, q) if len(sel) else c.mean()

    def __call__(self, inp, chunk: int = 8):
        p, v, pos = inp.view_probs.float(), inp.view_valid.bool(), inp.view_positions
        la, g = self.la[pos], self.fusion.gamma
        ev = torch.where(v, calibrated_logit(p, self.area[pos], self.fusion.coef) - self.l0, torch.zeros_like(p))
        n_t = (((la[:, :, None] - la[:, None]).abs() < SAME_SCALE) & v[:, None]).sum(2).float()
        b = inp.fused.float().clamp(1e-6, 1 - 1e-6)
        now = (b > 0.5).float() * (2 * b - 1)
        out = torch.zeros(len(b), len(self.area))
        for c0 in range(0, len(self.area), chunk):
            cs = torch.arange(c0, min(c0 + chunk, len(self.area)))
            fc = self.foot[cs]
            same = (la[:, :, None] - self.la[cs][None, None]).abs() < SAME_SCALE
            m = (same & v[:, :, None] & fc[None, None]).float()
            base = self.l0 + (ev[:, :, None] / (n_t[:, :, None] + m) ** g).sum(1)  # the earlier views, recounted
            scale = (1.0 + m.sum(1)) ** -g
            after = base[..., None, None] + (self.table[self.bin[cs]][None] - self.l0) * scale[..., None, None]
            d = (after > 0).float().mean(-1)  # (B, C, N, label): P(positive after the view | label)
            bb = b[:, None]
            out[:, cs] = ((bb * d[..., 1] - (1 - bb) * d[..., 0] - now[:, None]) * fc[None].float()).sum(-1)
        return out


class CellTargets:
    """Per cell and layer (0: the lowest, 1: the top): the change of the cell's N_tp - N_fp after a view from that
    layer, averaged over the unvisited viewpoints of the layer that see it; and per viewpoint, the change of the
    map's N_tp - N_fp after its view (the label teacher's gain); reads the labels."""

    def __init__(self, cache, rows, fusion, config, chunk: int = 8):
        self.cache, self.fusion, self.chunk = cache, fusion, chunk
        self.rows = torch.as_tensor(np.asarray(rows), dtype=torch.long)
        self.labels = cache.occupancy[self.rows]
        self.foot = footprints(config).float()
        self.layer = (~lowest_layer(config)).long()
        self.state, self.fused, self.seen = None, None, 0

    def __call__(self, inp):
        for j in range(self.seen, inp.view_positions.shape[1]):
            self.state, self.fused = self.fusion.update(self.state, route_views(self.cache, self.rows,
                                                                                inp.view_positions[:, j:j + 1]))
        self.seen = inp.view_positions.shape[1]
        sign = 2 * self.labels.float() - 1
        now = (self.fused > 0.5).float() * sign
        B, P = inp.visited.shape
        total, count = torch.zeros(B, 2, now.shape[1]), torch.zeros(B, 2, now.shape[1])
        self.view_gains = torch.zeros(B, P)
        for c0 in range(0, P, self.chunk):
            cs = torch.arange(c0, min(c0 + self.chunk, P))
            k = len(cs)
            _, fused = self.fusion.update(repeat_state(self.state, k), route_views(
                self.cache, self.rows.repeat_interleave(k), cs.repeat(B)[:, None]))
            d = ((fused > 0.5).float() * sign.repeat_interleave(k, 0)).reshape(B, k, -1) - now[:, None]
            self.view_gains[:, cs] = d.sum(-1)
            w = self.foot[cs][None] * (~inp.visited[:, cs]).float()[..., None]  # (B, k, N)
            total.index_add_(1, self.layer[cs], d * w)
            count.index_add_(1, self.layer[cs], w)
        return total / count.clamp(min=1), count > 0


def per_layer_sum(gains, config):
    """(B, 2, N) per-cell gains of a view from each layer -> (B, P) the sum over each viewpoint's footprint."""
    foot = footprints(config).float()
    return torch.where(lowest_layer(config), gains[:, 0] @ foot.T, gains[:, 1] @ foot.T)


class CellNet(nn.Module):
    """The map policy's state and trunk, one output per cell and layer."""

    def __init__(self, config):
        super().__init__()
        self.map = MapPolicyNet(MapPolicyConfig(config_to_dict(config)))
        self.out = nn.Conv2d(self.map.cfg.cell_features, 2, 1)

    def forward(self, planes):
        return self.out(self.map.trunk(planes)).flatten(2)


def table_keys(planes) -> torch.Tensor:
    """(B, N) a cell's bin: fused p (26 logit bins) x top-layer views (0-3+) x low-layer views (0-2+)."""
    x = planes.flatten(2).float()
    i = MAP_PLANES.index
    lp = torch.logit(x[:, i("fused")].clamp(1e-6, 1 - 1e-6))
    top = (x[:, i("views_top")] * 4).round().clamp(max=3).long()
    low = (x[:, i("views_low")] * 4).round().clamp(max=2).long()
    return (torch.bucketize(lp, torch.linspace(-6, 6, 25)) * 4 + top) * 3 + low


def map_planes(config):
    """inp -> the map policy's planes (B, MAP_PLANES, n, n) of a state."""
    net = MapPolicyNet(MapPolicyConfig(config_to_dict(config)))
    return lambda inp: net.state(inp)[0]


def collect(train, fusion, config, rule, state, episodes: int, seed: int):
    """(planes, targets, mask) of every state of rule rollouts (30% random moves) on random training scenes, and
    (footprint features, viewpoint gains, allowed) of those after the survey; `state`: map_planes(config)."""
    gen = torch.Generator().manual_seed(seed)
    rows = torch.randint(train.num_scenes, (episodes,), generator=gen)
    targets = CellTargets(train, rows, fusion, config)
    X, Y, M, F, G, A = [], [], [], [], [], []

    noisy = NoisyRule(rule, 0.3, gen)

    class Recorder:
        def act(self, inp, generator=None):
            planes = state(inp)
            y, m = targets(inp)
            live = candidates(inp).any(1)
            X.append(planes[live].half()), Y.append(y[live]), M.append(m[live])
            if inp.step >= len(rule.survey):
                F.append(footprint_features(inp, config))
                G.append(targets.view_gains.clone())
                A.append(candidates(inp))
            return noisy.act(inp)

    with torch.no_grad():
        run_search(CachedViews(train, rows, config), Agent(fusion, Recorder()), generator=gen)
    return (torch.cat(X), torch.cat(Y), torch.cat(M)), (torch.cat(F), torch.cat(G), torch.cat(A))


def footprint_features(inp, config) -> torch.Tensor:
    """(B, P, 2f + 1) what a viewpoint's footprint holds: the two highest open p (open: no lowest-layer view has
    measured the cell), the sum of open p and of its square, the open cells above p 0.1 / 0.3 / 0.5 / 0.7, the
    cells above 0.5 measured from low and still open, the summed uncertainty 4p(1 - p), the cells no view has
    seen, the summed highest p any view gave the open cells, the flight time to it; once for lowest-layer
    viewpoints and once for the others, and which it is."""
    foot = footprints(config).float()
    lowest = lowest_layer(config)
    low = lowest.float()
    p, v = inp.fused.float(), inp.view_valid
    open_ = (~(lowest[inp.view_positions][..., None] & v).any(1)).float()
    po = p * open_
    top2 = (po[:, None] * foot[None]).topk(2, -1).values
    maxp = torch.where(v, inp.view_probs.float(), torch.zeros_like(inp.view_probs.float())).amax(1)
    f = [top2[..., 0], top2[..., 1], po @ foot.T, (po * po) @ foot.T]
    f += [(po > th).float() @ foot.T for th in (0.1, 0.3, 0.5, 0.7)]
    f += [((p > 0.5).float() * (1 - open_)) @ foot.T, ((p > 0.5).float() * open_) @ foot.T,
          (4 * p * (1 - p)) @ foot.T, (1 - v.any(1).float()) @ foot.T, (maxp * open_) @ foot.T,
          config.lattice.flight_time_t.float()[inp.lattice_idx] / 60]
    x = torch.stack(f, -1)
    is_low = low[None, :, None].expand(len(p), -1, 1)
    return torch.cat([x * is_low, x * (1 - is_low), is_low], -1)


RIDGE = 100.0  # fixed beforehand; 1 and 1e4 score alike on validation


def fit_linear(F, G, A) -> torch.Tensor:
    """Ridge regression of the label teacher's viewpoint gains on the footprint features (both less their mean
    over the state's allowed viewpoints, as a ranking needs): weights over standardised features."""
    n = A.sum(1, keepdim=True).clamp(min=1)
    Fc = torch.where(A[..., None], F, torch.zeros_like(F))
    Fc = (Fc - Fc.sum(1, keepdim=True) / n[..., None])[A].double()
    Gc = torch.where(A, G, torch.zeros_like(G))
    Gc = (Gc - Gc.sum(1, keepdim=True) / n)[A].double()
    sd = Fc.std(0) + 1e-9
    Z = Fc / sd
    w = torch.linalg.solve(Z.T @ Z + RIDGE * torch.eye(Z.shape[1], dtype=torch.double), Z.T @ Gc)
    return (w / sd).float()


def fit_table(X, Y, M) -> torch.Tensor:
    k = table_keys(X)
    K = 26 * 4 * 3
    tab = torch.zeros(2, K)
    for layer in range(2):
        m = M[:, layer]
        s = torch.zeros(K).index_add_(0, k[m], Y[:, layer][m])
        tab[layer] = s / torch.zeros(K).index_add_(0, k[m], torch.ones(int(m.sum()))).clamp(min=1)
    return tab


def fit_adam(net: nn.Module, n: int, loss, seed: int, epochs: int, lr: float, weight_decay: float,
             batch: int = 64) -> nn.Module:
    """Adam over `epochs` shuffled passes of n examples; loss(indices, generator) -> the minibatch's loss (the
    generator, seeded by `seed`, also shuffles)."""
    opt = torch.optim.Adam(net.parameters(), lr=lr, weight_decay=weight_decay)
    gen = torch.Generator().manual_seed(seed)
    fit_minibatches(opt, n, epochs, batch, gen, lambda b: (loss(b, gen), 0.0))
    return net.eval()


def fit_net(config, X, Y, M, seed: int, epochs: int = 8) -> CellNet:
    torch.manual_seed(seed)
    net = CellNet(config)

    def loss(b, gen):
        w = M[b].float()
        return ((net(X[b].float()) - Y[b]) ** 2 * w).sum() / w.sum().clamp(min=1)

    return fit_adam(net, len(X), loss, seed, epochs, lr=1e-3, weight_decay=1e-5)


def feature_auc(net_p, family: str, scenes: int, fusion) -> list[tuple[str, float, float]]:
    """Validation AUC of a cell-view's label from (calibrated log-odds, log area) and from those plus the cell
    features, over the cell-views whose calibrated p exceeds 0.05 and 0.2 (where a decision can hang on them)."""
    tr = get_view_cache(net_p, family, "large", "train", limit=scenes, progress=False)
    va = get_view_cache(net_p, family, "large", "val", limit=scenes, progress=False)

    def data(c, above):
        v = c.valid
        z = calibrated_logit(c.log_probs[..., 1].exp()[v].float(), c.cell_area_px[v].float(), fusion.coef)
        keep = torch.sigmoid(z) > above
        la = c.cell_area_px[v].float().clamp(min=1).log()[keep]
        base = torch.stack([z[keep], la, z[keep] * la], 1)
        return base, c.cell_features[v][keep].float(), c.occupancy[:, None].expand(v.shape)[v][keep].float()

    def auc(Xt, yt, Xv, yv):
        w = torch.zeros(Xt.shape[1], requires_grad=True)
        b0 = torch.zeros(1, requires_grad=True)
        opt = torch.optim.LBFGS([w, b0], max_iter=300, line_search_fn="strong_wolfe")

        def loss():
            opt.zero_grad()
            out = nn.functional.binary_cross_entropy_with_logits(Xt @ w + b0, yt) + 1e-4 * (w * w).sum()
            out.backward()
            return out

        opt.step(loss)
        with torch.no_grad():
            s = Xv @ w
        r = torch.empty_like(s)
        r[s.argsort()] = torch.arange(len(s), dtype=s.dtype)
        n1 = yv.sum()
        return float((r[yv > 0].sum() - n1 * (n1 - 1) / 2) / (n1 * (len(yv) - n1)))

    out = []
    for above in (0.05, 0.2):
        (bt, ft, yt), (bv, fv, yv) = data(tr, above), data(va, above)
        mu, sd = ft.mean(0), ft.std(0) + 1e-6
        out.append((f"calibrated p > {above:g} ({len(yv)} validation cell-views, {yv.mean():.0%} occupied)",
                    auc(bt, yt, bv, yv), auc(torch.cat([bt, (ft - mu) / sd], 1), yt,
                                              torch.cat([bv, (fv - mu) / sd], 1), yv)))
    return out


def probe_parser(doc: str) -> argparse.ArgumentParser:
    """The options every probe takes: the family, the budget and the report to write."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--family", default="wide")
    ap.add_argument("--budget", choices=("8", "240"), default="8", help="T = 8 views, or 240 s of flight")
    ap.add_argument("--out", required=True, help="markdown file to write")
    return ap


def probe_setting(family: str, budget: str, train_scenes: int):
    """(perception, training cache of the first `train_scenes`, validation cache, the budget's config, the
    learned policy's fusion fitted on the first 20 training scenes, the rule's variant chosen on validation, the
    rule): what every probe starts from. The caches show a bar only while they are built."""
    net_p, _ = load_perception(str(shipped_perception(family)))
    train = get_view_cache(net_p, family, "large", "train", features=False, limit=train_scenes)
    val = get_view_cache(net_p, family, "large", "val", features=False)
    config = budget_config(train.config, budget)
    fusion = make_fusion(FUSION[budget], train.subset(np.arange(min(20, train.num_scenes))))
    variant, _ = choose_rule(val, config, fusion)
    return net_p, train, val, config, fusion, variant, rule_policy(config, variant)


def main() -> None:
    ap = probe_parser(__doc__)
    ap.add_argument("--train-scenes", type=int, default=100, help="scenes the learned probes' rollouts draw from")
    ap.add_argument("--episodes", type=int, default=256, help="rule rollouts the learned probes fit")
    ap.add_argument("--feature-scenes", type=int, default=20, help="scenes of each part for the feature probe")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    net_p, train, val, config, fusion, variant, rule = probe_setting(args.family, args.budget, args.train_scenes)

    def scores(policy) -> np.ndarray:
        return evaluate_agent(val, Agent(fusion, policy), 1, config=config).f1[:, -1]

    bar = tqdm(total=10 + len(SHORTER_SURVEYS), desc="probes", unit="probe")
    rule_f1 = scores(rule)
    rows = []

    def row(name, policy):
        f1 = scores(policy)
        rows.append((name, float(f1.mean()), *bootstrap_ci(f1 - rule_f1, seed=args.seed)))
        bar.update()

    _, below, per_second = RULE_VARIANTS[variant]
    for name, survey in SHORTER_SURVEYS.items():
        row(f"the rule with a shorter survey: {name}", DescendRule(
            config, survey, resurvey_below=below if survey else max(below, 0.4),
            per_second_overhead_s=RULE_OVERHEAD_S if per_second else None))
    for name, reduce in DESCENT_SCORES.items():
        row(f"the rule, descent score: {name}", DescentScore(rule, reduce))
    row("expected gain of one view (calibrated evidence model), after the survey",
        AfterSurvey(rule, ExpectedGain(train, fusion, config), config))
    rule_state = map_planes(config)
    (X, Y, M), (F, G, A) = collect(train, fusion, config, rule, rule_state, args.episodes, args.seed)
    bar.update()
    tab = fit_table(X, Y, M)
    row(f"learned per-cell gains, table (fit on {len(X)} states)", AfterSurvey(rule, lambda inp: per_layer_sum(
        tab[:, table_keys(rule_state(inp))].permute(1, 0, 2), config), config))
    cell_net = fit_net(config, X, Y, M, args.seed)
    row(f"learned per-cell gains, conv net (the map policy's trunk; {len(X)} states)", AfterSurvey(
        rule, lambda inp: per_layer_sum(cell_net(rule_state(inp)), config), config))
    w = fit_linear(F, G, A)
    row(f"learned viewpoint gains, ridge regression on footprint features ({len(F)} states after the survey)",
        AfterSurvey(rule, lambda inp: footprint_features(inp, config) @ w, config))
    targets = CellTargets(val, np.arange(val.num_scenes), fusion, config)
    row("true per-cell gains, summed the same way (reads the labels; bound)",
        AfterSurvey(rule, lambda inp: per_layer_sum(targets(inp)[0], config), config))
    greedy = LabelLookahead(val, torch.arange(val.num_scenes), fusion, config)
    row("label-peeking greedy after the survey (bound)", AfterSurvey(rule, greedy.gains, config, per_second=False))
    bar.close()
    feats = feature_auc(net_p, args.family, args.feature_scenes, fusion)
    lines = [f"# Probes of the wide-area search's descents: {args.family}, {budget_text(config)}", "",
             f"{val.num_scenes} validation scenes, paired against the rule ({variant}; AF1 {rule_f1.mean():.3f}); "
             f"fusion {FUSION[args.budget]} fitted on the first 20 training scenes; learned probes fit on "
             f"{args.episodes} rollouts of the first {train.num_scenes} training scenes, seed {args.seed}. "
             f"Δ: per-scene final AF1 minus the rule's, mean [95% bootstrap interval over scenes]. "
             f"`python tools/wide_policy_probes.py --budget {args.budget}`", "",
             "| policy (after the rule's survey unless said) | AF1 | Δ vs the rule [95% CI] |", "|---|---|---|"]
    lines += [f"| {n} | {a:.3f} | {d:+.3f} [{lo:+.3f}, {hi:+.3f}] |" for n, a, d, lo, hi in rows]
    lines += ["", f"Does a cell-view's label show in perception's cell features beyond its p? Logistic regression "
              f"fitted on {args.feature_scenes} training scenes' views, AUC on {args.feature_scenes} validation "
              "scenes' views:", "", "| cell-views | calibrated log-odds + area | + cell features |", "|---|---|---|"]
    lines += [f"| {n} | {a:.3f} | {b:.3f} |" for n, a, b in feats]
    lines += ["", f"{time.perf_counter() - t0:.0f} s"]
    write_markdown(args.out, lines)


def write_markdown(path, lines: list[str]) -> None:
    """Write a probe's report and print it."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    print(f"wrote {display_path(out)}")


if __name__ == "__main__":
    main()
