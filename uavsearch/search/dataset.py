"""View datasets for perception training and single-view evaluation: rendered once, cached on disk.

Rendering is the data bottleneck (PyBullet on CPU), so every (scene, lattice position) view is rendered
once and kept. A dataset is a directory:

    <dir>/manifest.json        format version, the ViewSetSpec (without its scene list), the camera, grid and
                               render options it was rendered with; a directory can grow by more scenes
                               of the same kind (e.g. 40 then 80 test scenes per density) and reuse shards
    <dir>/shards/s<seed>_k<K>.npz   one compressed shard per scene (numpy.savez_compressed):
        images         (V, H, W, 3) uint8   RGB, north up
        lattice_index  (V,) int16           index into config.lattice_positions (row-major from the NW corner)
        position_enu   (V, 3) float32       camera position, scene ENU metres (nadir, heading north)
        cell_area_px   (V, N*N) float32     F_size of every cell (clipped image polygon area)
        cells_in_view  (V, N*N) bool        c^t
        person_px      (V, N*N) int32       pixels showing a person inside each cell (diagnostics only)
        occupancy      (N*N,) int8          ground truth of the scene
        scene_seed, occupied_cells          ()-shaped int64

Cell label images are not stored: the teleport camera is exactly nadir at a lattice position, so the label
image is a pure function of the position (geometry.cell_label_image) and is recomputed once per position
at load time.

Generation is parallel over scenes (one process per worker, each with its own PyBullet renderer),
resumable (finished shards are skipped; a shard is written to a temporary name and renamed, so a killed
run never leaves a half shard) and deterministic: the lattice positions of scene s are drawn from
numpy.random.default_rng([spec.seed, s, K]), and renders are deterministic per (scene, position).
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Iterable, NamedTuple

import numpy as np
from tqdm import tqdm

from uavsearch.errors import UavsearchError
from uavsearch.geometry import cell_label_image, nadir_camera_pose
from uavsearch.paths import REPO_ROOT
from uavsearch.world.scene import generate_scene
from uavsearch.world.settings import SETTINGS, scene_seeds

from .config import SearchConfig, lattice_positions
from .views import TeleportVehicle

FORMAT = "uavsearch-views/1"
DATA_DIR = REPO_ROOT / "data" / "views"


@dataclass(frozen=True)
class ViewSetSpec:
    """What to render: which scenes, how many lattice positions per scene, and the seed of the draw."""
    name: str
    scenes: tuple[tuple[int, int], ...]  # (scene_seed, occupied_cells K)
    views_per_scene: int = 5  # distinct lattice positions per scene
    include_start: bool = True  # the start view (lattice centre) is always among them
    seed: int = 0
    altitude_m: float = 70.0

    def __post_init__(self):
        if not self.scenes:
            raise UavsearchError(f"view set {self.name!r} has no scenes")
        if self.views_per_scene < 1:
            raise UavsearchError("views_per_scene must be at least 1")

    def to_json(self) -> dict:
        d = asdict(self)
        d["scenes"] = [list(s) for s in self.scenes]
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


def search_config(spec: ViewSetSpec):

    return SearchConfig(altitude_m=spec.altitude_m)


def positions_for_scene(spec: ViewSetSpec, scene_seed: int, k: int, num_positions: int) -> np.ndarray:
    """The lattice indices rendered for one scene (sorted, distinct), a pure function of the spec."""
    n = min(spec.views_per_scene, num_positions)
    centre = num_positions // 2
    rng = np.random.default_rng([spec.seed, int(scene_seed), int(k)])
    if spec.include_start:
        others = np.delete(np.arange(num_positions), centre)
        pick = np.concatenate([[centre], rng.choice(others, n - 1, replace=False)])
    else:
        pick = rng.choice(num_positions, n, replace=False)
    return np.sort(pick).astype(np.int16)


def shard_path(root: Path, scene_seed: int, k: int) -> Path:
    return Path(root) / "shards" / f"s{int(scene_seed)}_k{int(k)}.npz"


def _render_scene(job: tuple[dict, str, int, int]) -> tuple[int, int, int, float]:
    """Worker: render one scene's views and write its shard. Returns (seed, K, views, seconds)."""
    spec_json, root, scene_seed, k = job
    spec = ViewSetSpec.from_json(spec_json)
    out = shard_path(Path(root), scene_seed, k)
    if out.is_file():
        return scene_seed, k, 0, 0.0


    t0 = time.perf_counter()
    config = search_config(spec)
    lattice = lattice_positions(config)
    idx = positions_for_scene(spec, scene_seed, k, len(lattice))
    scene = generate_scene(int(scene_seed), int(k))
    n_cells = config.grid.num_cells
    images, areas, inview, person_px = [], [], [], []
    with TeleportVehicle(scene, config, cache=False) as vehicle:
        for i in idx:
            view = vehicle.capture(lattice[i])
            images.append(view.image)
            areas.append(view.cell_area_px)
            inview.append(view.cells_in_view)
            lab = view.cell_label
            pm = view.person_mask if view.person_mask is not None else np.zeros(lab.shape, bool)
            person_px.append(np.bincount(lab[pm & (lab >= 0)].astype(np.int64), minlength=n_cells)[:n_cells])
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.stem + f".tmp{os.getpid()}.npz")
    np.savez_compressed(
        tmp,
        images=np.stack(images).astype(np.uint8),
        lattice_index=idx,
        position_enu=lattice[idx].astype(np.float32),
        cell_area_px=np.stack(areas).astype(np.float32),
        cells_in_view=np.stack(inview).astype(bool),
        person_px=np.stack(person_px).astype(np.int32),
        occupancy=scene.occupancy_array().astype(np.int8),
        scene_seed=np.int64(scene_seed),
        occupied_cells=np.int64(k),
    )
    os.replace(tmp, out)
    return scene_seed, k, len(idx), time.perf_counter() - t0


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
    """What must match for shards to be shared: everything but the set's name and scene list."""
    spec = {k: v for k, v in manifest.get("spec", {}).items() if k not in ("name", "scenes")}
    return {**manifest, "spec": spec}


def generate_views(spec: ViewSetSpec, root=None, workers: int = 2, progress: bool = True) -> Path:
    """Render (or finish rendering) a view set into `root` (default data/views/<name>); returns root."""
    root = Path(root) if root is not None else DATA_DIR / spec.name
    man_path = root / "manifest.json"
    manifest = json.loads(json.dumps(_manifest(spec)))  # as it reads back from disk
    if man_path.is_file():
        old = json.loads(man_path.read_text())
        if _comparable(old) != _comparable(manifest):
            raise UavsearchError(
                f"{root} holds a different view set (manifest differs); choose another directory or delete it"
            )
    else:
        root.mkdir(parents=True, exist_ok=True)
        man_path.write_text(json.dumps(manifest, indent=1))
    todo = [s for s in spec.scenes if not shard_path(root, *s).is_file()]
    if not todo:
        return root
    jobs = [(spec.to_json(), str(root), int(s), int(k)) for s, k in todo]
    bar = tqdm(total=len(spec.scenes), initial=len(spec.scenes) - len(todo), desc=f"render {spec.name}",
               unit="scene", disable=not progress)
    workers = max(1, min(int(workers), len(jobs)))
    try:
        if workers == 1:
            for job in jobs:
                _render_scene(job)
                bar.update(1)
        else:
            # spawn, not fork: the parent may hold torch/OpenMP threads, and each child builds its own
            # PyBullet client.
            with mp.get_context("spawn").Pool(workers) as pool:
                for _ in pool.imap_unordered(_render_scene, jobs):
                    bar.update(1)
    finally:
        bar.close()
    return root


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

    def __len__(self) -> int:
        return len(self.images)

    def subset(self, rows) -> "ViewSet":
        rows = np.asarray(rows)
        return ViewSet(*(x if name == "labels" else x[rows] for name, x in zip(self._fields, self)))

    def label_images(self, rows) -> np.ndarray:
        return self.labels[self.label_id[np.asarray(rows)]]


def read_manifest(root) -> dict:
    path = Path(root) / "manifest.json"
    if not path.is_file():
        raise UavsearchError(f"{root} is not a view set (no manifest.json); generate it first")
    try:
        man = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise UavsearchError(f"{path} is not valid JSON: {e}") from None
    if man.get("format") != FORMAT:
        raise UavsearchError(f"{path}: unknown view set format {man.get('format')!r} (expected {FORMAT})")
    return man


def shards_in(root) -> list[tuple[int, int]]:
    """(seed, K) of every finished shard in a view-set directory, sorted."""
    out = []
    for p in (Path(root) / "shards").glob("s*_k*.npz"):
        if ".tmp" in p.name:
            continue
        s, k = p.stem.split("_")
        out.append((int(s[1:]), int(k[1:])))
    return sorted(out)


def load_views(root, scenes: Iterable[tuple[int, int]] | None = None, start_only: bool = False) -> ViewSet:
    """Load the given scenes of a view set (default: every finished shard, sorted); `start_only` keeps the
    start (lattice centre) views."""
    man = read_manifest(root)
    spec = ViewSetSpec.from_json({**man["spec"], "scenes": [[0, 0]]})
    config = search_config(spec)

    centre = len(lattice_positions(config)) // 2
    wanted = list(scenes) if scenes is not None else shards_in(root)
    parts: dict[str, list] = {k: [] for k in ("images", "lattice_index", "position_enu", "cell_area_px",
                                              "cells_in_view", "person_px", "occupancy", "scene_seed",
                                              "occupied_cells")}
    for s, k in wanted:
        path = shard_path(root, s, k)
        if not path.is_file():
            raise UavsearchError(f"{path} missing: the view set is incomplete (run the generation again to resume)")
        try:
            with np.load(path) as z:
                rows = np.flatnonzero(z["lattice_index"] == centre) if start_only else np.arange(len(z["lattice_index"]))
                for key in ("images", "lattice_index", "position_enu", "cell_area_px", "cells_in_view", "person_px"):
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
    lattice = lattice_positions(config)
    labels = np.stack([cell_label_image(config.grid, config.intrinsics, nadir_camera_pose(lattice[i])) for i in uniq])
    return ViewSet(
        images=cat["images"], label_id=label_id.astype(np.int64), labels=labels,
        lattice_index=cat["lattice_index"], position_enu=cat["position_enu"], cell_area_px=cat["cell_area_px"],
        cells_in_view=cat["cells_in_view"], person_px=cat["person_px"], occupancy=cat["occupancy"],
        scene_seed=cat["scene_seed"], occupied_cells=cat["occupied_cells"],
    )
