"""Search episodes stepped on per-cell views, batched: the state machine of the gymnasium environments.

The envs (search/envs/) and the external-policy adapter (external_policy.py) share
this module, so what a learner is trained on and what `uavsearch eval search` feeds it are one code path.
Nothing here imports gymnasium (flying and evaluation never load it).

- `CellTables`: every (scene, viewpoint) of a view cache as the fusion reads it: p(y=1), the valid mask
  (cell in view and pooled pixels > 0), the cell's pixel area and, for a learned fusion, the confidence
  scores, each scored once.
- `SearchBatch`: B episodes on a `ViewSource`, stepped with one array operation per step. Moves, revisits and
  the time budget follow `search_loop.run_search` (the lattice's move table; `search_loop.affordable`);
  the fused map is the fusion object's `fuse` over each episode's views so far (fixed (B, T, N) buffers,
  views not yet taken masked out, which gives run_search's maps); the rewards are `search_loop.step_rewards`.
- `cells_observation`: the "cells" observation (map-shaped arrays) from those arrays; `external_policy`
  builds the same dict from a `search_loop.PolicyInput`.
"""

from __future__ import annotations

from typing import NamedTuple, Protocol

import numpy as np
import torch

from uavsearch.errors import UavsearchError

from .config import SearchConfig
from .fusion import Fusion, FusionViews
from .metrics import map_accuracy, map_f1
from .search_loop import R_FP, R_RE, R_TP, affordable, step_rewards

REWARD_MODES = ("terminal", "shaped")


class CellTables(NamedTuple):
    """The per-cell view tables of S scenes at P viewpoints (N cells each)."""

    p: torch.Tensor  # (S, P, N) float32 p(y=1) of the view
    valid: torch.Tensor  # (S, P, N) bool, the view measured the cell
    area_px: torch.Tensor  # (S, P, N) float32 F_size
    scores: torch.Tensor | None  # (S, P, N) float32 confidence scores (learned fusion), else None
    labels: torch.Tensor  # (S, N) bool ground truth
    scene_seed: np.ndarray  # (S,) int64
    occupied_cells: np.ndarray  # (S,) int64


@torch.no_grad()
def cell_tables(cache, fusion: Fusion, chunk: int = 4096) -> CellTables:
    """The tables of a view_cache.ViewCache; a fusion with a scorer (learned) scores every view's cells once."""
    p = cache.log_probs[..., 1].exp().float()
    scores = None
    if fusion.scorer is not None:
        feats = cache.cell_features
        if feats.shape[-1] == 0:
            raise UavsearchError(f"{fusion.name} fusion needs the cache's cell features (load it with features)")
        net = fusion.frozen().scorer
        flat = feats.reshape(-1, *feats.shape[2:])
        scores = torch.cat([net(flat[i:i + chunk].float()) for i in range(0, len(flat), chunk)]).reshape(p.shape)
    return CellTables(p, cache.valid.bool(), cache.cell_area_px.float(), scores, cache.occupancy.bool(),
                      np.asarray(cache.scene_seed), np.asarray(cache.occupied_cells))


class ViewCells(NamedTuple):
    """What the fusion reads of k views (k, N) each."""

    p: torch.Tensor
    valid: torch.Tensor
    area_px: torch.Tensor
    scores: torch.Tensor | None


class ViewSource(Protocol):
    """Where an episode's views come from: `cells(envs, idx)` for episodes `envs` (k,) at viewpoints `idx`."""

    def cells(self, envs: torch.Tensor, idx: torch.Tensor) -> ViewCells: ...


class TableSource:
    """Episodes on cached scenes: episode b reads row `rows[b]` of the tables."""

    def __init__(self, tables: CellTables, batch_size: int):
        self.tables = tables
        self.rows = torch.zeros(batch_size, dtype=torch.long)

    def cells(self, envs, idx) -> ViewCells:
        t, r = self.tables, self.rows[envs]
        return ViewCells(t.p[r, idx], t.valid[r, idx], t.area_px[r, idx], None if t.scores is None else t.scores[r, idx])


def observation_keys(config: SearchConfig) -> tuple[str, ...]:
    """The "cells" observation's keys, sorted (gymnasium's Dict space sorts a dict's keys; flattening follows it)."""
    keys = ["cell_views", "fused", "in_view", "p_view", "position", "step", "visits"]
    if config.budget_s is not None:
        keys += ["action_mask", "time_left_s"]
    return tuple(sorted(keys))


def cells_observation(config: SearchConfig, p_view, valid, fused, cell_views, visits, idx, step,
                      time_left_s=None, allowed=None) -> dict[str, np.ndarray]:
    """The "cells" observation of B episodes, float32 numpy, map-shaped fields (B, n, n) with n the grid side.

    p_view (B, N) the view's p(y=1) (0 where it measured nothing), valid (B, N) bool, fused (B, N), cell_views
    (B, N) views that measured each cell so far, visits (B, P) views taken at each viewpoint, idx (B,) long
    viewpoint, step (B,) long view index; with a time budget time_left_s (B,) and allowed (B, P) bool.
    """
    B, n = int(fused.shape[0]), config.grid.n
    P, T = config.lattice.num_positions, config.budget_T

    def grid(x):  # new arrays: callers keep what they are given, the episode state moves on
        return torch.as_tensor(x).reshape(B, n, n).numpy().astype(np.float32)

    valid = torch.as_tensor(valid).bool()
    step = torch.as_tensor(step).long().clamp(max=T - 1)
    out = {
        "cell_views": grid(cell_views),
        "fused": grid(fused),
        "in_view": grid(valid),
        "p_view": grid(torch.where(valid, torch.as_tensor(p_view).float(), 0.0)),
        "position": torch.nn.functional.one_hot(torch.as_tensor(idx).long(), P).float().numpy(),
        "step": torch.nn.functional.one_hot(step, T).float().numpy(),
        "visits": torch.as_tensor(visits).numpy().astype(np.float32),
    }
    if config.budget_s is not None:
        out["action_mask"] = torch.as_tensor(allowed).numpy().astype(np.float32)
        out["time_left_s"] = torch.as_tensor(time_left_s).reshape(B, 1).numpy().astype(np.float32)
    return {k: out[k] for k in observation_keys(config)}


def flatten_cells(obs: dict[str, np.ndarray]) -> np.ndarray:
    """(B, F) float32: a batch of "cells" observations flattened in key order (gymnasium.spaces.flatten of one)."""
    B = next(iter(obs.values())).shape[0]
    return np.concatenate([np.asarray(obs[k], np.float32).reshape(B, -1) for k in obs], axis=1)


class SearchBatch:
    """B search episodes, stepped together (see the module docstring); episodes start and end independently."""

    def __init__(self, config: SearchConfig, fusion: Fusion, batch_size: int, reward: str = "terminal",
                 r_tp: float = R_TP, r_fp: float = R_FP, r_re: float = R_RE):
        if reward not in REWARD_MODES:
            raise UavsearchError(f"unknown reward mode {reward!r}; valid: {', '.join(REWARD_MODES)}")
        self.config, self.fusion, self.reward_mode = config, fusion, reward
        self.r = {"r_tp": float(r_tp), "r_fp": float(r_fp), "r_re": float(r_re)}
        B, T, N, P = batch_size, config.budget_T, config.grid.num_cells, config.lattice.num_positions
        self.B, self.T, self.N, self.P = B, T, N, P
        self.moves = config.lattice.moves
        self.timed = config.budget_s is not None
        self.flight_s = config.lattice.flight_time_t if self.timed else None
        self.idx = torch.full((B,), config.lattice.start_index, dtype=torch.long)
        self.t = torch.zeros(B, dtype=torch.long)
        self.visits = torch.zeros(B, P, dtype=torch.long)
        # float64 views: the fused map then rounds to the same float32 whatever the batch's size and layout (a
        # vector env equals its single envs bit for bit)
        self.hist_p = torch.zeros(B, T, N, dtype=torch.float64)
        self.hist_valid = torch.zeros(B, T, N, dtype=torch.bool)
        self.hist_area = torch.zeros(B, T, N, dtype=torch.float64)
        self.hist_scores = torch.zeros(B, T, N, dtype=torch.float64)
        self.fused = torch.full((B, N), float(fusion.prior))
        self.labels = torch.zeros(B, N, dtype=torch.bool)
        self.time_left = torch.zeros(B, dtype=torch.float64)
        self.allowed = torch.ones(B, P, dtype=torch.bool)
        self.revisit = torch.zeros(B, dtype=torch.bool)
        self.done = torch.zeros(B, dtype=torch.bool)
        self._ar = torch.arange(B)
        self.source: ViewSource | None = None

    # ----------------------------------------------------------------------------------------------
    def _take(self, envs: torch.Tensor, idx: torch.Tensor) -> None:
        """Episodes `envs` take their next view (index t) at viewpoints `idx` and re-fuse."""
        c = self.source.cells(envs, idx)
        t = self.t[envs]
        self.hist_p[envs, t], self.hist_valid[envs, t] = c.p.double(), c.valid
        self.hist_area[envs, t] = c.area_px.double()
        if c.scores is not None:
            self.hist_scores[envs, t] = c.scores.double()
        views = FusionViews(self.hist_p[envs], self.hist_valid[envs], self.hist_area[envs],
                            scores=self.hist_scores[envs] if c.scores is not None else None, labels=self.labels[envs])
        self.fused[envs] = self.fusion.fuse(views).float()
        self.visits[envs, idx] += 1

    def _ended(self, envs: torch.Tensor) -> torch.Tensor:
        """After a view: the budget of views is spent, or (time budget) no unvisited viewpoint is affordable."""
        end = self.t[envs] >= self.T - 1
        if self.timed:
            self.allowed[envs] = affordable(self.config, self.idx[envs], self.visits[envs] > 0, self.time_left[envs])
            end = end | ~self.allowed[envs].any(1)
        return end

    @torch.no_grad()
    def start(self, envs, labels) -> None:
        """Start episodes `envs` (k,) with ground truth `labels` (k, N) bool (their source is set already)."""
        envs = torch.as_tensor(envs, dtype=torch.long).reshape(-1)
        self.idx[envs] = self.config.lattice.start_index
        self.t[envs] = 0
        for buf in (self.visits, self.hist_p, self.hist_valid, self.hist_area, self.hist_scores):
            buf[envs] = 0
        self.labels[envs] = torch.as_tensor(labels).bool().reshape(len(envs), -1)
        if self.timed:
            self.time_left[envs] = float(self.config.budget_s)
        self.revisit[envs] = False
        self._take(envs, self.idx[envs])
        self.done[envs] = self._ended(envs)

    @torch.no_grad()
    def step(self, actions, active=None) -> tuple[torch.Tensor, torch.Tensor]:
        """Move the `active` episodes (default all) by `actions` (B,): (rewards (B,) float32, terminated (B,) bool);
        inactive episodes are left as they are, with reward 0."""
        actions = torch.as_tensor(np.asarray(actions), dtype=torch.long).reshape(-1)
        act = torch.ones(self.B, dtype=torch.bool) if active is None else torch.as_tensor(active).bool().clone()
        if bool((self.done & act).any()):
            raise UavsearchError("an episode that has ended was stepped; start it again first")
        first = act & (self.t == 0)
        prev = self.fused.clone()
        nxt = self.moves[self.idx, actions.clamp(0, self.moves.shape[1] - 1)]
        cant = torch.zeros(self.B, dtype=torch.bool)
        if self.timed:  # a move it cannot afford ends the episode where it is (run_search's rule)
            cost = self.flight_s[self.idx, nxt]
            cant = act & (cost > self.time_left + 1e-9)
            self.time_left = torch.where(act & ~cant, self.time_left - cost, self.time_left)
        move = act & ~cant
        self.revisit = move & (self.visits[self._ar, nxt] > 0)
        envs = move.nonzero().reshape(-1)
        terminated = cant.clone()
        if len(envs):
            self.idx[envs] = nxt[envs]
            self.t[envs] += 1
            self._take(envs, nxt[envs])
            terminated[envs] = self._ended(envs)
        self.done |= terminated
        return self._rewards(prev, act, first, terminated), terminated

    def _rewards(self, prev, act, first, terminated) -> torch.Tensor:
        r, rev = self.r, self.revisit
        if self.reward_mode == "terminal":
            last = step_rewards(self.fused[:, None], self.labels, rev[:, None], **r)[:, 0]
            out = torch.where(terminated, last, step_rewards(None, None, rev, **r))
        else:  # shaped: R_cls as it accrues; the start view's share comes with the first step
            maps = torch.stack([prev, self.fused], 1)
            out = step_rewards(maps, self.labels, torch.stack([torch.zeros_like(rev), rev], 1), shaped=True, **r)
            out = out[:, 1] + torch.where(first, out[:, 0], 0.0)
        return torch.where(act, out, 0.0).float()

    # ----------------------------------------------------------------------------------------------
    def observation(self) -> dict[str, np.ndarray]:
        """The "cells" observation of every episode (its latest view)."""
        last = self.t[:, None, None].expand(-1, 1, self.N)
        p = self.hist_p.gather(1, last)[:, 0]
        valid = self.hist_valid.gather(1, last)[:, 0]
        return cells_observation(self.config, p, valid, self.fused, self.hist_valid.sum(1), self.visits, self.idx,
                                 self.t, self.time_left if self.timed else None, self.allowed if self.timed else None)

    def scores(self) -> dict[str, np.ndarray]:
        """Per episode: Aacc and F1 of the fused map (search/metrics.py), and the ground truth."""
        fused, labels = self.fused.numpy(), self.labels.numpy()
        return {"f1": map_f1(fused, labels), "acc": map_accuracy(fused, labels)}


__all__ = ["REWARD_MODES", "CellTables", "SearchBatch", "TableSource", "ViewCells", "cell_tables", "cells_observation",
           "flatten_cells", "observation_keys"]
