"""Perception speed on CPU: ms per view for all 100 cells, pooled (one backbone pass per image) vs the
literal per-cell masked pass of Eq. 2 (one backbone pass per cell).

    .venv/bin/python tools/bench_perception.py [--threads 2] [--repeats 3] [--checkpoint models/perception.pt]
    .venv/bin/python tools/bench_perception.py --setting wide --altitude 40 --no-literal   # 900 cells, one view's

A scene family (`--setting wide`) pools its own grid (30 x 30 cells) at the altitude given: the cells in view
are what that altitude's footprint holds (the rest cost nothing but the label image's bincount).

Inputs are random images with the real label image of the start view (speed does not depend on pixel
values). CPU time (process time, all threads) is printed beside wall time because the machine is shared:
the CPU figure is the cost, the wall figure what you get right now.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch

from uavsearch.geometry import cell_label_image, nadir_camera_pose
from uavsearch.search.config import setting_config
from uavsearch.search.perception import PerceptionNet, images_to_tensor, load_perception, shipped_perception


def _time(fn, repeats: int) -> tuple[float, float]:
    fn()  # warm-up
    w0, c0 = time.perf_counter(), time.process_time()
    for _ in range(repeats):
        fn()
    return (time.perf_counter() - w0) / repeats, (time.process_time() - c0) / repeats


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--batch", type=int, default=32, help="views per batch for the batched pooled pass")
    ap.add_argument("--setting", default="2", help="whose grid and camera: a paper setting 1-3 or a family (wide)")
    ap.add_argument("--altitude", type=float, default=70.0, help="camera altitude in metres (nadir, over the centre)")
    ap.add_argument("--checkpoint", default=None, help="default: the setting's shipped net")
    ap.add_argument("--no-literal", action="store_true", help="skip the slow literal Eq. 2 rows")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    config = setting_config(int(a.setting) if a.setting.isdigit() else a.setting)
    checkpoint = a.checkpoint or str(shipped_perception(a.setting))
    if Path(checkpoint).is_file():
        net, _ = load_perception(checkpoint)
        src = checkpoint
    else:
        net, src = PerceptionNet().eval(), "random init"
    intr, grid = config.intrinsics, config.grid
    net = net.for_grid(grid.num_cells)
    label = cell_label_image(grid, intr, nadir_camera_pose([0.0, 0.0, a.altitude]))
    rng = np.random.default_rng(0)
    imgs = images_to_tensor(rng.integers(0, 256, (a.batch, intr.height_px, intr.width_px, 3), dtype=np.uint8))
    labs = torch.as_tensor(np.repeat(label[None], a.batch, 0))
    n_cells = int((np.bincount(label[label >= 0].astype(int), minlength=grid.num_cells) > 0).sum())
    params = sum(p.numel() for p in net.parameters())
    print(f"perception {src}: {params / 1e6:.2f} M parameters, backbone {net.cfg.layers}, "
          f"{n_cells} cells in the view at {a.altitude:g} m (grid of {grid.num_cells}), {a.threads} torch threads")

    rows = []
    alt = a.altitude
    with torch.no_grad():
        w, c = _time(lambda: net(imgs[:1], labs[:1], altitude_m=alt), a.repeats)
        rows.append(("pooled, batch 1", w * 1e3, c * 1e3))
        w, c = _time(lambda: net(imgs, labs, altitude_m=alt), a.repeats)
        rows.append((f"pooled, batch {a.batch}", w * 1e3 / a.batch, c * 1e3 / a.batch))
        if not a.no_literal:
            lit_rep = max(1, a.repeats // 3)
            w, c = _time(lambda: net.forward_literal(imgs[:1], labs[:1], batch_cells=False, altitude_m=alt), lit_rep)
            rows.append(("literal Eq. 2, one pass per cell", w * 1e3, c * 1e3))
            w, c = _time(lambda: net.forward_literal(imgs[:1], labs[:1], batch_cells=True, altitude_m=alt), lit_rep)
            rows.append(("literal Eq. 2, cells batched", w * 1e3, c * 1e3))

    ref = rows[2:] or rows[:1]
    lit_w, lit_c = min(r[1] for r in ref), min(r[2] for r in ref)
    print(f"\n| {'method (all cells of one view)':<36} | {'wall ms/view':>12} | {'CPU ms/view':>11} | "
          f"{'speed-up, wall':>14} | {'speed-up, CPU':>13} |")
    print(f"|{'-' * 38}|{'-' * 14}|{'-' * 13}|{'-' * 16}|{'-' * 15}|")
    for name, w, c in rows:
        print(f"| {name:<36} | {w:>12.1f} | {c:>11.1f} | {lit_w / w:>13.1f}x | {lit_c / c:>12.1f}x |")
    print("\nspeed-up: against the faster of the two literal variants (1.0x = that variant)" if not a.no_literal
          else "\nspeed-up: against pooled batch 1 (literal rows skipped)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
