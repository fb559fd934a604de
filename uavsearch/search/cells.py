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

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import torch

from uavsearch.errors import UavsearchError

from .config import SearchConfig
from .fusion import Fusion
from .metrics import map_accuracy, map_f1
from .episode import SLACK_S, Observation, SearchState, ViewSource, host
from .search_loop import R_FP, R_RE, R_TP

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
    # (rows, positions) -> (..., N, D) the views' cell features (ViewCache.features_at), for a fusion that reads
    # them (a learned aggregation), else None: read view by view, a scene family's stay on disk
    features: Callable | None = None


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
                      np.asarray(cache.scene_seed), np.asarray(cache.occupied_cells),
                      cache.features_at if "cell_features" in fusion.needs else None)


class TableSource:
    """Episodes on cached scenes (a ViewSource): episode b reads row `rows[b]` of the tables."""

    def __init__(self, tables: CellTables, batch_size: int):
        self.tables = tables
        self.device = tables.p.device  # the tables': every tensor of its episodes lives there
        self._rows = np.zeros(batch_size, dtype=np.int64)
        self.rows = torch.as_tensor(self._rows, device=self.device)  # on the CPU, the same memory as _rows
        self._shared = self.rows.device.type == "cpu" and self.rows.data_ptr() == self._rows.ctypes.data
        self.batch_size = batch_size
        self._host: tuple | None = None

    def host_tables(self) -> tuple:
        """(area_px, valid, scores or None, p, labels) as numpy arrays on the host (copied once from a device;
        on the CPU they share the tables' memory)."""
        if self._host is None:
            t = self.tables
            self._host = tuple(None if x is None else host(x) for x in (t.area_px, t.valid, t.scores, t.p, t.labels))
        return self._host

    def host_rows(self) -> np.ndarray:
        """(B,) the table row of each episode, numpy."""
        return self._rows if self._shared else host(self.rows)

    def set_rows(self, envs: np.ndarray, rows: np.ndarray) -> None:
        """Episodes `envs` read table rows `rows` from now on (in numpy where `rows` shares its memory)."""
        if self._shared:
            self._rows[envs] = rows
        else:
            self.rows[torch.as_tensor(envs, device=self.device)] = torch.as_tensor(rows, device=self.device)

    def observe_host(self, lattice_idx: np.ndarray) -> Observation:
        """`observe` in numpy (a buffered SearchState's views, episode.py)."""
        area, valid, scores, p, _ = self.host_tables()
        r = self.host_rows()
        feats = self.tables.features
        f = None if feats is None else host(feats(r, lattice_idx)).astype(np.float32)
        return Observation(None, f, None, area[r, lattice_idx], valid[r, lattice_idx],
                           None if scores is None else scores[r, lattice_idx], p[r, lattice_idx])

    def observe(self, lattice_idx) -> Observation:
        t, r = self.tables, self.rows
        f = None if t.features is None else t.features(r.cpu(), torch.as_tensor(lattice_idx).cpu()).float().to(
            self.device)
        return Observation(None, f, None, t.area_px[r, lattice_idx], t.valid[r, lattice_idx],
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
    viewpoint, step (B,) long view index; with a time budget time_left_s (B,) and allowed (B, P) bool. Tensors
    (any device) or numpy arrays; built in numpy (episode.py says why).
    """
    B, n = int(fused.shape[0]), config.grid.n
    P, T = config.lattice.num_positions, config.budget_T

    def grid(x):  # new arrays: callers keep what they are given, the episode state moves on
        return host(x).reshape(B, n, n).astype(np.float32)

    valid = host(valid).astype(bool)
    step = np.minimum(host(step).astype(np.int64), T - 1)
    out = {
        "cell_views": grid(cell_views),
        "fused": grid(fused),
        "in_view": grid(valid),
        "p_view": grid(np.where(valid, host(p_view).astype(np.float32), np.float32(0.0))),
        "position": np.eye(P, dtype=np.float32)[host(idx).astype(np.int64)],
        "step": np.eye(T, dtype=np.float32)[step],
        "visits": host(visits).astype(np.float32),
    }
    if config.budget_s is not None:
        out["action_mask"] = host(allowed).astype(np.float32)
        out["time_left_s"] = host(time_left_s).reshape(B, 1).astype(np.float32)
    return {k: out[k] for k in observation_keys(config)}


def flatten_cells(obs: dict[str, np.ndarray]) -> np.ndarray:
    """(B, F) float32: a batch of "cells" observations flattened in key order (gymnasium.spaces.flatten of one)."""
    B = next(iter(obs.values())).shape[0]
    return np.concatenate([np.asarray(obs[k], np.float32).reshape(B, -1) for k in obs], axis=1)


class SearchBatch:
    """B search episodes of the envs, stepped together (see the module docstring); episodes start and end
    independently. A skin over the episode engine (episode.SearchState, buffered: numpy on the host): the move
    rule of the action set, the env's rewards and observation. Its state reads as CPU tensors (`idx`, `t`,
    `fused`, ...: views of the engine's arrays) and `step` returns numpy arrays."""

    def __init__(self, config: SearchConfig, fusion: Fusion, batch_size: int, reward: str = "terminal",
                 r_tp: float = R_TP, r_fp: float = R_FP, r_re: float = R_RE, device="cpu"):
        if reward not in REWARD_MODES:
            raise UavsearchError(f"unknown reward mode {reward!r}; valid: {', '.join(REWARD_MODES)}")
        self.config, self.fusion, self.reward_mode = config, fusion, reward
        self.r = {"r_tp": float(r_tp), "r_fp": float(r_fp), "r_re": float(r_re)}
        self.device = torch.device(device)  # the fusion's and the tables'; the episodes step on the host
        self.state = SearchState(config, fusion, batch_size, buffered=True)
        self.B, self.T, self.N, self.P = batch_size, config.budget_T, config.grid.num_cells, config.lattice.num_positions
        self._revisit = np.zeros(self.B, dtype=bool)
        self._done = np.zeros(self.B, dtype=bool)
        self._lead = np.zeros(self.B, dtype=np.int64)  # the one vehicle
        self.source: ViewSource | None = None

    # what the envs read of the state (tensors sharing the engine's memory)
    @property
    def idx(self) -> torch.Tensor:
        """(B,) the viewpoint of each episode's latest view."""
        return torch.from_numpy(self.state.pos[:, 0])

    @property
    def t(self) -> torch.Tensor:
        """(B,) the index of each episode's latest view."""
        return torch.from_numpy(self.state.views - 1)

    @property
    def fused(self) -> torch.Tensor:
        return torch.from_numpy(self.state.fused)

    @property
    def labels(self) -> torch.Tensor:
        return torch.from_numpy(self.state.labels)

    @property
    def allowed(self) -> torch.Tensor:
        return torch.from_numpy(self.state.allowed)

    @property
    def visits(self) -> torch.Tensor:
        return torch.from_numpy(self.state.visits)

    @property
    def revisit(self) -> torch.Tensor:
        """(B,) bool: the latest step revisited a viewpoint."""
        return torch.from_numpy(self._revisit)

    @property
    def revisit_host(self) -> np.ndarray:
        """`revisit` as the engine's numpy array."""
        return self._revisit

    @property
    def done(self) -> torch.Tensor:
        """(B,) bool: the episode has ended."""
        return torch.from_numpy(self._done)

    # ----------------------------------------------------------------------------------------------
    def start(self, envs, labels) -> None:
        """Start episodes `envs` (k,) with ground truth `labels` (k, N) bool (their source is set already)."""
        envs = host(envs).astype(np.int64).reshape(-1)
        st = self.state
        st.restart(envs, host(labels).astype(bool).reshape(len(envs), -1))
        self._revisit[envs] = False
        mask = np.zeros(self.B, dtype=bool)
        mask[envs] = True
        st.take(self.source, mask=mask)
        self._done[envs] = st.ended()[envs]

    def step(self, actions, active=None) -> tuple[np.ndarray, np.ndarray]:
        """Move the `active` episodes (default all) by `actions` (B,): (rewards (B,) float32, terminated (B,) bool);
        inactive episodes are left as they are, with reward 0."""
        st = self.state
        actions = host(actions).astype(np.int64).reshape(-1)
        act = np.ones(self.B, dtype=bool) if active is None else host(active).astype(bool).reshape(-1)
        if (self._done & act).any():
            raise UavsearchError("an episode that has ended was stepped; start it again first")
        first = act & (st.views == 1)
        prev = st.fused.copy() if self.reward_mode == "shaped" else None
        idx, now = st.pos[:, 0], st.clock_s[:, 0]
        nxt = st.moves[idx, np.clip(actions, 0, st.moves.shape[1] - 1)]
        cant = np.zeros(self.B, dtype=bool)
        if st.timed:  # a move it cannot afford ends the episode where it is (run_search's rule)
            cant = act & (st.cost_s[idx, nxt] > st.time_left_s(now) + SLACK_S)
        move = act & ~cant
        st.fly(self._lead, nxt, move, now)
        self._revisit = np.zeros(self.B, dtype=bool)
        terminated = cant.copy()
        if move.any():
            _, self._revisit = st.take(self.source, mask=move)
            terminated |= move & st.ended()
        self._done |= terminated
        return self._rewards(prev, act, first, terminated), terminated

    def _cls(self, fused) -> np.ndarray:
        """(B,) R_cls of maps: search_loop.classification_reward in the float32 arithmetic torch does it in."""
        pred, y = fused > 0.5, self.state.labels
        return (np.float32(self.r["r_tp"]) * (pred & y).sum(-1).astype(np.float32)
                + np.float32(self.r["r_fp"]) * (pred & ~y).sum(-1).astype(np.float32))

    def _rewards(self, prev, act, first, terminated) -> np.ndarray:
        """search_loop.step_rewards of the latest step, in numpy float32 (the same numbers)."""
        zero = np.float32(0.0)
        rev = np.float32(self.r["r_re"]) * self._revisit.astype(np.float32) + zero  # + 0: no -0.0
        if self.reward_mode == "terminal":
            out = np.where(terminated, rev + self._cls(self.state.fused), rev)
        else:  # shaped: R_cls as it accrues; the start view's share comes with the first step
            before = self._cls(prev)
            out = (rev + (self._cls(self.state.fused) - before)) + np.where(first, zero + before, zero)
        return np.where(act, out, zero).astype(np.float32)

    # ----------------------------------------------------------------------------------------------
    def observation(self) -> dict[str, np.ndarray]:
        """The "cells" observation of every episode (its latest view)."""
        st = self.state
        t = st.views - 1
        ar = np.arange(self.B)
        return cells_observation(self.config, st.hist_p[ar, t], st.hist_valid[ar, t], st.fused, st.hist_valid.sum(1),
                                 st.visits, st.pos[:, 0], t, st.time_left_s(st.clock_s[:, 0]) if st.timed else None,
                                 st.allowed if st.timed else None)

    def scores(self) -> dict[str, np.ndarray]:
        """Per episode: Aacc and F1 of the fused map (search/metrics.py), and the ground truth."""
        fused, labels = self.state.fused, self.state.labels
        return {"f1": map_f1(fused, labels), "acc": map_accuracy(fused, labels)}


__all__ = ["REWARD_MODES", "CellTables", "SearchBatch", "TableSource", "cell_tables", "cells_observation",
           "flatten_cells", "observation_keys"]
