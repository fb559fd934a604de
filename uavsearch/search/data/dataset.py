"""View datasets for perception training and single-view evaluation: rendered once, cached on disk.

Rendering is the data bottleneck (PyBullet on CPU), so every (scene, lattice position) view is rendered
once and kept. A dataset is a folder, local or at an fsspec URL (parallel.Store):

    <dir>/manifest.json        format version, the ViewSetSpec (without its scene list), the camera, grid and
                               render options it was rendered with, and "shards": per finished shard its
                               key, sha256, size and render tag; a directory can grow by more scenes
                               of the same kind (e.g. 40 then 80 test scenes per density) and reuse shards
    <dir>/shards/s<seed>_k<K>.npz   one compressed shard per scene (a scene family's: s<seed>_k<K>_<family>.npz,
                               so no family shard is ever taken for a paper one) (parallel.npz_bytes: no timestamps):
        images         (V, H, W, 3) uint8   RGB, north up
        lattice_index  (V,) int16           index into config.lattice.positions_enu (row-major from the NW corner)
        position_enu   (V, 3) float32       camera position, scene ENU metres (nadir, heading north)
        cell_area_px   (V, N*N) float32     F_size of every cell (clipped image polygon area)
        cells_in_view  (V, N*N) bool        c^t
        person_px      (V, N*N) int32       pixels showing a person inside each cell (diagnostics only)
        person_frac    (V, H, W) uint8      share of each pixel showing a person x 255: the dense target of
                                            perception's auxiliary person head (mostly zeros: compresses well)
        occupancy      (N*N,) int8          ground truth of the scene
        scene_seed, occupied_cells          ()-shaped int64

Cell label images are not stored: the teleport camera is exactly nadir at a lattice position, so the label
image is a pure function of the position (views.nadir_view_geometry), computed once per position and
process and shared by every scene, rendered or loaded.

Generation is one per-scene task (render_scene_shard) mapped over the scenes by parallel.map_scenes, on
local processes or on Ray; resumable (scenes whose manifest entry matches are skipped; a shard is written
whole, so a killed run never leaves a half shard) and deterministic: the lattice positions of scene s are
drawn from numpy.random.default_rng([spec.seed, s, K]), renders are deterministic per (scene, position),
and the shard's bytes are the same whichever executor or machine wrote them (same library versions).
"""

from __future__ import annotations

import functools
import hashlib
import io
import json
import re
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Iterable, NamedTuple

import numpy as np

from uavsearch.errors import UavsearchError
from uavsearch.parallel import Executor, Store, finished, manifest_entry, map_scenes, npz_bytes, process_tree_cpu_s
from uavsearch.paths import REPO_ROOT
from uavsearch.world.scene import generate_scene, scene_to_json
from uavsearch.world.settings import SETTINGS, generate_setting_scene, scene_seeds, setting_params

from ..config import SearchConfig, config_from_dict
from ..views import TeleportVehicle, nadir_view_geometry

FORMAT = "uavsearch-views/2"
DATA_DIR = REPO_ROOT / "data" / "views"
PROBE_SCENE = (424242, 5)  # (seed, K) of the scene whose start view fingerprints the renderer


@dataclass(frozen=True)
class ViewSetSpec:
    """What to render: which scenes, how many lattice positions per scene, and the seed of the draw."""
    name: str
    scenes: tuple[tuple[int, int], ...]  # (scene_seed, occupied_cells K)
    views_per_scene: int = 5  # distinct lattice positions per scene
    include_start: bool = True  # the start view (lattice centre) is always among them
    seed: int = 0
    altitude_m: float = 70.0
    search: dict | None = None  # config_to_dict of the SearchConfig whose lattice is rendered (None: the paper's at altitude_m)
    family: str | None = None  # a scene family's name (world/settings.py, e.g. "wide"): its generator makes the
    # scenes; None: generate_scene(seed, K), the paper's

    def __post_init__(self):
        if not self.scenes:
            raise UavsearchError(f"view set {self.name!r} has no scenes")
        if self.views_per_scene < 1:
            raise UavsearchError("views_per_scene must be at least 1")

    def to_json(self) -> dict:
        d = asdict(self)
        d["scenes"] = [list(s) for s in self.scenes]
        for k in ("search", "family"):
            if d[k] is None:
                del d[k]  # view sets of the paper's lattice and scenes keep the manifest they always had
        return d

    @staticmethod
    def from_json(d: dict) -> "ViewSetSpec":
        d = dict(d)
        d["scenes"] = tuple(tuple(int(x) for x in s) for s in d["scenes"])
        return ViewSetSpec(**d)


def perception_scenes(part: str, n: int, seed: int, k_range: tuple[int, int] = (1, 12)) -> tuple[tuple[int, int], ...]:
    """Scenes for stage 1: the large split's `part` seeds of settings 1-3 in turn, each with K drawn
    uniformly in k_range (a seed fixes the city, K the people), so perception sees every density of
    Table I while the test seeds of every split and the density set stay unseen."""
    if part not in ("train", "val"):
        raise UavsearchError(f"perception scenes come from the train or val parts, not {part!r}")
    pools = [scene_seeds(s, "large", part) for s in sorted(SETTINGS)]
    if n > sum(len(p) for p in pools):
        raise UavsearchError(f"asked for {n} {part} scenes; the large split has {sum(len(p) for p in pools)}")
    out = []
    for i in range(n):
        s = pools[i % len(pools)][i // len(pools)]
        k = int(np.random.default_rng([int(seed), s]).integers(k_range[0], k_range[1] + 1))
        out.append((s, k))
    return tuple(out)


def search_config(spec: ViewSetSpec) -> SearchConfig:
    """The SearchConfig whose lattice the view set renders."""
    return config_from_dict(spec.search) if spec.search is not None else SearchConfig(altitude_m=spec.altitude_m)


def positions_for_scene(spec: ViewSetSpec, scene_seed: int, k: int, num_positions: int) -> np.ndarray:
    """The lattice indices rendered for one scene (sorted, distinct), a pure function of the spec."""
    n = min(spec.views_per_scene, num_positions)
    centre = search_config(spec).lattice.start_index
    rng = np.random.default_rng([spec.seed, int(scene_seed), int(k)])
    if spec.include_start:
        others = np.delete(np.arange(num_positions), centre)
        pick = np.concatenate([[centre], rng.choice(others, n - 1, replace=False)])
    else:
        pick = rng.choice(num_positions, n, replace=False)
    return np.sort(pick).astype(np.int16)


def shard_key(scene_seed: int, k: int, family: str | None = None) -> str:
    return f"shards/s{int(scene_seed)}_k{int(k)}{'' if family is None else '_' + family}.npz"


def shard_path(root: Path, scene_seed: int, k: int, family: str | None = None) -> Path:
    """The shard's file in a local view-set folder."""
    return Path(root) / shard_key(scene_seed, k, family)


def make_scene(scene_seed: int, k: int, family: str | None = None):
    """The scene of a shard: the family's generator (its own K), or the paper's generate_scene(seed, K)."""
    if family is None:
        return generate_scene(int(scene_seed), int(k))
    scene = generate_setting_scene(family, int(scene_seed))
    if len(np.flatnonzero(scene.occupancy_array())) != int(k):
        raise UavsearchError(f"scene family {family!r} has K = {setting_params(family).k}, not {k}")
    return scene


@functools.lru_cache(maxsize=8)
def probe_render(config: SearchConfig | None = None, family: str | None = None) -> tuple[str, str, bytes]:
    """(the config's render key, probe scene JSON, its rendered start view's bytes) as this code makes them
    now: what decides the pixels, once per process and config (about a second). No config: the renderer's
    own fingerprint, with the paper's camera. A family's probe is its own scene of the probe seed."""
    config = config or SearchConfig()
    probe = make_scene(PROBE_SCENE[0], PROBE_SCENE[1] if family is None else setting_params(family).k, family)
    with TeleportVehicle(probe, config, cache=False) as vehicle:
        view = vehicle.capture([0.0, 0.0, config.altitude_m])
    return config.render_key(), scene_to_json(probe), np.ascontiguousarray(view.image).tobytes()


def render_tag(family: str | None = None) -> str:
    """The generator/renderer tag of every shard written now: a shard whose manifest entry carries another
    tag was made by other scene or render code and is rendered again, never mixed in. A family's shards
    also fingerprint its probe scene (the paper's tag is what it always was)."""
    h = hashlib.sha256(FORMAT.encode())
    parts = probe_render() if family is None else (*probe_render(), *probe_render(None, family)[1:])
    for part in parts:
        h.update(part.encode() if isinstance(part, str) else part)
    return h.hexdigest()[:12]


def render_scene_shard(job: tuple[dict, Store, int, int, str]) -> dict:
    """The per-scene task: render one scene's views and write its shard to the store, a pure function of
    (spec, scene seed, K). Returns the shard's manifest entry plus views, seconds and CPU seconds."""
    spec_json, store, scene_seed, k, tag = job
    spec = ViewSetSpec.from_json(spec_json)
    t0, cpu0 = time.perf_counter(), process_tree_cpu_s()
    config = search_config(spec)
    lattice = config.lattice.positions_enu
    idx = positions_for_scene(spec, scene_seed, k, len(lattice))
    scene = make_scene(scene_seed, k, spec.family)
    n_cells = config.grid.num_cells
    images, areas, inview, person_px, person_frac = [], [], [], [], []
    with TeleportVehicle(scene, config, cache=False) as vehicle:
        for i in idx:
            view = vehicle.capture(lattice[i])
            images.append(view.image)
            areas.append(view.cell_area_px)
            inview.append(view.cells_in_view)
            lab = view.cell_label
            pm = view.person_mask if view.person_mask is not None else np.zeros(lab.shape, bool)
            person_px.append(np.bincount(lab[pm & (lab >= 0)].astype(np.int64), minlength=n_cells)[:n_cells])
            frac = view.person_fraction if view.person_fraction is not None else pm.astype(np.float32)
            person_frac.append(np.round(np.clip(frac, 0.0, 1.0) * 255.0).astype(np.uint8))
    data = npz_bytes(dict(
        images=np.stack(images).astype(np.uint8),
        lattice_index=idx,
        position_enu=lattice[idx].astype(np.float32),
        cell_area_px=np.stack(areas).astype(np.float32),
        cells_in_view=np.stack(inview).astype(bool),
        person_px=np.stack(person_px).astype(np.int32),
        person_frac=np.stack(person_frac),
        occupancy=scene.occupancy_array().astype(np.int8),
        scene_seed=np.int64(scene_seed),
        occupied_cells=np.int64(k),
    ))
    key = shard_key(scene_seed, k, spec.family)
    store.write_bytes(key, data)
    return {**manifest_entry(key, data, tag), "views": len(idx), "seconds": time.perf_counter() - t0,
            "cpu_s": process_tree_cpu_s() - cpu0}


def _manifest(spec: ViewSetSpec) -> dict:
    config = search_config(spec)
    intr, grid = config.intrinsics, config.grid
    return {
        "format": FORMAT,
        "spec": {k: v for k, v in spec.to_json().items() if k != "scenes"},
        "camera": {"width_px": intr.width_px, "height_px": intr.height_px, "hfov_deg": intr.hfov_deg},
        "grid": {"n": grid.n, "cell_m": grid.cell_m},
        "render": repr(config.render),
    }


def _comparable(manifest: dict) -> dict:
    """What must match for shards to be shared: everything but the set's name, scene list and shards, and
    the format (a shard of an older format carries an older render tag, so it is rendered again in place);
    of the search config only what decides the pixels (its budgets, moves and speeds do not)."""
    spec = {k: v for k, v in manifest.get("spec", {}).items() if k not in ("name", "scenes")}
    if isinstance(spec.get("search"), dict):
        spec["search"] = {k: v for k, v in spec["search"].items() if k not in _NOT_RENDERED}
    return {**{k: v for k, v in manifest.items() if k not in ("shards", "format")}, "spec": spec}


_NOT_RENDERED = ("budget_T", "budget_s", "actions", "move_set", "speeds")


def _root_of(store: Store):
    return Path(store.root) if store.local else store.url


def generate_views(spec: ViewSetSpec, root=None, workers: int = 2, progress: bool = True,
                   executor: Executor | None = None) -> Path | str:
    """Render (or finish rendering) a view set into `root`, a folder or an fsspec URL (default
    data/views/<name>); returns root. `executor` (default: `workers` local processes) runs the scenes.

    The manifest lists every finished shard (key, sha256, size, render tag); a resumed run renders only
    the scenes without a matching entry. Shards of an older run without entries are adopted (hashed and
    recorded) when their bytes are complete, which the atomic write guarantees."""
    store = Store(root if root is not None else DATA_DIR / spec.name)
    executor = executor or Executor("local", workers)
    manifest = json.loads(json.dumps(_manifest(spec)))  # as it reads back from disk
    old = store.read_json("manifest.json")
    if old is not None and _comparable(old) != _comparable(manifest):
        raise UavsearchError(
            f"{store.url} holds a different view set (manifest differs); choose another directory or delete it"
        )
    tag = render_tag(spec.family)
    shards: dict[str, dict] = dict((old or {}).get("shards", {}))
    stored = set(store.keys("shards"))
    for key in sorted(stored - set(shards)):  # written by a run that stopped before recording them
        shards[key] = manifest_entry(key, store.read_bytes(key), tag)
    manifest["shards"] = shards
    save = lambda: store.write_json("manifest.json", {**manifest, "shards": dict(sorted(shards.items()))})  # noqa: E731
    save()
    todo = [(s, k) for s, k in spec.scenes if not finished(store, shards.get(shard_key(s, k, spec.family)), tag)]
    if not todo:
        return _root_of(store)
    last = [time.monotonic()]

    def record(_, entry):
        shards[entry["key"]] = {k: entry[k] for k in ("key", "sha256", "size", "tag")}
        if time.monotonic() - last[0] > 5.0:  # a killed run loses at most the last few seconds' entries
            save()
            last[0] = time.monotonic()

    jobs = [(spec.to_json(), store, int(s), int(k), tag) for s, k in todo]
    try:
        map_scenes(render_scene_shard, jobs, executor, desc=f"render {spec.name}", progress=progress,
                   on_result=record)
    finally:
        save()
    return _root_of(store)


class ViewSet(NamedTuple):
    """A whole view set in memory, one row per view; label images shared per distinct position."""
    images: np.ndarray  # (V, H, W, 3) uint8
    label_id: np.ndarray  # (V,) int64 index into labels
    labels: np.ndarray  # (P, H, W) int16 cell label image of each distinct position
    lattice_index: np.ndarray  # (V,) int16
    position_enu: np.ndarray  # (V, 3) float32
    cell_area_px: np.ndarray  # (V, N*N) float32
    cells_in_view: np.ndarray  # (V, N*N) bool
    person_px: np.ndarray  # (V, N*N) int32
    occupancy: np.ndarray  # (V, N*N) int8, the scene's ground truth repeated per view
    scene_seed: np.ndarray  # (V,) int64
    occupied_cells: np.ndarray  # (V,) int64
    person_frac: np.ndarray | None = None  # (V, H, W) uint8, loaded on request (load_views(person_frac=True))

    def __len__(self) -> int:
        return len(self.images)

    def subset(self, rows) -> "ViewSet":
        rows = np.asarray(rows)
        return ViewSet(*(x if name == "labels" or x is None else x[rows] for name, x in zip(self._fields, self)))

    def label_images(self, rows) -> np.ndarray:
        return self.labels[self.label_id[np.asarray(rows)]]


def concat_views(sets: list[ViewSet]) -> ViewSet:
    """One ViewSet of several (e.g. one per setting), label images shared per distinct lattice position."""
    li = np.concatenate([v.lattice_index for v in sets])
    uniq, label_id = np.unique(li, return_inverse=True)
    labels = np.empty((len(uniq), *sets[0].labels.shape[1:]), sets[0].labels.dtype)
    for v in sets:
        labels[np.searchsorted(uniq, v.lattice_index[np.unique(v.label_id, return_index=True)[1]])] = v.labels
    fields = {}
    for name in ViewSet._fields:
        if name in ("labels", "label_id"):
            continue
        parts = [getattr(v, name) for v in sets]
        fields[name] = None if any(x is None for x in parts) else np.concatenate(parts)
    return ViewSet(labels=labels, label_id=label_id.astype(np.int64), **fields)


def read_manifest(root) -> dict:
    store = Store(root)
    man = store.read_json("manifest.json")
    if man is None:
        raise UavsearchError(f"{root} is not a view set (no manifest.json); generate it first")
    if man.get("format") != FORMAT:
        raise UavsearchError(f"{store.path('manifest.json')}: unknown view set format {man.get('format')!r} "
                             f"(expected {FORMAT})")
    return man


_SHARD_NAME = re.compile(r"^s(\d+)_k(\d+)(?:_([A-Za-z][\w-]*))?\.npz$")


def shards_in(root) -> list[tuple[int, int]]:
    """(seed, K) of every finished shard of the view set's scenes (folder or URL), sorted."""
    family = _family_of(root)
    out = []
    for key in Store(root).keys("shards"):
        m = _SHARD_NAME.match(key.rsplit("/", 1)[-1])
        if m and m.group(3) == family:
            out.append((int(m.group(1)), int(m.group(2))))
    return sorted(out)


def _family_of(root) -> str | None:
    man = Store(root).read_json("manifest.json") or {}
    return man.get("spec", {}).get("family")


def load_views(root, scenes: Iterable[tuple[int, int]] | None = None, start_only: bool = False,
               person_frac: bool = False) -> ViewSet:
    """Load the given scenes of a view set (default: every finished shard, sorted); `start_only` keeps the
    start (lattice centre) views; `person_frac` also loads the dense person targets."""
    man = read_manifest(root)
    spec = ViewSetSpec.from_json({**man["spec"], "scenes": [[0, 0]]})
    config = search_config(spec)
    centre = config.lattice.start_index
    wanted = list(scenes) if scenes is not None else shards_in(root)
    parts: dict[str, list] = {k: [] for k in ("images", "lattice_index", "position_enu", "cell_area_px",
                                              "cells_in_view", "person_px", "occupancy", "scene_seed",
                                              "occupied_cells")}
    if person_frac:
        parts["person_frac"] = []
    store = Store(root)
    for s, k in wanted:
        key = shard_key(s, k, spec.family)
        path = store.path(key)
        if not store.exists(key):
            raise UavsearchError(f"{path} missing: the view set is incomplete (run the generation again to resume)")
        try:
            with np.load(io.BytesIO(store.read_bytes(key))) as z:
                rows = np.flatnonzero(z["lattice_index"] == centre) if start_only else np.arange(len(z["lattice_index"]))
                for key in ("images", "lattice_index", "position_enu", "cell_area_px", "cells_in_view", "person_px",
                            *(("person_frac",) if person_frac else ())):
                    parts[key].append(z[key][rows])
                parts["occupancy"].append(np.repeat(z["occupancy"][None], len(rows), 0))
                parts["scene_seed"].append(np.full(len(rows), int(z["scene_seed"])))
                parts["occupied_cells"].append(np.full(len(rows), int(z["occupied_cells"])))
        except (OSError, KeyError, ValueError) as e:
            raise UavsearchError(f"{path} is corrupt ({type(e).__name__}: {e}); delete it and regenerate") from None
    if not parts["images"]:
        raise UavsearchError(f"no views selected from {root}")
    cat = {k: np.concatenate(v) for k, v in parts.items()}
    uniq, label_id = np.unique(cat["lattice_index"], return_inverse=True)
    lattice = config.lattice.positions_enu
    labels = np.stack([nadir_view_geometry(config.grid, config.intrinsics, tuple(lattice[i].tolist()))[0] for i in uniq])
    return ViewSet(
        images=cat["images"], label_id=label_id.astype(np.int64), labels=labels,
        lattice_index=cat["lattice_index"], position_enu=cat["position_enu"], cell_area_px=cat["cell_area_px"],
        cells_in_view=cat["cells_in_view"], person_px=cat["person_px"], occupancy=cat["occupancy"],
        scene_seed=cat["scene_seed"], occupied_cells=cat["occupied_cells"], person_frac=cat.get("person_frac"),
    )
