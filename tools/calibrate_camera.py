"""Calibrate the start view's difficulty against the paper.

At 70 m, nadir, from the centre and from a corner of the 10 m lattice, over N scenes of a setting:
cell pixel areas (F_size) of cells in view, person pixel counts from the segmentation (pixels touched
by a person, and the effective area = sum of subpixel fractions), and the share of occupied cells in
which no person pixel is visible (hidden under trees, or too small). One table per field of view.

    .venv/bin/python tools/calibrate_camera.py                 # 20 scenes of setting 2, hfov 60
    .venv/bin/python tools/calibrate_camera.py --hfov 50 60 65 --scenes 10
"""

from __future__ import annotations

import argparse

import numpy as np
from tqdm import tqdm

from uavsearch.geometry import CameraIntrinsics, cell_pixel_areas, nadir_camera_pose, project_points
from uavsearch.world.render import RenderOptions, SceneRenderer
from uavsearch.world.scene import generate_scene
from uavsearch.world.settings import SETTINGS, scene_seeds

ALTITUDE_M = 70.0
POSITIONS = {"centre": (0.0, 0.0), "corner": (20.0, 20.0)}


def _stats(x) -> str:
    x = np.asarray(x, float)
    if x.size == 0:
        return "-"
    return f"{x.min():.1f} / {np.percentile(x, 10):.1f} / {np.median(x):.1f} / {np.percentile(x, 90):.1f} / {x.max():.1f}"


def measure(hfov_deg: float, seeds: list[int], k: int, supersample: int) -> dict:
    intr = CameraIntrinsics(224, 224, hfov_deg)
    res: dict = {name: {"areas": [], "in_view": [], "px": [], "eff": [], "hidden_people": 0, "people": 0,
                        "occ_hidden": 0, "occ_in_view": 0} for name in POSITIONS}  # fmt: skip
    for seed in tqdm(seeds, desc=f"hfov {hfov_deg:g}", leave=False):
        spec = generate_scene(seed, k)
        occ = spec.occupancy_array()
        with SceneRenderer(spec, intr, RenderOptions(supersample=supersample)) as r:
            for name, (x, y) in POSITIONS.items():
                pose = nadir_camera_pose((x, y, ALTITUDE_M))
                out = r.render(pose)
                areas = cell_pixel_areas(spec.grid, intr, pose)
                d = res[name]
                full = areas >= 1.0
                d["areas"] += areas[full].tolist()
                d["in_view"].append(int(full.sum()))
                people = spec.people
                idx = out.person_index
                # people in the grid whose ground position projects into the image
                pos = np.array([[p.x_m, p.y_m, 0.0] for p in people])
                uv, _ = project_points(pos, intr, pose)
                inside = (uv[:, 0] >= 0) & (uv[:, 0] < intr.width_px) & (uv[:, 1] >= 0) & (uv[:, 1] < intr.height_px)
                for i, p in enumerate(people):
                    if p.cell < 0 or not inside[i]:
                        continue
                    n_px = int((idx == i).sum())
                    d["people"] += 1
                    d["px"].append(n_px)
                    d["eff"].append(float(out.person_fraction[idx == i].sum()))
                    d["hidden_people"] += n_px == 0
                seen_cells = {people[int(i)].cell for i in np.unique(idx[idx >= 0])}
                for c in np.flatnonzero(occ):
                    if areas[c] >= 0.5 * areas.max():  # the cell is (mostly) in view
                        d["occ_in_view"] += 1
                        d["occ_hidden"] += int(c) not in seen_cells
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hfov", type=float, nargs="+", default=[60.0], help="horizontal fields of view (deg)")
    ap.add_argument("--scenes", type=int, default=20)
    ap.add_argument("--setting", type=int, default=2, choices=sorted(SETTINGS))
    ap.add_argument("--supersample", type=int, default=RenderOptions().supersample)
    args = ap.parse_args()
    seeds = scene_seeds(args.setting, "paper", "train")[: args.scenes]
    k = SETTINGS[args.setting]
    print(f"{len(seeds)} scenes of setting {args.setting} (K={k}), 224x224, {ALTITUDE_M:g} m, nadir, "
          f"supersample {args.supersample}; stats are min / p10 / median / p90 / max")  # fmt: skip
    header = ("| hfov | view | cells in view | cell area px (cells in view) | person px (mask) | "
              "person px (effective) | people hidden | occupied cells with no person px |")  # fmt: skip
    print(header)
    print("|" + "---|" * 8)
    for hfov in args.hfov:
        res = measure(hfov, seeds, k, args.supersample)
        for name, d in res.items():
            full_areas = np.asarray(d["areas"])
            print(f"| {hfov:g} | {name} {POSITIONS[name]} | {np.median(d['in_view']):.0f} | {_stats(full_areas)} | "
                  f"{_stats(d['px'])} | {_stats(d['eff'])} | {d['hidden_people']}/{d['people']} "
                  f"({d['hidden_people'] / max(d['people'], 1):.1%}) | {d['occ_hidden']}/{d['occ_in_view']} "
                  f"({d['occ_hidden'] / max(d['occ_in_view'], 1):.1%}) |")  # fmt: skip


if __name__ == "__main__":
    main()
