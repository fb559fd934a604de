"""What Table II's rows are measured against: paired differences per scene, and how much any route could do.

Table II gives each row's mean over scenes with a spread over evaluation seeds; two rows within that spread
cannot be told apart, although both ran on the same scenes. Here:

- `paired_differences`: per test scene, a row's mean final AF1 (over its episodes and seeds) minus a
  reference row's on the same scene, averaged over scenes, with a 95% bootstrap interval over scenes
  (`bootstrap_ci`, seeded). Scene-to-scene difficulty cancels; what is left is the methods' difference.
- `route_bounds`: the hindsight-best route. For each scene the best final AF1 (learned fusion) over all
  A^(T-1) move sequences from the start (256 for the paper), run in batch through search_loop.run_search
  with `FixedRoutes`. No policy that moves on the same lattice with the same fusion beats it on a scene.
  Also the best single route for all scenes, and the coverage route's own per-scene AF1 from the same runs.
- `label_greedy_af1`: a second bound, a greedy that peeks at the labels (reactive.LabelGreedyTeacher).
- `hidden_shares`: how hard the testbed is before any policy: the share of occupied cells whose person
  shows no pixel from the start view (and from every lattice position).
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import numpy as np
import torch

from uavsearch.devices import follow, make_generator
from uavsearch.errors import UavsearchError

from ..config import SearchConfig
from ..fusion import Fusion
from ..metrics import RESAMPLES, bootstrap_ci, map_f1
from ..policy import coverage_route
from ..reactive import LabelGreedyTeacher
from ..search_loop import Agent, CachedViews, run_search

TIE = 1e-12  # per-scene AF1 differences smaller than this count as ties


def scene_af1(res: dict) -> np.ndarray:
    """(S,) per-scene mean final AF1 over episodes and seeds of one evaluated row ({"f1": (seeds, S*E, T),
    "scenes": S}; episodes are scene-major, as evaluate_agent runs them)."""
    f1 = np.asarray(res["f1"])[:, :, -1]
    S = int(res["scenes"])
    if f1.shape[1] % S:
        raise UavsearchError(f"{f1.shape[1]} episodes do not split evenly over {S} scenes")
    return f1.reshape(f1.shape[0], S, -1).mean((0, 2))


def paired_differences(res: dict[str, dict], references: tuple[str, ...], labels: dict[str, str],
                       resamples: int = RESAMPLES, seed: int = 0) -> list[dict]:
    """One dict per (row, reference present in `res`): the row's per-scene AF1 minus the reference's."""
    out = []
    per = {k: scene_af1(r) for k, r in res.items()}
    for ref in references:
        if ref not in per:
            continue
        for key, af1 in per.items():
            if key == ref:
                continue
            d = af1 - per[ref]
            mean, lo, hi = bootstrap_ci(d, resamples, seed)
            r = res[key]
            out.append({"key": key, "method": labels.get(key, key), "reference": ref, "scenes": len(d),
                        "seeds": int(r["f1"].shape[0]), "episodes_per_scene": int(r["f1"].shape[1]) // len(d),
                        "af1": float(af1.mean()), "reference_af1": float(per[ref].mean()), "diff": mean,
                        "ci_low": lo, "ci_high": hi, "wins": int((d > TIE).sum()), "ties": int((abs(d) <= TIE).sum()),
                        "losses": int((d < -TIE).sum()), "resamples": int(resamples), "bootstrap_seed": int(seed)})
    return out


# --------------------------------------------------------------------------------------------------
# Upper bounds: every fixed route, in hindsight


class FixedRoutes:
    """Episode b flies routes[b] (a search_loop.Policy); the enumeration behind route_bounds."""

    def __init__(self, routes):
        self.routes = torch.as_tensor(np.asarray(routes), dtype=torch.long)

    def act(self, inp, generator=None):
        follow(self, inp.lattice_idx.device)
        return self.routes[:, inp.step], None, None


def all_routes(config: SearchConfig, budget_T: int | None = None) -> np.ndarray:
    """(A^(T-1), T-1) every move sequence, in itertools.product order (route r = its base-A digits)."""
    T = int(budget_T or config.budget_T)
    return np.array(list(itertools.product(range(len(config.actions)), repeat=T - 1)), dtype=np.int64).reshape(-1, T - 1)


def route_index(route, num_actions: int) -> int:
    """Row of `route` in all_routes."""
    i = 0
    for a in route:
        i = i * num_actions + int(a)
    return i


@torch.no_grad()
def route_af1(cache, fusion: Fusion | None, config: SearchConfig | None = None,
              max_episodes: int = 8192) -> np.ndarray:
    """(S, R) final AF1 of every scene under every route of all_routes with `fusion` (learned fusion, as a rule),
    `max_episodes` episodes at a time."""
    config = config or cache.config
    if fusion is None:
        raise UavsearchError("the route bound needs a fusion (learned fusion with its confidence network)")
    if isinstance(fusion, torch.nn.Module):
        fusion.eval()
    conf = fusion.scorer
    routes = all_routes(config)
    S, R = cache.num_scenes, len(routes)
    out = np.empty((S, R))
    step = max(1, max_episodes // R)
    for s0 in range(0, S, step):
        s1 = min(S, s0 + step)
        rows = np.repeat(np.arange(s0, s1), R)
        ep = run_search(CachedViews(cache, rows, config, conf), Agent(fusion, FixedRoutes(np.tile(routes, (s1 - s0, 1)))),
                        config.budget_T)
        out[s0:s1] = map_f1(ep.maps[:, -1].cpu().numpy(), ep.labels.cpu().numpy()).reshape(s1 - s0, R)
    return out


class RouteBounds(NamedTuple):
    """What fixed routes can do on a set of scenes (all AF1 at the last view)."""

    best: np.ndarray  # (S,) hindsight-best route per scene
    best_route: np.ndarray  # (S, T-1) the move sequence achieving it (first in product order on ties)
    best_fixed: float  # mean AF1 of the single route best on average over the scenes
    best_fixed_route: tuple[int, ...]
    coverage: np.ndarray  # (S,) the coverage route (policy.coverage_route) from the same runs


def route_bounds(cache, fusion: Fusion | None, config: SearchConfig | None = None) -> RouteBounds:
    config = config or cache.config
    af1 = route_af1(cache, fusion, config)
    routes = all_routes(config)
    arg = af1.argmax(1)
    fixed = int(af1.mean(0).argmax())
    cov = route_index(coverage_route(config), len(config.actions))
    return RouteBounds(af1.max(1), routes[arg], float(af1.mean(0)[fixed]), tuple(int(a) for a in routes[fixed]),
                       af1[:, cov])


@torch.no_grad()
def label_greedy_af1(cache, fusion: Fusion, config: SearchConfig | None = None, seed: int = 0) -> np.ndarray:
    """(S,) final AF1 of the label-peeking greedy with learned fusion, one episode per scene."""
    config = config or cache.config
    rows = np.arange(cache.num_scenes)
    teacher = LabelGreedyTeacher(cache, rows, fusion.scorer, config)
    ep = run_search(CachedViews(cache, rows, config, fusion.scorer), Agent(fusion, teacher),
                    config.budget_T, generator=make_generator(seed, cache.occupancy.device))
    return map_f1(ep.maps[:, -1].cpu().numpy(), ep.labels.cpu().numpy())


def hidden_shares(cache, config: SearchConfig | None = None) -> tuple[float, float] | None:
    """(share of occupied cells with no person pixel in the start view, ... in any lattice view), or None for a
    cache without person_px."""
    if cache.person_px is None:
        return None
    occ = cache.occupancy.cpu().numpy().astype(bool)
    px = cache.person_px.cpu().numpy()
    n = max(int(occ.sum()), 1)
    start = px[:, (config or cache.config).lattice.start_index] == 0
    return float((start & occ).sum() / n), float(((px.max(1) == 0) & occ).sum() / n)


__all__ = ["FixedRoutes", "RouteBounds", "all_routes", "hidden_shares", "label_greedy_af1",
           "paired_differences", "route_af1", "route_bounds", "route_index", "scene_af1"]
