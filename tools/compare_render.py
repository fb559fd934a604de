"""Composite ground vs textured-quad ground: how close the two renderers' images are, per scene.

Renders the 25 lattice views at 70 m of test scenes of settings 1-3 with RenderOptions(ground="mesh")
(the reference: TinyRenderer draws the ground quad) and ground="composite" (the shaded ground texture
warped to the camera under the bodies), and prints per scene: RGB PSNR (mean and min over views; a
view whose images are identical counts as PSNR_CAP dB), the share of identical pixel values, the
person mask's IoU and identical-pixel share, whether person_index is identical, and the CPU ms per
frame of each. With a perception checkpoint it also prints how the net's p(occupied) moves on the
cells in view (mean |delta p|, share of decisions at 0.5 that flip). --png writes the worst view side
by side: mesh | composite | |difference| x 4.

    .venv/bin/python tools/compare_render.py
    .venv/bin/python tools/compare_render.py --png /tmp/compare.png --perception models/perception.pt
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from uavsearch.geometry import nadir_camera_pose
from uavsearch.search.config import SearchConfig
from uavsearch.world.render import RenderOptions, SceneRenderer
from uavsearch.world.scene import generate_scene
from uavsearch.world.settings import SETTINGS, scene_seeds

PSNR_CAP = 100.0  # dB for a pair of identical images (their PSNR is infinite)
# Four test scenes over settings 1-3 (setting, index into its test seeds).
SCENES = ((1, 0), (2, 0), (3, 0), (2, 1))


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return PSNR_CAP if mse == 0 else min(PSNR_CAP, 10.0 * np.log10(255.0**2 / mse))


def render_views(spec, config: SearchConfig, ground: str) -> tuple[list, float]:
    """The lattice views of one scene with one ground mode, and the CPU ms per frame (this process and
    its render worker together are not separable: the world is built in-process to time it)."""
    options = RenderOptions(ground=ground, isolate=False)
    out = []
    with SceneRenderer(spec, config.intrinsics, options) as r:
        r.render(nadir_camera_pose(config.lattice.positions_enu[0]))  # warm-up
        t0 = time.process_time()
        for pos in config.lattice.positions_enu:
            out.append(r.render(nadir_camera_pose(pos)))
        ms = (time.process_time() - t0) / len(out) * 1e3
    return out, ms


def perception_delta(net, config: SearchConfig, old: list, new: list) -> tuple[np.ndarray, np.ndarray]:
    """p(occupied) of the cells in view under both renderers (flattened over views)."""
    import torch

    from uavsearch.search.views import make_view

    p_old, p_new = [], []
    for pos, a, b in zip(config.lattice.positions_enu, old, new):
        va = make_view(a.rgb, nadir_camera_pose(pos), config.grid, config.intrinsics, None, config.min_cell_area_px)
        with torch.no_grad():
            lp = net(np.stack([a.rgb, b.rgb]), np.stack([va.cell_label, va.cell_label]))
        p = lp[..., 1].exp().numpy()
        p_old.append(p[0][va.cells_in_view])
        p_new.append(p[1][va.cells_in_view])
    return np.concatenate(p_old), np.concatenate(p_new)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--png", type=Path, help="write the lowest-PSNR view: mesh | composite | |diff| x 4")
    ap.add_argument("--perception", type=Path, default=Path("models/perception.pt"),
                    help="perception checkpoint for the decision-flip table ('' to skip)")  # fmt: skip
    args = ap.parse_args()
    config = SearchConfig()
    net = None
    if str(args.perception) and args.perception.is_file():
        from uavsearch.search.perception import load_perception

        net, _ = load_perception(args.perception)
    print("| setting | seed | views | PSNR mean dB | PSNR min dB | identical values | person IoU | "
          "person px identical | person_index identical | ms mesh | ms composite |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    worst, all_p = (PSNR_CAP + 1, None), []
    totals = {"psnr": [], "same": [], "inter": 0, "union": 0, "mask_same": [], "index_same": [], "ms": []}
    for setting, k in SCENES:
        seed = scene_seeds(setting, "paper", "test")[k]
        spec = generate_scene(seed, SETTINGS[setting])
        old, ms_old = render_views(spec, config, "mesh")
        new, ms_new = render_views(spec, config, "composite")
        ps = [psnr(a.rgb, b.rgb) for a, b in zip(old, new)]
        same = np.mean([np.mean(a.rgb == b.rgb) for a, b in zip(old, new)])
        inter = sum(int((a.person_mask & b.person_mask).sum()) for a, b in zip(old, new))
        union = sum(int((a.person_mask | b.person_mask).sum()) for a, b in zip(old, new))
        mask_same = np.mean([np.mean(a.person_mask == b.person_mask) for a, b in zip(old, new)])
        index_same = all(np.array_equal(a.person_index, b.person_index) for a, b in zip(old, new))
        i = int(np.argmin(ps))
        if ps[i] < worst[0]:
            worst = (ps[i], (old[i].rgb, new[i].rgb, seed, i))
        print(f"| {setting} | {seed} | {len(ps)} | {np.mean(ps):.1f} | {np.min(ps):.1f} | {same:.5f} | "
              f"{inter / max(union, 1):.4f} | {mask_same:.6f} | {index_same} | {ms_old:.0f} | {ms_new:.0f} |")  # fmt: skip
        totals["psnr"] += ps
        totals["same"].append(same)
        totals["inter"] += inter
        totals["union"] += union
        totals["mask_same"].append(mask_same)
        totals["index_same"].append(index_same)
        totals["ms"].append((ms_old, ms_new))
        if net is not None:
            all_p.append(perception_delta(net, config, old, new))
    ms = np.mean(totals["ms"], axis=0)
    print(f"| all | | {len(totals['psnr'])} | {np.mean(totals['psnr']):.1f} | {np.min(totals['psnr']):.1f} | "
          f"{np.mean(totals['same']):.5f} | {totals['inter'] / max(totals['union'], 1):.4f} | "
          f"{np.mean(totals['mask_same']):.6f} | {all(totals['index_same'])} | {ms[0]:.0f} | {ms[1]:.0f} |")  # fmt: skip
    if all_p:
        p_old = np.concatenate([a for a, _ in all_p])
        p_new = np.concatenate([b for _, b in all_p])
        flips = np.mean((p_old >= 0.5) != (p_new >= 0.5))
        print(f"\nPerception ({args.perception}) on the {len(p_old)} cells in view of those views:")
        print("| mean abs delta p(occupied) | max abs delta | decisions at 0.5 that flip |\n|---|---|---|")
        print(f"| {np.mean(np.abs(p_new - p_old)):.3g} | {np.max(np.abs(p_new - p_old)):.3g} | "
              f"{flips:.4%} ({int(round(flips * len(p_old)))} cells) |")  # fmt: skip
    if args.png is not None and worst[1] is not None:
        a, b, seed, i = worst[1]
        diff = np.clip(np.abs(a.astype(int) - b.astype(int)) * 4, 0, 255).astype(np.uint8)
        args.png.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(args.png), np.hstack([a, b, diff])[:, :, ::-1])
        print(f"\nworst view (scene {seed}, lattice index {i}, PSNR {worst[0]:.1f} dB) -> {args.png}")


if __name__ == "__main__":
    main()
