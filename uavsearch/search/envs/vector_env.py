"""The native vector env: N search episodes on the view caches, stepped in one array operation.

``gym.make_vec("uavsearch/ActiveSearch-v0", num_envs=N, vectorization_mode="vector_entry_point", **kwargs)``
(or ``uavsearch/WideSearch-v0``) builds a `SearchVectorEnv`; its manual is the class docstring.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from ...devices import resolve_device
from ...errors import UavsearchError
from ...world import settings
from ..cells import SearchBatch, TableSource
from ..config import SearchConfig, setting_config
from .search_env import SceneViews, cells_space, default_fusion
from ..search_loop import R_FP, R_RE, R_TP


class SearchVectorEnv(VectorEnv):
    """``num_envs`` episodes of ActiveSearchEnv / WideSearchEnv with ``obs="cells"``, stepped together.

    Everything (task, action space, the "cells" observation, fusion, reward modes, budgets, arguments) is the
    single env's (see ActiveSearchEnv's and WideSearchEnv's docstrings); only the views differ: every scene
    comes from the view caches (no live fallback, no images). Observations are the single env's batched
    (``gymnasium.vector.utils.batch_space``): a dict of ``(num_envs, ...)`` float32 arrays.

    **Seeding.** ``reset(seed=s)`` seeds episode i with ``s + i`` (a list seeds each); episode i then draws the
    same scenes as ``ActiveSearchEnv(...).reset(seed=s + i)`` and the resets after it, so the vector env equals
    ``gym.make_vec(..., vectorization_mode="sync")`` of the single env step for step.

    **Autoreset** (gymnasium 1.x, ``metadata["autoreset_mode"] = AutoresetMode.NEXT_STEP``): the step after an
    episode terminates resets it: its action is ignored, its observation is the new episode's first, its
    reward 0 and its ``terminated`` / ``truncated`` False. ``reset(options={"reset_mask": mask})`` resets only
    the masked episodes.

    **Info**: per episode ``f1``, ``acc`` (the fused map's, search/metrics.py), ``revisit``, ``scene_seed``,
    ``lattice_index``, ``step``, ``occupancy`` (num_envs, N*N) int8, with a time budget ``action_mask``
    (num_envs, P) int8; each key with gymnasium's ``_key`` mask (all True).
    """

    metadata = {"autoreset_mode": AutoresetMode.NEXT_STEP, "render_modes": []}

    def __init__(self, num_envs: int = 1, config: SearchConfig | None = None, setting: int | str = 2,
                 split: str | None = None, part: str = "train", obs: str = "cells", reward: str = "terminal",
                 fusion: str | None = None, limit: int | None = None, perception=None, models_dir=None,
                 cache_dir=None, cache=None, r_tp: float = R_TP, r_fp: float = R_FP, r_revisit: float = R_RE,
                 progress: bool = True, views: str = "cache", render_mode: str | None = None, workers: int = 1,
                 device: str = "cpu", render_all: bool = False):
        if obs != "cells" or views != "cache":
            raise UavsearchError("the native vector env steps cached 'cells' observations only; for images use "
                                 "gym.make_vec(..., vectorization_mode='sync') of the single env")
        if num_envs < 1:
            raise UavsearchError(f"num_envs must be at least 1, got {num_envs}")
        setting = settings.setting_key(setting)  # 2 for "2"; a bad setting is a one-line error
        self.num_envs = int(num_envs)
        self.config = config or getattr(cache, "config", None) or setting_config(setting)
        self.setting, self.split, self.part = setting, split or settings.setting_params(setting).split, part
        self.device = resolve_device(device)
        self.scenes = SceneViews(setting, self.split, part, self.config, None, perception, limit, cache_dir,
                                 cache, progress, workers, self.device, render_all=render_all)
        self.fusion = self.scenes.use_fusion(fusion or default_fusion(setting), models_dir)
        self.render_mode = render_mode
        self.single_observation_space = cells_space(self.config)
        self.single_action_space = gym.spaces.Discrete(self.config.num_actions)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._batch = SearchBatch(self.config, self.fusion, self.num_envs, reward, r_tp, r_fp, r_revisit,
                                  device=self.device)
        self._source: TableSource | None = None
        self._rngs = [seeding.np_random(None)[0] for _ in range(self.num_envs)]
        self._autoreset = np.zeros(self.num_envs, dtype=bool)
        self._started = False

    def _start(self, envs: np.ndarray) -> None:
        tables = self.scenes.tables
        if self._source is None:
            self._source = TableSource(tables, self.num_envs)
            self._batch.source = self._source
        S = len(self.scenes.seeds)
        rows = np.array([int(self._rngs[i].integers(S)) for i in envs], dtype=np.int64)
        self._source.set_rows(envs, rows)
        self._batch.start(envs, self._source.host_tables()[4][rows])

    def _info(self) -> dict[str, Any]:
        b, st = self._batch, self._batch.state  # the engine's numpy arrays (episode.py)
        sc = b.scores()
        info = {"f1": sc["f1"], "acc": sc["acc"], "revisit": b.revisit_host.copy(),
                "scene_seed": self.scenes.tables.scene_seed[b.source.host_rows()],
                "lattice_index": st.pos[:, 0].copy(), "step": st.views - 1,
                "occupancy": st.labels.astype(np.int8)}
        if self.config.budget_s is not None:
            info["action_mask"] = st.allowed.astype(np.int8)
        ones = np.ones(self.num_envs, dtype=bool)
        return {**info, **{f"_{k}": ones for k in list(info)}}

    def reset(self, *, seed: int | list[int | None] | None = None, options: dict | None = None):
        super().reset(seed=seed if seed is None or isinstance(seed, int) else None)
        if seed is not None:
            seeds = [seed + i for i in range(self.num_envs)] if isinstance(seed, int) else list(seed)
            if len(seeds) != self.num_envs:
                raise UavsearchError(f"{len(seeds)} seeds for {self.num_envs} environments")
            self._rngs = [seeding.np_random(s)[0] for s in seeds]
        mask = np.ones(self.num_envs, dtype=bool)
        if options and "reset_mask" in options:
            mask = np.asarray(options["reset_mask"], dtype=bool)
            if mask.shape != (self.num_envs,):
                raise UavsearchError(f"reset_mask must be ({self.num_envs},) bool")
            if not self._started and not mask.all():
                raise UavsearchError("the first reset must reset every episode")
        envs = np.flatnonzero(mask)
        self._start(envs)
        self._autoreset[envs] = False
        self._started = True
        return self._batch.observation(), self._info()

    def step(self, actions):
        if not self._started:
            raise gym.error.ResetNeeded("call reset() before step()")
        actions = np.asarray(actions).reshape(-1)
        if actions.shape != (self.num_envs,):
            raise gym.error.InvalidAction(f"expected {self.num_envs} actions, got shape {actions.shape}")
        again = self._autoreset.copy()
        if ((actions < 0) | (actions >= self.single_action_space.n))[~again].any():
            raise gym.error.InvalidAction(f"actions outside {self.single_action_space}: {actions}")
        rewards, terminated = self._batch.step(np.where(again, 0, actions), active=~again)
        rewards = rewards.astype(np.float64)
        if again.any():
            self._start(np.flatnonzero(again))
        truncated = np.zeros(self.num_envs, dtype=bool)
        self._autoreset = terminated | truncated
        return self._batch.observation(), rewards, terminated, truncated, self._info()

    def close_extras(self, **kwargs):
        self._source = None


__all__ = ["SearchVectorEnv"]
