"""The teleport search environments (gymnasium API); their manuals are the class docstrings.

- `ActiveSearchEnv` (``uavsearch/ActiveSearch-v0``): the paper's settings 1-3, image or "cells" observations.
- `WideSearchEnv` (``uavsearch/WideSearch-v0``): the wide scene family (any viewpoint next, time budget).
- The batched form of both is `envs.vector_env.SearchVectorEnv` (``gym.make_vec(id, num_envs=N,
  vectorization_mode="vector_entry_point")``).

Every env steps the episode engine (episode.SearchState, through cells.SearchBatch) on the project's view caches
(data/view_cache.get_view_cache: built on first use, shared on disk by every process); a scene outside the
caches is rendered live, with a one-line warning.
"""

from __future__ import annotations

import json
import sys
import warnings
from collections import OrderedDict
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from ...devices import resolve_device, to_device
from ...errors import SceneError, UavsearchError
from ...world import settings
from ...world.scene import SceneSpec, scene_from_json, scene_to_json
from ..cells import REWARD_MODES, SearchBatch, TableSource, cell_tables, observation_keys
from ..config import SearchConfig, setting_config
from ..episode import Observation, PolicyInput
from ..table3_choices import BUDGET_HEADS, Table3Choice, table3_choice
from ..agents import make_fusion
from ..fusion import CalibratedFusion, Fusion, calibrated_gamma
from ..perception import perceive
from ..search_loop import R_FP, R_RE, R_TP
from ..views import TeleportVehicle, View

OBS_MODES = ("image", "cells")
VIEW_MODES = ("cache", "live")


def _as_scene(obj):
    if isinstance(obj, SceneSpec):
        return obj
    if isinstance(obj, dict):
        return scene_from_json(json.dumps(obj))
    if isinstance(obj, str):
        return scene_from_json(obj)
    raise SceneError(f"options['scene'] must be a SceneSpec, a dict or a JSON string, not {type(obj).__name__}")


def default_fusion(setting) -> str:
    """The fusion an env fuses with unless told: the family's declared one (settings 1-3: the paper's learned
    confidence fusion from the setting's shipped checkpoint; the wide families' both-budget task: Bayes).
    WideSearchEnv's one-budget tasks fuse as Table III does (TABLE3)."""
    return settings.setting_params(setting).task.fusion


# What Table III (results/search_wide/table3.md) chose on the validation scenes per budget of the wide family: the
# fusion every row but ours fuses with, the rule's variant, the best fixed route and the rule's validation AF1
TABLE3 = {budget: table3_choice("wide", budget) for budget in BUDGET_HEADS}
Table3Task = Table3Choice
# Table III fits the calibrated fusion on the family's first 20 training scenes (tools/reproduce.sh
# --wide-train-scenes 20; `uavsearch train map --calibration-scenes 20` fits the shipped policies' alike).
CALIBRATION_SCENES = 20
# A wide scene's lattice views and caches, measured on the 2-core development machine, quiet (load 1.1): an env's
# first reset rendered 4 validation scenes (its one render process) and ran perception over them in 18.6 s, 76 MB
# under cache/; renders, features and the cache's rows take 3.7 + 14.2 + 1.1 MB a scene.
FEW_SCENES = 5  # a first reset renders at most this many scenes without being asked (limit= or render_all=True)
WIDE_SCENE_S = 4.6
WIDE_SCENE_MB = 19.0


def check_buffered_fusion(fusion: Fusion) -> None:
    """The envs' buffered episodes keep each view's p, pixel areas, scores and viewpoint, and of its cell
    features only a fusion's running sum of them (Fusion.feature_summary): a fusion that reads features without
    one is a one-line error here rather than at the first step."""
    if "cell_features" in fusion.needs and type(fusion).feature_summary is Fusion.feature_summary:
        raise UavsearchError(f"{getattr(fusion, 'spec', fusion.name)} reads each view's cell features, which the "
                             "envs' buffered episodes do not keep: give the env a fusion over scores or a learned "
                             "aggregation (neighbour:PATH)")


class SceneViews:
    """Where an env's scenes come from: the view cache of one (setting, split, part) under a config, loaded on
    first use (built then if missing, with progress bars), plus the scene seeds it holds.

    `cache` (a view_cache.ViewCache already in memory, e.g. a synthetic one) replaces the lookup. `workers`: render
    processes for a cache being built (1, the default, renders in this process: a script without an
    ``if __name__ == "__main__":`` guard cannot start spawned workers). `fusion` may be None until `use_fusion`
    builds one from a spec.

    A scene family's scenes are large (WIDE_SCENE_S, WIDE_SCENE_MB): before a build renders any, a line says how
    many, how long and how big, and a build of the whole part (no `limit`) that would render more than
    FEW_SCENES is refused in one line unless `render_all`."""

    def __init__(self, setting, split, part, config: SearchConfig, fusion: Fusion | None, perception=None, limit=None,
                 cache_dir=None, cache=None, progress: bool = True, workers: int = 1, device="cpu",
                 render_all: bool = False):
        self.setting, self.split, self.part, self.config, self.fusion = setting, split, part, config, fusion
        self.device = torch.device(device)  # where the tables (and so the episodes) live; the cache stays on the CPU
        self.limit, self.cache_dir, self.progress, self.workers = limit, cache_dir, progress, workers
        self.render_all = bool(render_all)
        self._perception, self._cache = perception, cache
        self._tables = None
        if cache is not None:
            self.seeds = [int(s) for s in np.asarray(cache.scene_seed)]
            self.k = int(np.asarray(cache.occupied_cells)[0])
        else:
            self.seeds = list(settings.scene_seeds(setting, split, part))[:limit]
            self.k = settings.setting_params(setting).k
        self._row = {s: i for i, s in enumerate(self.seeds)}

    @property
    def perception(self):
        """The frozen perception net (the setting's shipped one unless given: perception.shipped_perception),
        for the grid of the config."""
        from ..perception import load_perception, shipped_perception

        if self._perception is None:
            self._perception = shipped_perception(self.setting)
        if not isinstance(self._perception, torch.nn.Module):
            self._perception, _ = load_perception(self._perception)
        return self._perception.eval().for_grid(self.config.grid.num_cells)

    def use_fusion(self, spec: str, models_dir=None) -> Fusion:
        """Build the fusion a spec names and fuse with it: agents.make_fusion's, plus "name:prior" and Table III's
        "calibrated:GAMMA" (fitted on the family's first CALIBRATION_SCENES training scenes, _calibration)."""
        gamma = calibrated_gamma(spec)
        if gamma is not None:
            coef, prior = self._calibration()
            self.fusion = CalibratedFusion(coef, prior, gamma)
        elif ":" in str(spec):
            self.fusion = make_fusion(spec)
        else:
            self.fusion = make_fusion(spec, setting=self.setting, models_dir=models_dir, device=self.device)
        check_buffered_fusion(self.fusion)
        return self.fusion

    def _calibration(self) -> tuple[list[float], float]:
        """Table III's calibration (Platt coefficients, prior) for this perception. The shipped wide-area
        policies saved the very fit beside them (same scenes, same net: read, not refitted); another net is
        fitted on the training scenes' view cache (built first if missing), and a cache in memory on itself."""
        from ..data.view_cache import get_view_cache
        from ..map_policy import BUDGETS
        from ..checkpoints import wide_checkpoint
        from ..perception import perception_tag
        from ..policy import load_search_model

        if self._cache is not None:
            tag, train = self._cache.perception_tag, self._cache
        else:
            tag, train = perception_tag(self.perception), None
        for budget in BUDGETS:
            path = wide_checkpoint(budget)
            if not path.is_file():
                continue
            fusion, _, extra = load_search_model(path, "cpu")
            fusion = getattr(fusion, "base", fusion)  # a learned aggregation keeps Table III's calibration beneath
            args = extra.get("args", {}) if isinstance(extra, dict) else {}
            if (isinstance(fusion, CalibratedFusion) and extra.get("perception_tag") == tag
                    and args.get("family") == self.setting and args.get("calibration_scenes") == CALIBRATION_SCENES):
                return fusion.coef, fusion.prior
        if train is None:
            self._announce(self.pending(CALIBRATION_SCENES, "train"), CALIBRATION_SCENES, "train")
            train = get_view_cache(self.perception, self.setting, self.split, "train", cache_dir=self.cache_dir,
                                   progress=self.progress, config=self.config, workers=self.workers, features=False,
                                   limit=CALIBRATION_SCENES)
        fitted = make_fusion("calibrated", train)
        return fitted.coef, fitted.prior

    def pending(self, limit=..., part: str | None = None) -> int:
        """How many scenes of the part (its first `limit`; default this one's) a cache build would render."""
        from ...parallel import Store
        from ..data.dataset import shard_key
        from ..data.view_cache import CACHE_DIR, CacheKey, world_tag
        from ..perception import perception_tag

        if self._cache is not None:
            return 0
        limit = self.limit if limit is ... else limit
        key = CacheKey(self.setting, self.split, part or self.part, self.config, limit)
        store = Store(self.cache_dir if self.cache_dir is not None else CACHE_DIR)
        world = world_tag(self.config, key.family)
        if store.exists(f"search_views/{world}-{perception_tag(self.perception)}/{key.name}.npz"):
            return 0
        manifest = store.read_json(f"lattice_views/{world}/{key.part_name}/manifest.json") or {}
        done = manifest.get("shards", {})
        return sum(shard_key(s, k, key.family) not in done for s, k in key.scenes())

    def _announce(self, todo: int, limit, part: str) -> None:
        """The line before a build renders scenes of a scene family; a refusal where it would render the
        whole part's many scenes unasked."""
        if todo == 0 or settings.setting_params(self.setting).task.mission != "team":
            return
        what = (f"{todo} scenes of {self.setting} {self.split}/{part} (about {_duration(todo * WIDE_SCENE_S)} at "
                f"{WIDE_SCENE_S:g} s a scene, measured on 2 cores; about {_size(todo * WIDE_SCENE_MB)} under cache/)")
        if limit is None and todo > FEW_SCENES and not self.render_all:
            raise UavsearchError(f"the first reset would render {what}: pass limit=N to use the first N scenes "
                                 f"(e.g. limit=20), or render_all=True to render them all")
        if self.progress:
            print(f"uavsearch: rendering {what}", file=sys.stderr, flush=True)

    @property
    def tables(self):
        if self._tables is None:
            if self._cache is None:
                from ..data.view_cache import get_view_cache

                self._announce(self.pending(), self.limit, self.part)
                self._cache = get_view_cache(self.perception, self.setting, self.split, self.part,
                                             cache_dir=self.cache_dir, progress=self.progress, config=self.config,
                                             workers=self.workers,
                                             features=self.fusion.scorer is not None, limit=self.limit)
            self._tables = cell_tables(to_device(self._cache, self.device), self.fusion)
        return self._tables

    @property
    def cache(self):
        self.tables
        return self._cache

    def row(self, scene: SceneSpec) -> int | None:
        """The cache row of a scene, or None when the caches do not hold it."""
        r = self._row.get(int(scene.seed))
        if r is None or int(scene.occupied_cells_k) != self.k:
            return None
        if self._cache is None or getattr(self._cache, "perception_tag", "") != "synthetic":
            if scene_to_json(scene) != scene_to_json(settings.generate_setting_scene(self.setting, scene.seed)):
                return None
        return r

    def renders_root(self) -> Path:
        """The folder of the lattice renders (view_cache's first layer) the cache was computed from."""
        from ..data.view_cache import CACHE_DIR, CacheKey, world_tag

        key = CacheKey(self.setting, self.split, self.part, self.config, self.limit)
        return Path(self.cache_dir or CACHE_DIR) / "lattice_views" / world_tag(self.config, key.family) / key.part_name


def _size(mb: float) -> str:
    return f"{mb / 1000:.1f} GB" if mb >= 1000 else f"{mb:.0f} MB"


def _duration(seconds: float) -> str:
    return f"{seconds / 60:.0f} min" if seconds >= 120 else f"{seconds:.0f} s"


class LiveSource:
    """One episode on a scene outside the caches (a ViewSource): render at the viewpoint, run perception (B = 1)."""

    def __init__(self, vehicle: TeleportVehicle, perception, fusion: Fusion, device="cpu"):
        self.vehicle, self.perception, self.scorer = vehicle, perception, fusion.frozen().scorer
        self.device = torch.device(device)
        self.positions = vehicle.config.lattice.positions_enu
        self._memo: dict[int, tuple[View, Observation]] = {}
        self.batch_size = 1

    def view(self, idx: int) -> tuple[View, Observation]:
        if idx not in self._memo:
            view = self.vehicle.capture(self.positions[idx])
            o, valid, area = perceive(self.perception, [view])
            with torch.no_grad():
                scores = None if self.scorer is None else self.scorer(o.cell_features.float().to(self.device))
            self._memo[idx] = (view, to_device(Observation(None, None, None, area, valid, scores,
                                                           o.log_probs[..., 1].exp().float()), self.device))
        return self._memo[idx]

    def observe(self, lattice_idx) -> Observation:
        return self.view(int(lattice_idx.reshape(-1)[0]))[1]


def cells_frame(fused, labels, seen, n: int, size_px: int = 240) -> np.ndarray:
    """(H, W, 3) uint8, north up: the fused map (viridis, p 0 to 1; the cells it calls occupied, p >= 0.5,
    outlined white) beside the ground truth (occupied cells red, cells no view has measured yet grey), titled."""
    import cv2

    c = max(2, size_px // n)
    up = lambda a: np.kron(np.asarray(a).reshape(n, n), np.ones((c, c))).astype(np.uint8)  # noqa: E731
    p = np.clip(np.asarray(fused, dtype=np.float64).reshape(n, n), 0.0, 1.0)
    left = cv2.cvtColor(cv2.applyColorMap(up(np.round(p * 255)), cv2.COLORMAP_VIRIDIS), cv2.COLOR_BGR2RGB)
    for r, col in zip(*np.nonzero(p >= 0.5)):
        cv2.rectangle(left, (int(col) * c, int(r) * c), ((int(col) + 1) * c - 1, (int(r) + 1) * c - 1), (255, 255, 255), 1)
    right = np.full((n * c, n * c, 3), 30, np.uint8)
    right[up(~np.asarray(seen, dtype=bool)) > 0] = (110, 110, 110)
    right[up(np.asarray(labels, dtype=bool)) > 0] = (230, 40, 40)
    gap = np.full((n * c, 6, 3), 255, np.uint8)
    body = np.concatenate([left, gap, right], axis=1)
    head = np.full((18, body.shape[1], 3), 255, np.uint8)
    for x, text in ((2, "fused p (white: called occupied)"), (n * c + 8, "truth (red; grey: unseen)")):
        cv2.putText(head, text, (x, 13), cv2.FONT_HERSHEY_SIMPLEX, 0.33, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([head, body], axis=0)


def cells_space(config: SearchConfig) -> spaces.Dict:
    """The "cells" observation space of one episode (cells.cells_observation builds its values)."""
    n, P, T = config.grid.n, config.lattice.num_positions, config.budget_T
    box = {
        "cell_views": spaces.Box(0.0, float(T), (n, n), np.float32),
        "fused": spaces.Box(0.0, 1.0, (n, n), np.float32),
        "in_view": spaces.Box(0.0, 1.0, (n, n), np.float32),
        "p_view": spaces.Box(0.0, 1.0, (n, n), np.float32),
        "position": spaces.Box(0.0, 1.0, (P,), np.float32),
        "step": spaces.Box(0.0, 1.0, (T,), np.float32),
        "visits": spaces.Box(0.0, float(T), (P,), np.float32),
        "action_mask": spaces.Box(0.0, 1.0, (P,), np.float32),
        "time_left_s": spaces.Box(0.0, float(config.budget_s or 0.0), (1,), np.float32),
    }
    return spaces.Dict({k: box[k] for k in observation_keys(config)})


class ActiveSearchEnv(gym.Env):
    """The paper's search task without dynamics (teleport camera), registered as ``uavsearch/ActiveSearch-v0``.

    **Task.** A nadir camera starts 70 m above the centre of a 50 m x 50 m search area (10 x 10 cells of
    5 m) and may take ``budget_T`` views in all (the start view counts as the first). Between views it
    moves one lattice step (10 m) north, east, west or south, heading fixed north.

    **Action space.** ``Discrete(config.num_actions)``; the paper's order: 0 MoveAhead (north),
    1 MoveRight (east), 2 MoveLeft (west), 3 MoveBack (south).

    **Moves** follow the search loop's move rule (``config.lattice.moves``, the table training,
    evaluation and flight use): a move that would leave the lattice (the camera positions above the search
    area, {-20..20 m}^2 for the paper) keeps the camera where it is; the view is re-taken and counts as a
    revisit.

    **Observation space** (``Dict``), by ``obs``:

    ``obs="image"`` (default):

    - ``image``: ``(H, W, 3)`` uint8 RGB, north up.
    - ``position_enu``: ``(3,)`` float32 camera position in scene ENU metres (origin: ground, centre).
    - ``cell_label``: ``(H, W)`` int16, the grid cell each pixel sees on the ground, -1 off the grid.
      The paper's mask m_i^t is ``cell_label == i``.
    - ``cell_area_px``: ``(N*N,)`` float32 pixel area of each cell's (clipped) image polygon, F_size.
    - ``cells_in_view``: ``(N*N,)`` int8, c^t: 1 where the cell covers at least ``min_cell_area_px`` px.
    - ``step``: int, index of this view in the episode (0 for the start view).

    ``obs="cells"``: what the shipped perception and the env's fusion say, as float32 arrays; map-shaped
    fields are ``(N, N)``, row 0 the northernmost cells, column 0 the westernmost:

    - ``p_view``: p(y=1) of each cell in this view (the frozen perception), 0 where the view measured nothing.
    - ``in_view``: 1 where this view measured the cell (in view, c^t, and pooled pixels > 0), else 0.
    - ``fused``: the fused map M-bar^t over the views so far, p(y=1) (the never-seen prior is 0.1).
    - ``cell_views``: how many views so far measured each cell.
    - ``visits``: ``(P,)`` views taken at each viewpoint so far (P = 25 lattice viewpoints).
    - ``position``: ``(P,)`` one-hot of the camera's viewpoint; ``step``: ``(T,)`` one-hot of the view index.
    - with a time budget (the wide family): ``action_mask`` ``(P,)`` 1 for the unvisited viewpoints affordable
      in the time left; ``time_left_s`` ``(1,)`` simulated seconds of flight left.

    All values lie in [0, 1] but the counts (in [0, T]) and ``time_left_s``. The keys are sorted (gymnasium's
    order); ``gymnasium.wrappers.FlattenObservation`` gives the vector ``external_policy`` reads.

    **Fusion** (``fusion``): default the paper's learned confidence fusion with the setting's shipped
    confidence net (``models/search_s<K>_learned.pt``); any name of search/fusion.py's FUSIONS ("bayes",
    "average", "size", "oracle") works, without a checkpoint. The reward and ``info["f1"]`` score its map.

    **Reward** (``reward``), computed by ``search_loop.step_rewards`` (the one reward of training and the
    flight log) with R_tp, R_fp, R_re (``r_tp``, ``r_fp``, ``r_revisit``; defaults ``search_loop.R_TP``, ``R_FP``,
    ``R_RE`` = 1, -1, -0.5):

    - ``"terminal"`` (default, the paper's Eq. 13-15): R_re at every step that revisits a viewpoint, plus
      N_tp R_tp + N_fp R_fp of the final fused map (thresholded at 0.5) at the last step.
    - ``"shaped"``: R_re at a revisit plus the change of N_tp R_tp + N_fp R_fp the step's view made; the first
      step also pays the start view's own. An episode's rewards sum to its terminal reward.

    **Views.** ``views="cache"`` (default): the perception outputs (and, for images, the renders) of every
    lattice viewpoint of the ``setting``'s ``split``/``part`` scenes come from the project's view caches
    (``cache/``, built on first use with progress bars, shared by every process; ``limit``: the first scenes
    only). A scene outside them (a reset option naming another scene) is rendered live, with a one-line
    warning. ``views="live"`` renders every view (about a second a step).

    **Episode end.** ``terminated`` after the T-th view (T - 1 steps); never truncated.

    **Reset options.** ``{"scene": SceneSpec | dict | JSON str}`` a given scene; ``{"scene_seed": s,
    "occupied_cells": K}`` a generated one; ``{"occupied_cells": K}`` a new scene with K occupied cells and
    a seed drawn from the env's RNG; ``{"scene_seed": s}`` the setting's scene of that seed; ``{"setting": 1 |
    2 | 3}`` a scene drawn from that setting's ``split``/``part`` seed list (default: the constructor's
    setting). The same ``reset(seed=...)`` always gives the same scene and views.

    **Arguments.** ``config`` (SearchConfig: altitude, step, budget T, action set, camera; default the
    setting's), ``setting`` / ``split`` / ``part`` / ``limit`` (which scenes reset draws), ``obs``, ``reward``,
    ``fusion``, ``views``, ``perception`` (checkpoint path or net; default the setting's shipped one: models/perception.pt, or
    models/perception_wide.pt for the wide families where it exists),
    ``models_dir`` (where a trained fusion's checkpoint lives), ``cache_dir``, ``cache`` (a ViewCache in
    memory instead), ``r_tp`` / ``r_fp`` / ``r_revisit``, ``render_mode`` (``"rgb_array"``: the last view's
    image in image mode; in cells mode the fused map beside the ground truth, cells_frame), ``render_all`` (a
    scene family: render a whole part unasked, SceneViews), ``cache_scenes`` (live scenes whose renders are kept), ``progress``, ``workers`` (render
    processes when a cache is built; 1 renders in this process), ``device`` (where the episode's tensors live:
    ``"cpu"`` (default), ``"cuda"``, ``"cuda:N"`` or ``"auto"``, devices.resolve_device; observations are numpy
    whatever it is, and on the CPU the same numbers as ever).

    **Info.** ``occupancy`` (N*N,) int8 ground truth; ``f1`` / ``acc`` of the fused map after this view
    (search/metrics.py); ``revisit`` bool; ``scene_seed``; ``occupied_cells``; ``lattice_index`` of the camera
    position; ``visited`` list of lattice indices so far; ``cached`` whether the scene came from the caches;
    ``person_mask`` of the view (live image mode, else None); ``action_mask`` (P,) int8 with a time budget.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 2}

    def __init__(
        self,
        config: SearchConfig | None = None,
        setting: int | str = 2,
        split: str | None = None,
        part: str = "train",
        obs: str = "image",
        reward: str = "terminal",
        fusion: str | None = None,
        views: str = "cache",
        limit: int | None = None,
        perception=None,
        models_dir=None,
        cache_dir=None,
        cache=None,
        r_tp: float = R_TP,
        r_fp: float = R_FP,
        r_revisit: float = R_RE,
        render_mode: str | None = None,
        cache_scenes: int = 8,
        progress: bool = True,
        workers: int = 1,
        device: str = "cpu",
        render_all: bool = False,
    ):
        setting = settings.setting_key(setting)  # 2 for "2"; a bad setting is a one-line error now
        if obs not in OBS_MODES:
            raise UavsearchError(f"unknown observation mode {obs!r}; valid: {', '.join(OBS_MODES)}")
        if views not in VIEW_MODES:
            raise UavsearchError(f"unknown views mode {views!r}; valid: {', '.join(VIEW_MODES)}")
        if reward not in REWARD_MODES:
            raise UavsearchError(f"unknown reward mode {reward!r}; valid: {', '.join(REWARD_MODES)}")
        if cache is not None and obs == "image":
            raise UavsearchError("a view cache given in memory holds no images: use obs='cells'")
        self.config = config or getattr(cache, "config", None) or setting_config(setting)
        self.setting, self.part = setting, part
        self.split = split or settings.setting_params(setting).split
        settings.scene_seeds(setting, self.split, part)  # validate early: a bad split/part is a one-line error now
        self.obs_mode, self.reward_mode, self.views_mode = obs, reward, views
        self.r_revisit = float(r_revisit)
        self.render_mode = render_mode
        self.device = resolve_device(device)
        self.scenes = SceneViews(setting, self.split, part, self.config, None, perception, limit, cache_dir,
                                 cache, progress, workers, self.device, render_all=render_all)
        self.fusion = self.scenes.use_fusion(fusion or default_fusion(setting), models_dir)
        self._batch = SearchBatch(self.config, self.fusion, 1, reward, r_tp, r_fp, r_revisit, device=self.device)
        self._vehicles: OrderedDict[str, TeleportVehicle] = OrderedDict()  # live scenes' renderers
        self._cache_scenes = cache_scenes
        self._images: OrderedDict[int, Any] = OrderedDict()  # cached scenes' renders (ViewSets), by row
        self._warned = False
        self.action_space = spaces.Discrete(self.config.num_actions)
        self.observation_space = self._image_space() if obs == "image" else cells_space(self.config)
        self._scene: SceneSpec | None = None
        self._scene_seed: int | None = None
        self._scene_k = 0
        self._row: int | None = None
        self._live: LiveSource | None = None
        self._visited: list[int] = []
        self._last_view: View | None = None

    def _image_space(self) -> spaces.Dict:
        intr, n_cells = self.config.intrinsics, self.config.grid.num_cells
        h, w = intr.height_px, intr.width_px
        return spaces.Dict({
            "image": spaces.Box(0, 255, (h, w, 3), np.uint8),
            "position_enu": spaces.Box(-1000.0, 1000.0, (3,), np.float32),
            "cell_label": spaces.Box(-1, n_cells - 1, (h, w), np.int16),
            "cell_area_px": spaces.Box(0.0, float(h * w), (n_cells,), np.float32),
            "cells_in_view": spaces.MultiBinary(n_cells),
            "step": spaces.Discrete(self.config.budget_T),
        })

    # ----------------------------------------------------------------------------------------------
    def _pick(self, options: dict) -> tuple[int | None, SceneSpec | None, int, int]:
        """(cache row or None, scene or None, scene seed, K) of the episode the reset options ask for; a
        scene of the caches is not generated (about a second) unless the options give it."""
        if "scene" in options:
            scene = _as_scene(options["scene"])
            return self.scenes.row(scene), scene, int(scene.seed), int(scene.occupied_cells_k)
        setting = options.get("setting", self.setting)
        fam = settings.setting_params(setting)
        ours = fam is settings.setting_params(self.setting)
        if "occupied_cells" in options or "scene_seed" in options:
            k = int(options.get("occupied_cells", fam.k))
            seed = options.get("scene_seed")
            if seed is None:
                seed = int(self.np_random.integers(0, 2**31 - 1))
            seed = int(seed)
            if ours and k == self.scenes.k and seed in self.scenes.seeds:
                return self.scenes.seeds.index(seed), None, seed, k
            if k == fam.k:
                return None, settings.generate_setting_scene(setting, seed), seed, k
            from ...world.scene import generate_scene

            return None, generate_scene(seed, k), seed, k
        if ours:
            row = int(self.np_random.integers(len(self.scenes.seeds)))
            return row, None, self.scenes.seeds[row], self.scenes.k
        seeds = settings.scene_seeds(setting, self.split, self.part)
        seed = int(seeds[int(self.np_random.integers(len(seeds)))])
        return None, settings.generate_setting_scene(setting, seed), seed, fam.k

    @property
    def scene(self) -> SceneSpec | None:
        """The episode's scene (generated on first ask for a scene of the caches)."""
        if self._scene is None and self._scene_seed is not None:
            self._scene = settings.generate_setting_scene(self.setting, self._scene_seed)
        return self._scene

    def _vehicle_for(self, scene) -> TeleportVehicle:
        key = scene_to_json(scene)
        v = self._vehicles.pop(key, None)
        if v is None:
            v = TeleportVehicle(scene, self.config)
        self._vehicles[key] = v  # most recently used last
        while len(self._vehicles) > self._cache_scenes:
            self._vehicles.popitem(last=False)[1].close()
        return v

    def _cached_images(self, row: int):
        from ..data.dataset import load_views

        if row not in self._images:
            seed = self.scenes.seeds[row]
            self.scenes.tables  # builds the renders too
            vs = load_views(self.scenes.renders_root(), scenes=[(seed, self.scenes.k)])
            self._images[row] = vs.subset(np.argsort(vs.lattice_index))
            while len(self._images) > max(self._cache_scenes, 32):  # about 4 MB a paper scene
                self._images.popitem(last=False)
        return self._images[row]

    def _obs(self) -> dict[str, Any]:
        if self.obs_mode == "cells":
            return {k: v[0] for k, v in self._batch.observation().items()}
        idx, t = self._visited[-1], int(self._batch.t[0])
        if self._live is not None:
            view = self._last_view = self._live.view(idx)[0]
            return {  # copies: views are cached per position, and users keep what they are given
                "image": view.image.copy(), "position_enu": view.position_enu.astype(np.float32),
                "cell_label": view.cell_label.copy(), "cell_area_px": view.cell_area_px.copy(),
                "cells_in_view": view.cells_in_view.astype(np.int8), "step": t}
        vs = self._cached_images(self._row)
        self._last_view = None
        return {"image": vs.images[idx].copy(), "position_enu": vs.position_enu[idx].astype(np.float32),
                "cell_label": vs.label_images([idx])[0].copy(), "cell_area_px": vs.cell_area_px[idx].copy(),
                "cells_in_view": vs.cells_in_view[idx].astype(np.int8), "step": t}

    def _info(self) -> dict[str, Any]:
        sc = self._batch.scores()
        info = {
            "occupancy": self._batch.labels[0].cpu().numpy().astype(np.int8),
            "f1": float(sc["f1"][0]), "acc": float(sc["acc"][0]),
            "revisit": bool(self._batch.revisit[0]),
            "scene_seed": self._scene_seed,
            "occupied_cells": self._scene_k,
            "lattice_index": self._visited[-1],
            "visited": list(self._visited),
            "cached": self._live is None,
            "person_mask": None if self._last_view is None or self._last_view.person_mask is None
            else self._last_view.person_mask.copy(),
        }
        if self.config.budget_s is not None:
            info["action_mask"] = self._batch.allowed[0].cpu().numpy().astype(np.int8)
        return info

    # ----------------------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        row, self._scene, self._scene_seed, self._scene_k = self._pick(options or {})
        self._row = None if self.views_mode == "live" else row
        if self._row is None and self._scene is None:
            self._scene = settings.generate_setting_scene(self.setting, self._scene_seed)
        if self._row is None:
            if self.views_mode == "cache" and not self._warned:
                warnings.warn(f"uavsearch: scene {self._scene_seed} (K={self._scene_k}) is not in the "
                              f"view caches of setting {self.setting} {self.split}/{self.part}; rendering it live "
                              "(about a second a view)", stacklevel=2)
                self._warned = True
            self._live = LiveSource(self._vehicle_for(self.scene), self.scenes.perception, self.fusion, self.device)
            self._batch.source = self._live
            labels = self.scene.occupancy_array()
        else:
            self._live = None
            src = TableSource(self.scenes.tables, 1)
            src.rows[0] = self._row
            self._batch.source = src
            labels = self.scenes.tables.labels[self._row]
        self._batch.start([0], torch.as_tensor(labels).bool()[None])  # a table's labels live on the env's device
        self._visited = [int(self._batch.idx[0])]
        return self._obs(), self._info()

    def step(self, action):
        if self._scene_seed is None:
            raise gym.error.ResetNeeded("call reset() before step()")
        if bool(self._batch.done[0]):
            raise gym.error.ResetNeeded(f"the episode's budget (T={self.config.budget_T} views"
                                        + (f", {self.config.budget_s:g} s" if self.config.budget_s else "")
                                        + ") is spent")
        if not self.action_space.contains(action):
            raise gym.error.InvalidAction(f"action {action!r} not in {self.action_space}")
        t0 = int(self._batch.t[0])
        reward, terminated = self._batch.step([int(action)])
        if int(self._batch.t[0]) > t0:
            self._visited.append(int(self._batch.idx[0]))
        return self._obs(), float(reward[0]), bool(terminated[0]), False, self._info()

    def render(self):
        if self.render_mode != "rgb_array" or self._scene_seed is None:
            return None
        if self.obs_mode == "image":
            return self._obs()["image"]
        seen = self._batch.observation()["cell_views"][0] > 0
        host = lambda x: torch.as_tensor(x).cpu().numpy()  # noqa: E731 - the engine's arrays, tensors or numpy
        return cells_frame(host(self._batch.fused[0]), host(self._batch.labels[0]), seen, self.config.grid.n)

    def close(self):
        for v in self._vehicles.values():
            v.close()
        self._vehicles.clear()
        self._images.clear()


class LoopPolicyPlayer:
    """A search-loop policy (wide_policies' rule and fixed routes, a map policy: anything with ``act(PolicyInput)``)
    playing a single env in cells mode, from nothing but what the env shows: the observations and infos since
    reset rebuild the policy's PolicyInput. What lets a learner compare itself with the rule on the very env it
    learns on (tools/env_table3.py, tests/test_env_table3.py)."""

    def __init__(self, policy, config: SearchConfig):
        self.policy, self.config = policy, config
        self._valid: list[np.ndarray] = []
        self._probs: list[np.ndarray] = []

    def act(self, obs: dict, info: dict) -> int:
        """The next action; call with every observation from reset on (a step 0 observation starts afresh)."""
        if int(np.argmax(obs["step"])) == 0 and len(info["visited"]) == 1:
            self._valid, self._probs = [], []
        self._valid.append(np.asarray(obs["in_view"]).reshape(-1) > 0)
        self._probs.append(np.asarray(obs["p_view"], np.float32).reshape(-1))
        visited = torch.as_tensor(np.asarray(obs["visits"]) > 0)[None]
        timed = self.config.budget_s is not None
        valid = torch.as_tensor(np.stack(self._valid))[None]
        inp = PolicyInput(
            global_feature=None, cells_in_view=valid[:, -1].float(),
            fused=torch.as_tensor(np.asarray(obs["fused"], np.float32).reshape(1, -1)),
            lattice_idx=torch.as_tensor([int(info["lattice_index"])]), visited=visited,
            step=len(info["visited"]) - 1, budget_T=self.config.budget_T,
            view_positions=torch.as_tensor([list(info["visited"])]), view_probs=torch.as_tensor(np.stack(self._probs))[None],
            view_valid=valid,
            time_left_s=torch.as_tensor(np.asarray(obs["time_left_s"], np.float32).reshape(1)) if timed else None,
            allowed=torch.as_tensor(np.asarray(info["action_mask"]) > 0)[None] if timed else None)
        with torch.no_grad():
            action = self.policy.act(inp)[0]
        return int(action.reshape(-1)[0])


def play_scenes(env, act, seeds, progress: str | None = None) -> tuple[list[float], list[list[int]]]:
    """(final F1, route) per scene seed of a policy ``act(obs, info) -> action`` played through a single cells-mode
    env (a LoopPolicyPlayer's act, a learner's); `progress` names a tqdm bar."""
    from tqdm import tqdm

    f1, routes = [], []
    for seed in tqdm(seeds, desc=progress, unit="scene", disable=progress is None):
        obs, info = env.reset(options={"scene_seed": int(seed)})
        done = False
        while not done:
            obs, _, done, _, info = env.step(act(obs, info))
        f1.append(info["f1"])
        routes.append(info["visited"])
    return f1, routes


def wide_task(setting="wide", budget: str | int | None = "8", config: SearchConfig | None = None,
              cache=None) -> tuple[SearchConfig, str]:
    """(config, default fusion spec) of a scene family's one-budget task, as Table III searches it: budget "8"
    (T = 8 views, no time limit) or "240" (the family's 240 s of flight, as many views as fit), each with Table
    III's fusion for it (TABLE3); None: the config's own budgets (the family's declares both at once) and the
    family's declared fusion. `config` (else the cache's, else the family's) gives the lattice."""
    from ..config import wide_budgets
    from ..map_policy import BUDGETS

    base = config or getattr(cache, "config", None) or setting_config(setting)
    if budget is None:
        return base, default_fusion(setting)
    key = str(budget).removesuffix("s")
    if key not in TABLE3:
        raise UavsearchError(f"budget must be 8 (views), 240 (seconds of flight) or None (the config's own), "
                             f"not {budget!r}")
    return dict(zip(BUDGETS, wide_budgets(base).values()))[key], TABLE3[key].fusion


class WideSearchEnv(ActiveSearchEnv):
    """The wide-area search without dynamics, registered as ``uavsearch/WideSearch-v0``: by default Table III's
    task for one budget, its fusion and its scene split (results/search_wide/table3.md).

    **Task** (scene family ``"wide"`` of scenes/settings.yaml): a 150 m x 150 m area of 30 x 30 cells of 5 m, 10
    occupied cells in groups; 73 viewpoints: 6 x 6 25 m apart at 70 m and at 40 m, plus the start above the
    centre at 70 m. Any viewpoint may be next. ``budget="8"`` (default): T = 8 views (the start view counts), no
    time limit; ``budget="240"``: 240 s of simulated flight (lattice.flight_time_s between viewpoints; the start
    view is free) and as many views as fit; ``budget=None``: both at once (the family's declared task).

    **Action space.** ``Discrete(73)``: the index of the next viewpoint (lattice.py order: the 70 m layer
    row-major from the NW corner, then the 40 m layer, then the start). With a time budget ``action_mask`` (in
    the observation and in ``info``) marks the unvisited viewpoints affordable in the time left; a visited one
    may be chosen again (a revisit, R_re), an unaffordable one ends the episode where it is (the search loop's
    rule).

    **Observation** ``obs="cells"`` (default; ``(30, 30)`` maps, with a time budget ``action_mask`` and
    ``time_left_s``) or ``"image"``, as ActiveSearchEnv's. **Fusion** default Table III's for the budget
    (TABLE3): ``calibrated:0.25`` at T = 8, ``calibrated:0.75`` at 240 s, the calibrated fusion fitted on the
    family's first 20 training scenes (read from the shipped wide-area policies, which saved that very fit, when
    the perception is theirs; else fitted on those scenes); any name of ActiveSearchEnv's, ``name:prior``
    (``bayes:0.3``) or ``calibrated:GAMMA`` otherwise. **Reward** as ActiveSearchEnv's: terminal (default) or
    shaped; the last step is the one after which no view is left or affordable.

    **Scenes** (Table III's split, ``large``): ``part="train"`` (default; 500 scenes) to learn on, ``"val"`` (50,
    where Table III chose its fusion, rule and best fixed route) or ``"test"`` (100, Table III's rows).
    ``limit=N`` keeps the part's first N scenes. A scene's views cost about 4.6 s to render and 19 MB under
    cache/ (WIDE_SCENE_S, WIDE_SCENE_MB): the first reset says how many scenes it renders, how long and how
    big, and without ``limit`` refuses in one line to render more than a few unless ``render_all=True``.

    **Render.** ``render_mode="rgb_array"``: in cells mode the fused map (p, the cells it calls occupied
    outlined) beside the ground truth (the occupied cells; grey: cells no view has measured yet), uint8 RGB.

    **Episode end.** ``terminated`` after the last view of the budget, when no unvisited viewpoint is
    affordable in the time left, or on an unaffordable choice; never truncated. Other arguments as
    ActiveSearchEnv's.
    """

    def __init__(self, config: SearchConfig | None = None, setting: int | str = "wide", split: str | None = None,
                 part: str = "train", obs: str = "cells", limit: int | None = None, budget: str | int | None = "8",
                 fusion: str | None = None, **kwargs):
        if settings.setting_params(setting).task.mission != "team":
            raise UavsearchError(f"WideSearchEnv searches a scene family, not setting {setting!r}")
        config, table_fusion = wide_task(setting, budget, config, kwargs.get("cache"))
        super().__init__(config=config, setting=setting, split=split, part=part, obs=obs, limit=limit,
                         fusion=fusion or table_fusion, **kwargs)
        self.budget = None if budget is None else str(budget).removesuffix("s")


__all__ = ["ActiveSearchEnv", "CALIBRATION_SCENES", "LoopPolicyPlayer", "OBS_MODES", "play_scenes", "SceneViews", "TABLE3", "Table3Task",
           "VIEW_MODES", "WideSearchEnv", "cells_frame", "cells_space", "default_fusion", "wide_task"]
