"""Policies of the wide-area search (any viewpoint next, a view and a time budget): Table III's baselines.

The action of every policy here is the next viewpoint's index (config.move_set "any"); each picks among
the viewpoints it may take (PolicyInput.allowed: unvisited and affordable in the time left; without a time
budget every unvisited one). A viewpoint's footprint is the cells it sees (lattice cell area >= the config's
min_cell_area_px).

- `RoutePolicy`: a fixed sequence of viewpoints (one for all episodes, or one per episode); past its end it
  stays (a revisit). Routes: `lawnmower` (boustrophedon over one 6 x 6 layer from its north-west corner),
  `survey_then_lawnmower` (given 70 m survey viewpoints, then the 40 m lawnmower), `greedy_view_set` (the
  route chosen greedily on training scenes) and `label_routes` (hindsight bounds that read the labels).
- `DescendRule`, the rule: fly the survey (the start, then `SURVEY_OUTER`: four 70 m viewpoints whose
  footprints cover the area); then repeatedly descend to the allowed lowest-layer viewpoint whose footprint
  holds the highest fused p among the cells no lowest-layer view has measured yet (ties: the larger mean of
  those cells, then the lower index); when no lowest-layer viewpoint is allowed, the same score over every
  allowed viewpoint. With `resurvey_below` it keeps surveying (the nearest allowed 70 m viewpoint) while no
  open cell is that likely to hold a person; with `per_second_overhead_s` it weighs each descent by the flight
  time to it.
- `EntropyPerSecond`: the allowed viewpoint with the most binary entropy of the fused map in its footprint
  per second of flight from here (lattice.flight_time_s).
- `MaskedRandom`: uniform over the allowed viewpoints (the caller's generator).
"""

from __future__ import annotations

import numpy as np
import torch

from uavsearch.devices import follow
from uavsearch.errors import UavsearchError

from .config import SearchConfig
from .fusion import Fusion, FusionViews
from .metrics import map_f1
from .search_loop import Agent, PolicyInput

SURVEY_OUTER_M = ((-37.5, 37.5), (37.5, 37.5), (37.5, -37.5), (-37.5, -37.5))  # 4 x 81 m footprints cover 150 m
SURVEY_INNER_M = ((-12.5, 12.5), (12.5, 12.5), (12.5, -12.5), (-12.5, -12.5))


def _need_any(config: SearchConfig) -> None:
    if config.move_set != "any":
        raise UavsearchError("wide-area policies choose viewpoints: they need a config with move_set='any'")


def candidates(inp: PolicyInput) -> torch.Tensor:
    """(B, P) bool: the viewpoints a policy may take next (affordable and unvisited, or just unvisited)."""
    return inp.allowed if inp.allowed is not None else ~inp.visited


def footprints(config: SearchConfig) -> torch.Tensor:
    """(P, N) bool: the cells each viewpoint sees."""
    return config.lattice.cell_areas >= config.min_cell_area_px


def lowest_layer(config: SearchConfig) -> torch.Tensor:
    """(P,) bool: the viewpoints of the lattice's lowest altitude layer (the close looks)."""
    alts = config.lattice.positions_enu[:, 2]
    return torch.as_tensor(alts == alts.min())


def viewpoints_at(config: SearchConfig, xy_m, altitude_m: float) -> list[int]:
    """Lattice indices of the viewpoints at these (east, north) positions and altitude."""
    lat = config.lattice
    out = []
    for x, y in xy_m:
        i = lat.nearest([x, y, altitude_m])
        if np.linalg.norm(lat.positions_enu[i] - [x, y, altitude_m]) > 1e-6:
            raise UavsearchError(f"no viewpoint at ({x:g}, {y:g}, {altitude_m:g}) m in this lattice")
        out.append(i)
    return out


def lawnmower(config: SearchConfig, altitude_m: float) -> list[int]:
    """Boustrophedon over one layer: rows north to south, alternating west->east and east->west."""
    lat = config.lattice
    layer = lat.altitudes_m.index(float(altitude_m))
    L = lat.size
    return [layer * L * L + r * L + (c if r % 2 == 0 else L - 1 - c) for r in range(L) for c in range(L)]


def survey_then_lawnmower(config: SearchConfig, survey_xy_m, low_m: float | None = None) -> list[int]:
    """The survey viewpoints at the start altitude, then the lawnmower of the lowest layer (default)."""
    low = min(config.lattice.altitudes_m) if low_m is None else low_m
    return viewpoints_at(config, survey_xy_m, config.layers_m[0]) + lawnmower(config, low)


class RoutePolicy:
    """Fly fixed viewpoints in order: `routes` (L,) for every episode or (B, L) per episode; -1 or past the
    end: stay (re-take the view)."""

    def __init__(self, routes):
        r = torch.as_tensor(np.asarray(routes), dtype=torch.long)
        self.routes = r[None] if r.dim() == 1 else r

    def act(self, inp: PolicyInput, generator=None):
        follow(self, inp.lattice_idx.device)
        B = inp.lattice_idx.shape[0]
        if inp.step >= self.routes.shape[1]:
            return inp.lattice_idx.clone(), None, None
        a = self.routes[:, inp.step].expand(B)
        return torch.where(a < 0, inp.lattice_idx, a), None, None


class MaskedRandom:
    """Uniform over the allowed viewpoints."""

    def __init__(self, config: SearchConfig):
        _need_any(config)

    def act(self, inp: PolicyInput, generator=None):
        w = candidates(inp).float()
        w[w.sum(1) == 0] = 1.0  # nothing allowed: the loop has ended these episodes anyway
        return torch.multinomial(w, 1, generator=generator).squeeze(-1), None, None


class NoisyRule:
    """A policy with a share `eps` of its moves replaced by random allowed ones, drawn from `gen`: varied states
    around the policy's own to fit on (the neighbour fusion's and the probes' training rollouts)."""

    def __init__(self, rule, eps: float, gen: torch.Generator):
        self.rule, self.eps, self.gen = rule, eps, gen

    def act(self, inp: PolicyInput, generator=None):
        a = self.rule.act(inp)[0]
        if not self.eps:
            return a, None, None
        w = candidates(inp).float()
        w[w.sum(1) == 0] = 1
        rnd = torch.multinomial(w, 1, generator=self.gen)[:, 0]
        return torch.where(torch.rand(len(a), generator=self.gen) < self.eps, rnd, a), None, None


def argmax_allowed(score: torch.Tensor, allowed: torch.Tensor) -> torch.Tensor:
    """The allowed index of the highest score, ties to the lowest index."""
    return torch.where(allowed, score, torch.full_like(score, -np.inf)).argmax(1)


class DescendRule:
    """Survey at 70 m, then descend over the viewpoint with the highest fused p (module docstring).

    `resurvey_below`: while no open cell under an allowed lowest-layer viewpoint has fused p at least this,
    take the nearest allowed top-layer viewpoint instead (keep surveying; 0: always descend). A time budget
    affords more views than the groups need: after the descents that find them, a 40 m look over an empty
    area adds its false alarms and little else, and another 70 m view finds the next group.
    `per_second_overhead_s`: choose the descent by its score per (flight time from here + this) instead of
    by its score alone (None); the overhead keeps a far bright spot worth more than a near dim one."""

    def __init__(self, config: SearchConfig, survey_xy_m=SURVEY_OUTER_M, resurvey_below: float = 0.0,
                 per_second_overhead_s: float | None = None):
        _need_any(config)
        self.survey = viewpoints_at(config, survey_xy_m, config.layers_m[0])
        self.foot = footprints(config).float()  # (P, N)
        alts = config.lattice.positions_enu[:, 2]
        self.low = lowest_layer(config)
        self.top = torch.as_tensor(alts == alts.max())
        self.resurvey_below = float(resurvey_below)
        self.overhead_s = per_second_overhead_s
        self.cost = config.lattice.flight_time_t.float()

    def act(self, inp: PolicyInput, generator=None):
        follow(self, inp.fused.device)
        if inp.step < len(self.survey):
            return torch.full_like(inp.lattice_idx, self.survey[inp.step]), None, None
        score, pick = self.descend_scores(inp)
        a = argmax_allowed(self.per_second(score, inp), pick)
        if self.resurvey_below <= 0.0:
            return a, None, None
        allowed = candidates(inp)
        low_ok, top_ok = allowed & self.low[None], allowed & self.top[None]
        best_low = torch.where(low_ok, score, torch.full_like(score, -1.0)).amax(1)
        nearest_top = argmax_allowed(-self.cost[inp.lattice_idx], top_ok)
        return torch.where((best_low < self.resurvey_below) & top_ok.any(1), nearest_top, a), None, None

    def per_second(self, score: torch.Tensor, inp: PolicyInput) -> torch.Tensor:
        """The descent scores per (second of flight from here + the overhead), or as they are without one."""
        if self.overhead_s is None:
            return score
        return score / (self.cost[inp.lattice_idx] + self.overhead_s).clamp(min=1.0)

    def descend_scores(self, inp: PolicyInput) -> tuple[torch.Tensor, torch.Tensor]:
        """(score (B, P), the viewpoints to pick among (B, P) bool) of the descent after the survey."""
        follow(self, inp.fused.device)
        allowed = candidates(inp)
        low_views = self.low[inp.view_positions][..., None] & inp.view_valid  # (B, t+1, N)
        open_ = (~low_views.any(1)).float()  # cells no low view has measured
        p = inp.fused * open_  # (B, N)
        best = (p[:, None, :] * self.foot[None]).amax(-1)  # (B, P)
        mean = (p @ self.foot.T) / self.foot.sum(1).clamp(min=1)
        low_ok = allowed & self.low[None]
        return best + 1e-3 * mean, torch.where(low_ok.any(1)[:, None], low_ok, allowed)


# The rule's variants (Table III chooses one on validation per family and budget): its survey (the 4 covering
# 70 m views, or those and the 4 inner ones: a time budget affords more survey, and the survey is what finds the
# groups to descend over), the fused p below which it keeps surveying instead of descending (0: always descend),
# and whether it weighs a descent by the flight time to it (per second of flight plus RULE_OVERHEAD_S).
RULE_SURVEYS = {"4 covering": SURVEY_OUTER_M, "4 covering + 4 inner": SURVEY_OUTER_M + SURVEY_INNER_M}
RULE_RESURVEY_BELOW = (0.0, 0.2, 0.3, 0.4, 0.5, 0.6)
RULE_OVERHEAD_S = 30.0  # about a descent's climb back and one move: a far bright spot still beats a near dim one
RULE_VARIANTS = {", ".join([s] + ([f"resurvey below p {t:g}"] if t else []) + (["per second"] if ps else [])): (s, t, ps)
                 for s in RULE_SURVEYS for t in RULE_RESURVEY_BELOW for ps in (False, True)}


def rule_policy(config: SearchConfig, variant: str) -> DescendRule:
    survey, below, per_second = RULE_VARIANTS[variant]
    return DescendRule(config, RULE_SURVEYS[survey], resurvey_below=below,
                       per_second_overhead_s=RULE_OVERHEAD_S if per_second else None)


@torch.no_grad()
def choose_rule(val, config: SearchConfig, fusion: Fusion) -> tuple[str, dict[str, float]]:
    """The rule's variant with the best mean final F1 (AF1) on a validation view cache (ties: the first listed,
    the simpler), and each variant's AF1."""
    from .scoring import evaluate_agent

    af1 = {k: float(evaluate_agent(val, Agent(fusion, rule_policy(config, k)), 1, config=config).f1[:, -1].mean())
           for k in RULE_VARIANTS}
    return max(RULE_VARIANTS, key=lambda k: (af1[k], -list(RULE_VARIANTS).index(k))), af1


def binary_entropy(p: torch.Tensor) -> torch.Tensor:
    q = p.clamp(1e-6, 1 - 1e-6)
    return -(q * q.log2() + (1 - q) * (1 - q).log2())


class EntropyPerSecond:
    """Most fused-map entropy in the footprint per second of flight."""

    def __init__(self, config: SearchConfig):
        _need_any(config)
        self.foot = footprints(config).float()
        self.cost = torch.as_tensor(config.lattice.flight_time_s, dtype=torch.float32)

    def act(self, inp: PolicyInput, generator=None):
        follow(self, inp.fused.device)
        gain = binary_entropy(inp.fused) @ self.foot.T  # (B, P)
        score = gain / self.cost[inp.lattice_idx].clamp(min=1.0)
        return argmax_allowed(score, candidates(inp)), None, None


# --------------------------------------------------------------------------------------------------
# Routes searched offline over a view cache: fixed view sets (training scenes) and hindsight bounds (labels)


def route_views(cache, rows: torch.Tensor, positions: torch.Tensor, features: bool = False) -> FusionViews:
    """FusionViews of views at `positions` (M, t) of scenes `rows` (M,); with `features` their cell features too
    (for a fusion that reads them)."""
    r = rows[:, None].expand_as(positions)
    return FusionViews(cache.log_probs[r, positions][..., 1].exp(), cache.valid[r, positions],
                       cache.cell_area_px[r, positions], cache.features_at(r, positions).float() if features else None,
                       viewpoints=positions, labels=cache.occupancy[rows])


def _check_fusion(fusion: Fusion) -> None:
    if fusion.trainable:
        raise UavsearchError("route search re-fuses views by their p: use a fusion without a confidence net")


def greedy_view_set(cache, fusion: Fusion, config: SearchConfig, per_second: bool = False) -> list[int]:
    """One route for all scenes, built greedily: each next viewpoint the one (reachable in the time left)
    that most raises the mean final AF1 over the cache's scenes (`per_second`: per second of flight)."""
    _check_fusion(fusion)
    lat = config.lattice
    cost = lat.flight_time_t
    S, P = cache.num_scenes, lat.num_positions
    dev = cache.occupancy.device
    rows = torch.arange(S, device=dev)
    y = cache.occupancy.cpu().numpy()
    route, here = [lat.start_index], lat.start_index
    left = float("inf") if config.budget_s is None else float(config.budget_s)
    base = map_f1(fusion.fuse(route_views(cache, rows, torch.tensor([route], device=dev).expand(S, -1))).cpu().numpy(),
                  y).mean()
    while len(route) < config.budget_T:
        cand = [c for c in range(P) if c not in route and float(cost[here, c]) <= left + 1e-9]
        if not cand:
            break
        pos = torch.tensor([route + [c] for c in cand], device=dev)  # (C, t+1)
        views = route_views(cache, rows.repeat(len(cand)), pos.repeat_interleave(S, 0))
        f1 = map_f1(fusion.fuse(views).cpu().numpy(), np.tile(y, (len(cand), 1))).reshape(len(cand), S).mean(1)
        gain = f1 - base
        if per_second:
            gain = gain / np.maximum(cost[here, cand].numpy(), 1.0)
        j = int(np.argmax(gain))
        left -= float(cost[here, cand[j]])
        here = cand[j]
        route.append(here)
        base = f1[j]
    return route[1:]


def label_routes(cache, fusion: Fusion, config: SearchConfig, beam: int = 1) -> torch.Tensor:
    """(S, L) per-scene routes that peek at the labels (-1 pads an early end): a beam search keeping the
    `beam` best partial routes by the AF1 of their fused map (ties: less flight time); beam = 1 is the
    label-peeking greedy. The best final map of any kept route is the hindsight bound."""
    _check_fusion(fusion)
    lat = config.lattice
    cost = lat.flight_time_s
    P, start = lat.num_positions, lat.start_index
    budget = float("inf") if config.budget_s is None else float(config.budget_s)
    out = []
    for s in range(cache.num_scenes):
        y = cache.occupancy[s].cpu().numpy()[None]
        states = [([start], budget, -np.inf)]  # (route, seconds left, AF1)
        done: list = []
        while states:
            grow = []
            for route, left, _ in states:
                if len(route) >= config.budget_T:
                    done.append((route, left, _))
                    continue
                cand = [c for c in range(P) if c not in route and cost[route[-1], c] <= left + 1e-9]
                if not cand:
                    done.append((route, left, _))
                    continue
                dev = cache.occupancy.device
                pos = torch.tensor([route + [c] for c in cand], device=dev)
                f1 = map_f1(fusion.fuse(route_views(cache, torch.full((len(cand),), s, device=dev), pos)).cpu().numpy(),
                            np.repeat(y, len(cand), 0))
                grow += [(route + [c], left - cost[route[-1], c], f) for c, f in zip(cand, f1)]
            grow.sort(key=lambda st: (-st[2], -st[1]))
            states = grow[:beam]
        best = max(done, key=lambda st: (st[2], st[1]))[0][1:]
        out.append(best)
    L = max(1, max(len(r) for r in out))
    return torch.tensor([r + [-1] * (L - len(r)) for r in out], dtype=torch.long)


__all__ = ["RULE_VARIANTS", "argmax_allowed", "choose_rule", "rule_policy", "DescendRule", "EntropyPerSecond", "MaskedRandom", "RoutePolicy", "SURVEY_INNER_M", "SURVEY_OUTER_M",
           "binary_entropy", "candidates", "footprints", "greedy_view_set", "label_routes", "lawnmower",
           "route_views", "survey_then_lawnmower", "viewpoints_at"]
