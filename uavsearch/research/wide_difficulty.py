"""How hard the wide family is to see: generation and render times, and visible person pixels per occupied
cell from the viewpoint lattice the wide search flies (6 x 6 positions, 25 m apart, at 70 m and 40 m).

Each occupied cell is looked at from its nearest lattice position, nadir, at each altitude; its visible
person pixels are the pixels whose person (the segmentation's person index) stands in that cell. A cell
with 0 px is wholly hidden (trees, parasols, buildings) or lies between views' sharp parts.

    .venv/bin/python tools/wide_difficulty.py                 # 20 wide scenes (train seeds)
    .venv/bin/python tools/wide_difficulty.py --scenes 5 --setting wide-uniform
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from ..geometry import CameraIntrinsics, nadir_camera_pose
from ..world.render import SceneRenderer
from ..world.settings import generate_setting_scene, scene_seeds

LATTICE_M = np.array([-62.5, -37.5, -12.5, 12.5, 37.5, 62.5])  # viewpoint centres per axis
ALTITUDES_M = (70.0, 40.0)


def nearest_viewpoint(xy: np.ndarray) -> tuple[float, float]:
    """The lattice position nearest a ground point (per axis: the lattice is a product)."""
    return tuple(float(LATTICE_M[np.argmin(np.abs(LATTICE_M - v))]) for v in xy)  # type: ignore[return-value]


def measure_scene(setting: str, seed: int, intr: CameraIntrinsics) -> dict:
    """Times and per-occupied-cell visible person pixels (cells, altitudes) of one scene."""
    t0 = time.perf_counter()
    spec = generate_setting_scene(setting, seed)
    t_gen = time.perf_counter() - t0
    cells = np.flatnonzero(spec.occupancy_array())
    person_cell = np.array([p.cell for p in spec.people] + [-1])  # index -1 (no person) -> cell -1
    px = np.zeros((len(cells), len(ALTITUDES_M)), np.int64)
    t_view = {a: [] for a in ALTITUDES_M}
    t0 = time.perf_counter()
    with SceneRenderer(spec, intr) as r:
        t_build = time.perf_counter() - t0
        views: dict[tuple, np.ndarray] = {}
        for i, cell in enumerate(cells):
            vx, vy = nearest_viewpoint(spec.grid.centers_enu[cell, :2])
            for j, alt in enumerate(ALTITUDES_M):
                key = (vx, vy, alt)
                if key not in views:
                    t1 = time.perf_counter()
                    views[key] = person_cell[r.render(nadir_camera_pose((vx, vy, alt))).person_index]
                    t_view[alt].append(time.perf_counter() - t1)
                px[i, j] = int((views[key] == cell).sum())
    return {"gen_s": t_gen, "build_s": t_build, "view_s": t_view, "px": px, "people": len(spec.people)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=20, help="scenes to measure (default 20)")
    ap.add_argument("--setting", default="wide", help="wide (default) or wide-uniform")
    ap.add_argument("--part", default="train", choices=("train", "val", "test"), help="seeds from this part")
    args = ap.parse_args()
    intr = CameraIntrinsics()
    seeds = scene_seeds(args.setting, part=args.part)[: args.scenes]
    rows = []
    for n, seed in enumerate(seeds, 1):
        rows.append(measure_scene(args.setting, seed, intr))
        print(f"  scene {n}/{len(seeds)} (seed {seed}): {rows[-1]['people']} people, "
              f"generated in {rows[-1]['gen_s']:.2f} s", flush=True)  # fmt: skip
    px = np.concatenate([r["px"] for r in rows])
    gen = np.array([r["gen_s"] for r in rows])
    build = np.array([r["build_s"] for r in rows])
    first = [r["view_s"] for r in rows]
    print(f"\n{args.setting}: {len(rows)} scenes ({args.part} seeds {seeds[0]}..{seeds[-1]}), "
          f"{len(px)} occupied cells, camera {intr.width_px} px, {intr.hfov_deg:.0f} deg\n")  # fmt: skip
    print("| measure | value |\n|---|---|")
    print(f"| generation per scene (median / max) | {np.median(gen):.2f} / {gen.max():.2f} s |")
    print(f"| world build per scene (median) | {np.median(build):.2f} s |")
    for j, alt in enumerate(ALTITUDES_M):
        t = np.array([s for f in first for s in f[alt]])
        print(f"| render one {alt:.0f} m view (median) | {np.median(t) * 1e3:.0f} ms |")
    for j, alt in enumerate(ALTITUDES_M):
        v = px[:, j]
        print(f"| person px per occupied cell at {alt:.0f} m: median / p90 | {np.median(v):.0f} / "
              f"{np.percentile(v, 90):.0f} |")  # fmt: skip
    for j, alt in enumerate(ALTITUDES_M):
        print(f"| cells with 0 px at {alt:.0f} m | {100 * np.mean(px[:, j] == 0):.0f}% |")
    print(f"| cells with 0 px at both altitudes | {100 * np.mean((px == 0).all(1)):.0f}% |")


if __name__ == "__main__":
    main()
