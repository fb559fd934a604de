"""Fast teleport mode: the frozen perception's outputs for every (scene, lattice position), computed once.

The policy only ever stands on lattice positions (25 for the paper), and stage 2 freezes the backbone and
classifier, so everything stage 2 and the evaluation need from an image is a pure function of (scene,
position, perception weights). It is computed once and kept on disk; training and evaluation never render.

Two layers, both under the gitignored ``cache/`` folder:

1. Renders: every lattice position of every scene of one (split, setting, part), as a dataset.py view set
   (``cache/lattice_views/<world tag>/<split>_s<setting>_<part>/``, views_per_scene = all positions).
   Independent of the perception weights, so retraining perception never re-renders. The world tag
   (world_tag) fingerprints a probe scene's spec and rendered start view plus the splits and the search
   config, so a change to how scenes are made or drawn never silently reuses old renders.
2. Perception outputs, one ``.npz`` per (world, perception weights, split, setting, part):
   ``cache/search_views/<world tag>-<perception tag>/<split>_s<setting>_<part>.npz`` (parallel.npz_bytes):

       format           () str        "uavsearch-search-views/1"
       perception_tag   () str        first 16 hex of sha256 over the perception state dict
       scene_seed       (S,) int64    scene seeds (generate_scene(seed, K) rebuilds a scene)
       occupied_cells   (S,) int64    K
       occupancy        (S, N) int8   ground truth, N = cells (100)
       log_probs        (S, P, N, 2) float32   l_i = [log p(y=0), log p(y=1)] of the view at position p
       cell_features    (S, P, N, D) float32   f_i, the confidence network's input (D = cell_dim); for a scene
                                               family (S, P, N, 0) float16: its features (73 views x 900 cells:
                                               13.7 MB a scene in float16) are in the feature store below
       global_feature   (S, P, G) float32      the image embedding's input (G = global_dim)
       cell_area_px     (S, P, N) float32      F_size: the cell's clipped image polygon area
       valid            (S, P, N) bool         cell measured by the view: in view (c^t) and pooled pixels > 0
       person_px        (S, P, N) int32        pixels showing a person inside the cell in that view (ground truth,
                                               for evaluation only: how visible each person is; absent in caches
                                               written before it, loaded as None)

       search_config    () str        config_to_dict of the SearchConfig, as JSON: P indexes its lattice
                                               (search/lattice.py; row-major from the NW corner, layer by layer)
       feature_store    () str        a scene family's only: the folder, beside the .npz, of its per-view cell
                                               features (feature_store.py: one memory-mapped float16 file per scene,
                                               shared by every `limit` of the part; caches written before it hold
                                               their features in cell_features and have no such key)

A run is resumable at layer 1 (dataset.generate_views skips finished shards; its scenes run on local
processes or on Ray, parallel.map_scenes); layer 2 is one pass of the CNN over the rendered images, in this
process (about a minute for a whole paper split on one core); a scene family's is resumable too, scene by
scene (its feature store keeps each finished scene's outputs). ``cache_dir`` may be an fsspec URL (e.g.
s3://bucket/uavsearch-cache) that every node of a cluster reaches.
"""

from __future__ import annotations

import functools
import hashlib
import io
import json
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from tqdm import tqdm

from uavsearch.errors import UavsearchError
from uavsearch.parallel import Executor, Store, npz_bytes
from uavsearch.paths import REPO_ROOT
from uavsearch.world import settings
from uavsearch.world.settings import scene_seeds

from ..config import SearchConfig, config_from_dict, config_to_dict, setting_config
from ..perception import PooledPerception, cell_pooling, perception_tag
from .dataset import ViewSetSpec, generate_views, load_views, probe_render
from .feature_store import FeatureStore

FORMAT = "uavsearch-search-views/1"
CACHE_DIR = REPO_ROOT / "cache"
PARTS = ("train", "val", "test")


class ViewCache(NamedTuple):
    """One (split, setting, part) in memory as torch tensors; row s is scene s, column p lattice position p."""
    scene_seed: np.ndarray  # (S,)
    occupied_cells: np.ndarray  # (S,)
    occupancy: torch.Tensor  # (S, N) bool
    log_probs: torch.Tensor  # (S, P, N, 2)
    cell_features: torch.Tensor  # (S, P, N, D)
    global_feature: torch.Tensor  # (S, P, G)
    cell_area_px: torch.Tensor  # (S, P, N)
    valid: torch.Tensor  # (S, P, N) bool
    perception_tag: str
    person_px: torch.Tensor | None = None  # (S, P, N) int32 visible person pixels per cell (None: an older cache)
    config: SearchConfig | None = None  # the search config whose lattice the positions are
    feature_store: FeatureStore | None = None  # where cell features kept on disk are (None: none, or in memory)

    @property
    def num_scenes(self) -> int:
        return int(self.occupancy.shape[0])

    @property
    def num_positions(self) -> int:
        return int(self.log_probs.shape[1])

    def subset(self, rows) -> "ViewCache":
        rows = np.asarray(rows)
        t = torch.as_tensor(rows, dtype=torch.long, device=self.occupancy.device)
        return ViewCache(self.scene_seed[rows], self.occupied_cells[rows], self.occupancy[t], self.log_probs[t],
                         self.cell_features[t], self.global_feature[t], self.cell_area_px[t], self.valid[t],
                         self.perception_tag, None if self.person_px is None else self.person_px[t], self.config,
                         self.feature_store)

    def features_at(self, rows, positions) -> torch.Tensor:
        """The (..., N, D) cell features of the views (scene row, lattice position): from memory when the cache
        holds them, else from its feature store (reading only those views), else the empty (..., N, 0)."""
        if self.cell_features.shape[-1] > 0 or self.feature_store is None:
            return self.cell_features[rows, positions]
        rows, positions = torch.broadcast_tensors(torch.as_tensor(rows), torch.as_tensor(positions))
        seeds = self.scene_seed[rows.reshape(-1).cpu().numpy()]
        out = self.feature_store.gather(seeds, positions.reshape(-1).cpu())
        return out.reshape(*rows.shape, *out.shape[1:]).to(self.occupancy.device)  # the cache's device


@dataclass(frozen=True)
class CacheKey:
    """Which scenes a cache holds (one part of one split of one setting: an id 1-3 or a scene family's name,
    whose generator and K make the scenes) and under which search config."""
    setting: int | str
    split: str = "paper"
    part: str = "train"
    config: SearchConfig | None = None  # None: the setting's own (config.setting_config)
    limit: int | None = None  # only the part's first `limit` scenes (a part still rendering); None: all

    def __post_init__(self):
        if self.limit is not None and self.limit < 1:
            raise UavsearchError(f"a cache's scene limit must be at least 1, got {self.limit}")

    @property
    def search_config(self) -> SearchConfig:
        return self.config if self.config is not None else setting_config(self.setting)

    @property
    def name(self) -> str:
        return self.part_name + ("" if self.limit is None else f"_first{self.limit}")

    @property
    def part_name(self) -> str:
        """The whole part's name: its renders live in one folder whatever the limit."""
        return f"{self.split}_s{self.setting}_{self.part}"

    def scenes(self) -> list[tuple[int, int]]:

        if self.part not in PARTS:
            raise UavsearchError(f"unknown part {self.part!r}; valid: {', '.join(PARTS)}")
        return [(int(s), settings.setting_params(self.setting).k)
                for s in scene_seeds(self.setting, self.split, self.part)[: self.limit]]

    @property
    def family(self) -> str | None:
        """The scene family whose generator renders the scenes; None where seed and K alone make them
        (generate_scene's: the paper's settings 1-3 and their variants)."""
        fam = settings.setting_params(self.setting)
        return None if fam.generic_scenes else fam.name


@functools.lru_cache(maxsize=8)
def world_tag(config: SearchConfig, family: str | None = None) -> str:
    """A hash of what decides the pixels of a config's lattice views: a probe scene's spec and its start
    view as rendered now, the scene splits and the config's render key (camera, grid, render options,
    viewpoints). Any change to how scenes are generated or drawn, or to where the camera may go, changes
    it (and so never silently reuses old renders); edits that change no pixel do not. About a second,
    once per process and config. A scene family's tag probes its own scene."""
    render_key, probe_json, image = probe_render(config, family)
    h = hashlib.sha256(render_key.encode())
    h.update(probe_json.encode())
    h.update(image)
    h.update(settings.scene_layout())
    return h.hexdigest()[:12]


@torch.no_grad()
def perception_outputs(net, images: np.ndarray, labels: np.ndarray, altitudes_m: np.ndarray, batch: int = 25,
                       poolings: dict | None = None) -> dict[str, np.ndarray]:
    """Run the frozen net over (V, H, W, 3) images with their (V, H, W) label images and (V,) camera
    altitudes, in batches. `poolings`: a dict kept across calls whose scenes share label batches (a
    lattice's): each batch's cell pooling, half a scene's perception time, is then made once."""
    net.eval()
    out: dict[str, list] = {"log_probs": [], "cell_features": [], "global_feature": [], "cell_pixels": []}
    for i in range(0, len(images), batch):
        lab, extra = labels[i : i + batch], {}
        if poolings is not None and isinstance(net, PooledPerception):
            key = hashlib.sha256(np.ascontiguousarray(lab).tobytes()).hexdigest() + str(lab.shape)
            if key not in poolings:
                poolings[key] = cell_pooling(torch.as_tensor(lab).to(net.device), net.cfg.stride, net.cfg.num_cells)
            extra = {"pooling": poolings[key]}
        o = net.forward_all(images[i : i + batch], lab, altitude_m=altitudes_m[i : i + batch], **extra)
        for k in out:
            out[k].append(getattr(o, k).cpu().numpy())
    return {k: np.concatenate(v).astype(np.float32) for k, v in out.items()}


def render_lattice_views(key: CacheKey, scenes=None, root=None, workers: int = 2, progress: bool = True,
                         executor: Executor | None = None):
    """Layer 1: render every lattice position of every scene (resumable); returns the view-set folder."""
    scenes = list(scenes) if scenes is not None else key.scenes()
    config = key.search_config
    default = config == SearchConfig(altitude_m=config.altitude_m)  # the paper's lattice at that altitude
    spec = ViewSetSpec(name=f"lattice-{key.part_name}", scenes=tuple((int(s), int(k)) for s, k in scenes),
                       views_per_scene=config.lattice.num_positions, include_start=True, seed=0,
                       altitude_m=config.altitude_m, search=None if default else config_to_dict(config),
                       family=key.family)
    root = root if root is not None else CACHE_DIR / "lattice_views" / world_tag(config, key.family) / key.part_name
    return generate_views(spec, root=root, workers=workers, progress=progress, executor=executor)


def build_view_cache(net, key: CacheKey, scenes=None, cache_dir=None, workers: int = 2,
                     progress: bool = True, executor: Executor | None = None):
    """Render (if needed) and run perception over one part; returns the .npz path or URL (reused when
    present). `cache_dir` is a folder or an fsspec URL; `executor` renders the scenes (default: `workers`
    local processes). Perception runs here, over the stored renders, in scene order."""
    store = Store(cache_dir if cache_dir is not None else CACHE_DIR)
    tag = perception_tag(net)
    world = world_tag(key.search_config, key.family)
    out_key = f"search_views/{world}-{tag}/{key.name}.npz"
    out = Path(store.path(out_key)) if store.local else store.path(out_key)
    if store.exists(out_key):
        return out
    scenes = list(scenes) if scenes is not None else key.scenes()
    root = render_lattice_views(key, scenes, root=store.path(f"lattice_views/{world}/{key.part_name}"), workers=workers,
                                progress=progress, executor=executor)
    # A scene family's features are too big to hold whole: float16, in a feature store beside the .npz, written
    # scene by scene (a resumed build skips the scenes it holds); the paper's stay in the .npz as float32.
    feature_dtype = np.float32 if key.family is None else np.float16
    features = None if key.family is None else FeatureStore(store.path(feature_store_key(world, tag, key)), tag)
    net = net.for_grid(key.search_config.grid.num_cells)
    parts: dict[str, list] = {k: [] for k in ("log_probs", "cell_features", "global_feature", "cell_area_px",
                                              "valid", "person_px", "occupancy", "scene_seed",
                                              "occupied_cells")}
    poolings: dict = {}  # every scene's lattice has the same label images: their cell pooling is made once
    for s, k in tqdm(scenes, desc=f"perception {key.name}", unit="scene", disable=not progress):
        if features is not None and features.done(s):
            o = features.outputs(s)
        else:
            o = scene_outputs(net, root, s, k, feature_dtype, poolings)
            if features is not None:
                features.write(s, o.pop("cell_features"), o)
        if features is not None:
            o["cell_features"] = np.zeros((*o["log_probs"].shape[:2], 0), feature_dtype)
        for name, value in o.items():
            parts[name].append(value)
        parts["scene_seed"].append(int(s))
        parts["occupied_cells"].append(int(k))
    # written whole (two processes building at once never clash), without timestamps (equal caches are equal bytes)
    store.write_bytes(out_key, npz_bytes({
        "format": np.array(FORMAT), "perception_tag": np.array(tag),
        "search_config": np.array(json.dumps(config_to_dict(key.search_config), sort_keys=True)),
        **{k: np.stack(v) if k not in ("scene_seed", "occupied_cells") else np.array(v, np.int64)
           for k, v in parts.items()},
        **({} if features is None else {"feature_store": np.array(f"{key.part_name}.features")})}, compress=False))
    return out


def scene_outputs(net, root, seed: int, k: int, feature_dtype=np.float32, poolings: dict | None = None) -> dict[str, np.ndarray]:
    """One scene's row of the cache: perception over its stored renders, in lattice order (`poolings`: see
    perception_outputs)."""
    vs = load_views(root, scenes=[(seed, k)])
    order = np.argsort(vs.lattice_index)
    if not np.array_equal(vs.lattice_index[order], np.arange(len(order))):
        raise UavsearchError(f"{root}: scene {seed} does not hold every lattice position")
    o = perception_outputs(net, vs.images[order], vs.label_images(order), vs.position_enu[order, 2], poolings=poolings)
    return {"log_probs": o["log_probs"], "cell_features": o["cell_features"].astype(feature_dtype),
            "global_feature": o["global_feature"], "cell_area_px": vs.cell_area_px[order],
            "valid": vs.cells_in_view[order] & (o["cell_pixels"] > 0), "person_px": vs.person_px[order].astype(np.int32),
            "occupancy": vs.occupancy[0]}


def feature_store_key(world: str, tag: str, key: CacheKey) -> str:
    """A part's feature store, shared by every `limit` of it: a longer build reuses the scenes a shorter one wrote."""
    return f"search_views/{world}-{tag}/{key.part_name}.features"


def load_view_cache(path, features: bool = True) -> ViewCache:
    """Read a cache .npz written by build_view_cache (a file or an fsspec URL); without `features` the cell
    features stay on disk ((S, P, N, 0): enough for every fusion but the learned one, and a fraction of
    the memory), where a cache with a feature store still serves them view by view (ViewCache.features_at)."""
    parent, _, name = str(path).rpartition("/")
    store = Store(parent or ".")
    if not store.exists(name):
        raise UavsearchError(f"view cache {path} not found")
    try:
        with np.load(io.BytesIO(store.read_bytes(name))) as z:
            if str(z["format"]) != FORMAT:
                raise KeyError(f"format {z['format']}")
            d = {k: z[k] for k in z.files if features or k != "cell_features"}
            if not features:
                d["cell_features"] = np.zeros((*d["log_probs"].shape[:3], 0), np.float32)
    except (OSError, KeyError, ValueError) as e:
        raise UavsearchError(f"{path} is not a uavsearch view cache ({type(e).__name__}: {e}); delete it") from None
    feature_store = None
    if "feature_store" in d:
        feature_store = FeatureStore(f"{parent}/{d['feature_store']}" if parent else str(d["feature_store"]))
        if feature_store.tag != str(d["perception_tag"]) or not all(str(int(s)) in feature_store.manifest["scenes"]
                                                                      for s in d["scene_seed"]):
            raise UavsearchError(f"{path}: its feature store {feature_store.store.url} lacks some of its scenes; delete both")
        if features:
            d["cell_features"] = feature_store.load(d["scene_seed"]).numpy()
    return ViewCache(
        scene_seed=d["scene_seed"], occupied_cells=d["occupied_cells"],
        occupancy=torch.as_tensor(d["occupancy"]).bool(), log_probs=torch.as_tensor(d["log_probs"]),
        cell_features=torch.as_tensor(d["cell_features"]), global_feature=torch.as_tensor(d["global_feature"]),
        cell_area_px=torch.as_tensor(d["cell_area_px"]), valid=torch.as_tensor(d["valid"]).bool(),
        perception_tag=str(d["perception_tag"]),
        person_px=torch.as_tensor(d["person_px"].astype(np.int32)) if "person_px" in d else None,
        config=config_from_dict(json.loads(str(d["search_config"]))) if "search_config" in d else None,
        feature_store=None if features else feature_store,
    )


def get_view_cache(net, setting: int, split: str = "paper", part: str = "train", cache_dir=None,
                   workers: int = 2, progress: bool = True, executor: Executor | None = None,
                   config: SearchConfig | None = None, features: bool = True, limit: int | None = None) -> ViewCache:
    """The cache of one part under `config` (default: the setting's), building it first if needed (the one
    call training and evaluation make); `limit`: the part's first scenes only."""
    return load_view_cache(build_view_cache(net, CacheKey(setting, split, part, config, limit), cache_dir=cache_dir,
                                            workers=workers, progress=progress, executor=executor), features)


def describe(cache: ViewCache) -> str:
    return json.dumps({"scenes": cache.num_scenes, "positions": cache.num_positions,
                       "cell_dim": int(cache.cell_features.shape[-1]), "perception": cache.perception_tag})
