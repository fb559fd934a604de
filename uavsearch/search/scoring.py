"""Scoring episodes: what training (validation), evaluation (the tables) and flying (a mission's score)
all measure, in one place, so the trainers and the evaluations never import each other."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from tqdm import tqdm

from uavsearch.devices import make_generator

from .config import SearchConfig
from .fusion import DEFAULT_PRIOR
from .metrics import map_accuracy, map_f1
from .perception import PerceptionNet
from .search_loop import Agent, CachedViews, Episode, run_search


class EpisodeScores(NamedTuple):
    """Per-episode, per-step map metrics of one method: (E, T) each."""
    acc: np.ndarray
    f1: np.ndarray
    revisit_rate: float


def score_episode(ep: Episode) -> EpisodeScores:
    maps = ep.maps.detach().cpu().numpy()
    y = ep.labels.cpu().numpy()
    T = maps.shape[1]
    acc = np.stack([map_accuracy(maps[:, t], y) for t in range(T)], 1)
    f1 = np.stack([map_f1(maps[:, t], y) for t in range(T)], 1)
    return EpisodeScores(acc, f1, float(ep.revisit[:, 1:].float().mean()) if T > 1 else 0.0)


@torch.no_grad()
def evaluate_agent(cache, agent: Agent, episodes_per_scene: int = 10, seed: int = 0, config: SearchConfig | None = None,
                   budget_T: int | None = None, single_view: bool = False) -> EpisodeScores:
    """Run `episodes_per_scene` episodes on every scene of the cache (on the cache's device); the generator is seeded
    by `seed`."""
    for m in (agent.fusion, getattr(agent.policy, "net", agent.policy)):
        if isinstance(m, torch.nn.Module):
            m.eval()
    rows = np.repeat(np.arange(cache.num_scenes), episodes_per_scene)
    gen = make_generator(seed, cache.occupancy.device)
    ep = run_search(CachedViews(cache, rows, config, agent.fusion.scorer), agent, 1 if single_view else budget_T, generator=gen)
    return score_episode(ep)


# --------------------------------------------------------------------------------------------------


@torch.no_grad()
def predict_views(net: PerceptionNet, views, batch_size: int = 64, progress: bool = False):
    """Single-view occupancy maps p(y=1) (V, N*N) with the prior where a cell is out of view, + pixels."""
    net.eval()
    probs, pixels = [], []
    for i in tqdm(range(0, len(views), batch_size), desc="predict", disable=not progress, leave=False):
        rows = np.arange(i, min(i + batch_size, len(views)))
        out = net.forward_all(views.images[rows], views.label_images(rows), altitude_m=views.position_enu[rows, 2])
        probs.append(out.log_probs[..., 1].exp().cpu().numpy())
        pixels.append(out.cell_pixels.cpu().numpy())
    p, px = np.concatenate(probs), np.concatenate(pixels)
    p = np.where(views.cells_in_view, p, DEFAULT_PRIOR)
    return p, px


__all__ = ["EpisodeScores", "evaluate_agent", "predict_views", "score_episode"]
