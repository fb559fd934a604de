"""The teleport search environment (gymnasium API); its manual is `ActiveSearchEnv`'s docstring."""

from __future__ import annotations

import json
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from ..errors import SceneError
from ..world.scene import SceneSpec, generate_scene, scene_from_json, scene_to_json
from ..world.settings import SETTINGS, scene_seeds
from .config import SearchConfig
from .search_loop import R_RE, step_rewards
from .views import TeleportVehicle, View


def _as_scene(obj):
    if isinstance(obj, SceneSpec):
        return obj
    if isinstance(obj, dict):
        return scene_from_json(json.dumps(obj))
    if isinstance(obj, str):
        return scene_from_json(obj)
    raise SceneError(f"options['scene'] must be a SceneSpec, a dict or a JSON string, not {type(obj).__name__}")


class ActiveSearchEnv(gym.Env):
    """The paper's search task without dynamics (teleport camera), registered as ``uavsearch/ActiveSearch-v0``.

    **Task.** A nadir camera starts 70 m above the centre of a 50 m x 50 m search area (10 x 10 cells of
    5 m) and may take ``budget_T`` views in all (the start view counts as the first). Between views it
    moves one lattice step (10 m) north, east, west or south, heading fixed north.

    **Action space.** ``Discrete(len(config.actions))``; the paper's order: 0 MoveAhead (north),
    1 MoveRight (east), 2 MoveLeft (west), 3 MoveBack (south).

    **Observation space** (``Dict``):

    - ``image``: ``(H, W, 3)`` uint8 RGB, north up.
    - ``position_enu``: ``(3,)`` float32 camera position in scene ENU metres (origin: ground, centre).
    - ``cell_label``: ``(H, W)`` int16, the grid cell each pixel sees on the ground, -1 off the grid.
      The paper's mask m_i^t is ``cell_label == i``.
    - ``cell_area_px``: ``(N*N,)`` float32 pixel area of each cell's (clipped) image polygon, F_size.
    - ``cells_in_view``: ``(N*N,)`` int8, c^t: 1 where the cell covers at least ``min_cell_area_px`` px.
    - ``step``: int, index of this view in the episode (0 for the start view).

    **Moves** follow the search loop's move rule (``config.lattice.moves``, the table training,
    evaluation and flight use): a move that would leave the lattice (the camera positions above the search
    area, {-20..20 m}^2 for the paper) keeps the camera where it is; the view is re-taken and counts as a
    revisit.

    **Reward.** The revisit part of ``search_loop.step_rewards`` (the one reward of training and the flight
    log): ``r_revisit`` when a step returns to a position already visited in the episode, else 0; the
    default is ``search_loop.R_RE`` (-0.5), the revisit reward R_re (Eq. 15) stage 2 trains with (the paper
    leaves its value open). The classification reward R_cls (Eq. 14) needs a map estimate, which
    belongs to the learner (fusion + perception), not to the env: ``info["occupancy"]`` gives the ground
    truth for it at the end.

    **Episode end.** ``terminated`` after the T-th view (T - 1 steps); never truncated.

    **Reset options.** ``{"scene": SceneSpec | dict | JSON str}`` a given scene; ``{"scene_seed": s,
    "occupied_cells": K}`` a generated one; ``{"occupied_cells": K}`` a new scene with K occupied cells and
    a seed drawn from the env's RNG; ``{"setting": 1 | 2 | 3}`` a scene drawn from that setting's
    ``split``/``part`` seed list (default: the constructor's setting). The same ``reset(seed=...)`` always
    gives the same scene and views.

    **Arguments.** ``config`` (SearchConfig: altitude, step, budget T, action set, camera), ``setting`` /
    ``split`` / ``part`` (where reset draws scenes from), ``r_revisit``, ``render_mode`` (``"rgb_array"``: the
    last view's image), ``cache_scenes`` (scenes whose renders are kept).

    **Info.** ``occupancy`` (N*N,) int8 ground truth; ``revisit`` bool; ``scene_seed``; ``occupied_cells``;
    ``lattice_index`` of the camera position; ``visited`` list of lattice indices so far; ``person_mask``
    of the view (or None).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 2}

    def __init__(
        self,
        config: SearchConfig | None = None,
        setting: int = 2,
        split: str = "paper",
        part: str = "train",
        r_revisit: float = R_RE,
        render_mode: str | None = None,
        cache_scenes: int = 8,
    ):
        self.config = config or SearchConfig()
        if setting not in SETTINGS:
            raise SceneError(f"unknown setting {setting!r}; valid: {sorted(SETTINGS)}")
        self.setting, self.split, self.part = setting, split, part
        scene_seeds(setting, split, part)  # validate early: a bad split/part is a one-line error now
        self.r_revisit = float(r_revisit)
        self.render_mode = render_mode
        self._lattice = self.config.lattice.positions_enu
        self._moves = self.config.lattice.moves.numpy()  # (P, A) the loop's move rule
        self._vehicles: dict[str, TeleportVehicle] = {}  # scene JSON hash -> vehicle with its render cache
        self._cache_scenes = cache_scenes
        intr, n_cells = self.config.intrinsics, self.config.grid.num_cells
        h, w = intr.height_px, intr.width_px
        self.action_space = spaces.Discrete(len(self.config.actions))
        self.observation_space = spaces.Dict(
            {
                "image": spaces.Box(0, 255, (h, w, 3), np.uint8),
                "position_enu": spaces.Box(-1000.0, 1000.0, (3,), np.float32),
                "cell_label": spaces.Box(-1, n_cells - 1, (h, w), np.int16),
                "cell_area_px": spaces.Box(0.0, float(h * w), (n_cells,), np.float32),
                "cells_in_view": spaces.MultiBinary(n_cells),
                "step": spaces.Discrete(self.config.budget_T),
            }
        )
        self.scene = None
        self._vehicle: TeleportVehicle | None = None
        self._idx = self.config.lattice.start_index
        self._t = 0
        self._visited: list[int] = []
        self._last_view: View | None = None

    # ----------------------------------------------------------------------------------------------
    def _pick_scene(self, options: dict):
        if "scene" in options:
            return _as_scene(options["scene"])
        if "occupied_cells" in options:
            k = int(options["occupied_cells"])
            seed = options.get("scene_seed")
            if seed is None:
                seed = int(self.np_random.integers(0, 2**31 - 1))
            return generate_scene(int(seed), k)
        setting = options.get("setting", self.setting)
        if setting not in SETTINGS:
            raise SceneError(f"unknown setting {setting!r}; valid: {sorted(SETTINGS)}")
        if "scene_seed" in options:
            return generate_scene(int(options["scene_seed"]), SETTINGS[setting])
        seeds = scene_seeds(setting, self.split, self.part)
        return generate_scene(int(seeds[int(self.np_random.integers(len(seeds)))]), SETTINGS[setting])

    def _vehicle_for(self, scene) -> TeleportVehicle:
        key = scene_to_json(scene)
        v = self._vehicles.pop(key, None)
        if v is None:
            v = TeleportVehicle(scene, self.config)
        self._vehicles[key] = v  # most recently used last
        while len(self._vehicles) > self._cache_scenes:
            old_key = next(iter(self._vehicles))
            self._vehicles.pop(old_key).close()
        return v

    def _obs(self, view: View) -> dict[str, Any]:
        return {
            # copies: views are cached per position, and users keep what they are given
            "image": view.image.copy(),
            "position_enu": view.position_enu.astype(np.float32),
            "cell_label": view.cell_label.copy(),
            "cell_area_px": view.cell_area_px.copy(),
            "cells_in_view": view.cells_in_view.astype(np.int8),
            "step": self._t,
        }

    def _info(self, revisit: bool) -> dict[str, Any]:
        return {
            "occupancy": self.scene.occupancy_array(),
            "revisit": revisit,
            "scene_seed": int(self.scene.seed),
            "occupied_cells": int(self.scene.occupied_cells_k),
            "lattice_index": self._visited[-1],
            "visited": list(self._visited),
            "person_mask": None if self._last_view.person_mask is None else self._last_view.person_mask.copy(),
        }

    def _capture(self) -> View:
        self._visited.append(self._idx)
        self._last_view = self._vehicle.capture(self._lattice[self._idx])
        return self._last_view

    # ----------------------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.scene = self._pick_scene(options or {})
        self._vehicle = self._vehicle_for(self.scene)
        self._idx, self._t, self._visited = self.config.lattice.start_index, 0, []
        view = self._capture()
        return self._obs(view), self._info(False)

    def step(self, action):
        if self.scene is None:
            raise gym.error.ResetNeeded("call reset() before step()")
        if self._t >= self.config.budget_T - 1:
            raise gym.error.ResetNeeded(f"the episode's budget of T={self.config.budget_T} views is spent")
        if not self.action_space.contains(action):
            raise gym.error.InvalidAction(f"action {action!r} not in {self.action_space}")
        self._idx = int(self._moves[self._idx, int(action)])
        self._t += 1
        revisit = self._idx in self._visited
        view = self._capture()
        reward = step_rewards(None, None, revisit, r_re=self.r_revisit)
        terminated = self._t >= self.config.budget_T - 1
        return self._obs(view), reward, terminated, False, self._info(revisit)

    def render(self):
        if self.render_mode == "rgb_array" and self._last_view is not None:
            return self._last_view.image
        return None

    def close(self):
        for v in self._vehicles.values():
            v.close()
        self._vehicles.clear()

