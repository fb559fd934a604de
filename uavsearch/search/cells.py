"""Search episodes stepped on per-cell views, batched: the state machine of the gymnasium environments.

The envs (search/envs/) and the external-policy adapter (external_policy.py) share
this module, so what a learner is trained on and what `uavsearch eval search` feeds it are one code path.
Nothing here imports gymnasium (flying and evaluation never load it).

- `CellTables`: every (scene, viewpoint) of a view cache as the fusion reads it: p(y=1), the valid mask
  (cell in view and pooled pixels > 0), the cell's pixel area and, for a learned fusion, the confidence
  scores, each scored once.
- `SearchBatch`: B episodes on a `ViewSource` (`TableSource`: the tables of cached scenes), stepped with one
  array operation per step: the episode engine (episode.SearchState) that run_search and run_team step too,
  with its map in fixed (B, T, N) buffers so that episodes start and end on their own; the action set's move
  rule; the rewards are `search_loop.step_rewards`.
- `cells_observation`: the "cells" observation (map-shaped arrays) from those arrays; `external_policy`
  builds the same dict from a `search_loop.PolicyInput`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from uavsearch.errors import UavsearchError

from .config import SearchConfig
from .fusion import Fusion
from .metrics import map_accuracy, map_f1
from .episode import SLACK_S, Observation, SearchState, ViewSource
from .search_loop import R_FP, R_RE, R_TP, step_rewards

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


class TableSource:
    """Episodes on cached scenes (a ViewSource): episode b reads row `rows[b]` of the tables."""

    def __init__(self, tables: CellTables, batch_size: int):
        self.tables = tables
        self.device = tables.p.device  # the tables': every tensor of its episodes lives there
        self.rows = torch.zeros(batch_size, dtype=torch.long, device=self.device)
        self.batch_size = batch_size

    def observe(self, lattice_idx) -> Observation:
        t, r = self.tables, self.rows
        return Observation(None, None, None, t.area_px[r, lattice_idx], t.valid[r, lattice_idx],
                           None if t.scores is None else t.scores[r, lattice_idx], t.p[r, lattice_idx])


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
        return torch.as_tensor(x).reshape(B, n, n).cpu().numpy().astype(np.float32)

    valid = torch.as_tensor(valid).bool()
    step = torch.as_tensor(step).long().clamp(max=T - 1)
    out = {
        "cell_views": grid(cell_views),
        "fused": grid(fused),
        "in_view": grid(valid),
        "p_view": grid(torch.where(valid, torch.as_tensor(p_view).float(), 0.0)),
        "position": torch.nn.functional.one_hot(torch.as_tensor(idx).long(), P).float().cpu().numpy(),
        "step": torch.nn.functional.one_hot(step, T).float().cpu().numpy(),
        "visits": torch.as_tensor(visits).cpu().numpy().astype(np.float32),
    }
    if config.budget_s is not None:
        out["action_mask"] = torch.as_tensor(allowed).cpu().numpy().astype(np.float32)
        out["time_left_s"] = torch.as_tensor(time_left_s).reshape(B, 1).cpu().numpy().astype(np.float32)
    return {k: out[k] for k in observation_keys(config)}


def flatten_cells(obs: dict[str, np.ndarray]) -> np.ndarray:
    """(B, F) float32: a batch of "cells" observations flattened in key order (gymnasium.spaces.flatten of one)."""
    B = next(iter(obs.values())).shape[0]
    return np.concatenate([np.asarray(obs[k], np.float32).reshape(B, -1) for k in obs], axis=1)


class SearchBatch:
    """B search episodes of the envs, stepped together (see the module docstring); episodes start and end
    independently. A skin over the episode engine (episode.SearchState, buffered): the move rule of the action
    set, the env's rewards and observation."""

    def __init__(self, config: SearchConfig, fusion: Fusion, batch_size: int, reward: str = "terminal",
                 r_tp: float = R_TP, r_fp: float = R_FP, r_re: float = R_RE, device="cpu"):
        if reward not in REWARD_MODES:
            raise UavsearchError(f"unknown reward mode {reward!r}; valid: {', '.join(REWARD_MODES)}")
        self.config, self.fusion, self.reward_mode = config, fusion, reward
        self.r = {"r_tp": float(r_tp), "r_fp": float(r_fp), "r_re": float(r_re)}
        self.device = dev = torch.device(device)
        self.state = SearchState(config, fusion, batch_size, buffered=True, device=dev)
        self.B, self.T, self.N, self.P = batch_size, config.budget_T, config.grid.num_cells, config.lattice.num_positions
        self.revisit = torch.zeros(self.B, dtype=torch.bool, device=dev)
        self.done = torch.zeros(self.B, dtype=torch.bool, device=dev)
        self._lead = torch.zeros(self.B, dtype=torch.long, device=dev)  # the one vehicle
        self.source: ViewSource | None = None

    # what the envs read of the state
    @property
    def idx(self) -> torch.Tensor:
        """(B,) the viewpoint of each episode's latest view."""
        return self.state.pos[:, 0]

    @property
    def t(self) -> torch.Tensor:
        """(B,) the index of each episode's latest view."""
        return self.state.views - 1

    @property
    def fused(self) -> torch.Tensor:
        return self.state.fused

    @property
    def labels(self) -> torch.Tensor:
        return self.state.labels

    @property
    def allowed(self) -> torch.Tensor:
        return self.state.allowed

    @property
    def visits(self) -> torch.Tensor:
        return self.state.visits

    # ----------------------------------------------------------------------------------------------
    @torch.no_grad()
    def start(self, envs, labels) -> None:
        """Start episodes `envs` (k,) with ground truth `labels` (k, N) bool (their source is set already)."""
        envs = torch.as_tensor(envs, dtype=torch.long, device=self.device).reshape(-1)
        st = self.state
        st.restart(envs, torch.as_tensor(labels, device=self.device).bool().reshape(len(envs), -1))
        self.revisit[envs] = False
        mask = torch.zeros(self.B, dtype=torch.bool, device=self.device)
        mask[envs] = True
        st.take(self.source, mask=mask)
        self.done[envs] = st.ended()[envs]

    @torch.no_grad()
    def step(self, actions, active=None) -> tuple[torch.Tensor, torch.Tensor]:
        """Move the `active` episodes (default all) by `actions` (B,): (rewards (B,) float32, terminated (B,) bool);
        inactive episodes are left as they are, with reward 0."""
        st = self.state
        dev = self.device
        actions = torch.as_tensor(np.asarray(actions), dtype=torch.long, device=dev).reshape(-1)
        act = torch.ones(self.B, dtype=torch.bool, device=dev) if active is None else \
            torch.as_tensor(active, device=dev).bool().clone()
        if bool((self.done & act).any()):
            raise UavsearchError("an episode that has ended was stepped; start it again first")
        first = act & (self.t == 0)
        prev = st.fused.clone()
        idx, now = st.pos[:, 0], st.clock_s[:, 0]
        nxt = st.moves[idx, actions.clamp(0, st.moves.shape[1] - 1)]
        cant = torch.zeros(self.B, dtype=torch.bool, device=dev)
        if st.timed:  # a move it cannot afford ends the episode where it is (run_search's rule)
            cant = act & (st.cost_s[idx, nxt] > st.time_left_s(now) + SLACK_S)
        move = act & ~cant
        st.fly(self._lead, nxt, move, now)
        self.revisit = torch.zeros(self.B, dtype=torch.bool, device=dev)
        terminated = cant.clone()
        if bool(move.any()):
            _, self.revisit = st.take(self.source, mask=move)
            terminated |= move & st.ended()
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
        st, t = self.state, self.t
        last = t[:, None, None].expand(-1, 1, self.N)
        p = st.hist_p.gather(1, last)[:, 0]
        valid = st.hist_valid.gather(1, last)[:, 0]
        return cells_observation(self.config, p, valid, st.fused, st.hist_valid.sum(1), st.visits, st.pos[:, 0], t,
                                 st.time_left_s(st.clock_s[:, 0]) if st.timed else None,
                                 st.allowed if st.timed else None)

    def scores(self) -> dict[str, np.ndarray]:
        """Per episode: Aacc and F1 of the fused map (search/metrics.py), and the ground truth."""
        fused, labels = self.fused.cpu().numpy(), self.labels.cpu().numpy()
        return {"f1": map_f1(fused, labels), "acc": map_accuracy(fused, labels)}


__all__ = ["REWARD_MODES", "CellTables", "SearchBatch", "TableSource", "cell_tables", "cells_observation",
           "flatten_cells", "observation_keys"]
