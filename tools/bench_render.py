"""Render throughput at 224 x 224 (issue 2, item 8): frames/s of SceneRenderer.render alone and with
the per-view grid projection (cell_label_image + cell_pixel_areas), with 1 and 2 processes; the cost
of supersampling; and scene construction time (generate_scene, SceneRenderer build).

Views are the 25 lattice positions {-20..20}^2 at 70 m, nadir, cycled.

    .venv/bin/python tools/bench_render.py            # default settings
    .venv/bin/python tools/bench_render.py --frames 50 --supersample 1 2 3 4
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import time

import numpy as np
from tqdm import tqdm

from uavsearch.geometry import CameraIntrinsics, Grid, cell_label_image, cell_pixel_areas, nadir_camera_pose
from uavsearch.world.render import RenderOptions, SceneRenderer
from uavsearch.world.scene import generate_scene

LATTICE = [(x, y) for y in range(20, -21, -10) for x in range(-20, 21, 10)]


def _poses():
    return [nadir_camera_pose((float(x), float(y), 70.0)) for x, y in LATTICE]


def _run(seed: int, frames: int, supersample: int, with_grid: bool, barrier=None, queue=None):
    intr = CameraIntrinsics()
    spec = generate_scene(seed, 5)
    grid = Grid()
    with SceneRenderer(spec, intr, RenderOptions(supersample=supersample)) as r:
        poses = _poses()
        r.render(poses[0])  # warm-up
        if barrier is not None:
            barrier.wait()
        t0 = time.perf_counter()
        for i in range(frames):
            pose = poses[i % len(poses)]
            r.render(pose)
            if with_grid:
                cell_label_image(grid, intr, pose)
                cell_pixel_areas(grid, intr, pose)
        dt = time.perf_counter() - t0
    if queue is not None:
        queue.put((frames, dt))
    return frames, dt


def throughput(procs: int, frames: int, supersample: int, with_grid: bool) -> float:
    if procs == 1:
        n, dt = _run(1, frames, supersample, with_grid)
        return n / dt
    ctx = mp.get_context("fork")
    barrier, queue = ctx.Barrier(procs), ctx.Queue()
    ps = [ctx.Process(target=_run, args=(1 + i, frames, supersample, with_grid, barrier, queue)) for i in range(procs)]
    for p in ps:
        p.start()
    results = [queue.get() for _ in ps]
    for p in ps:
        p.join()
    return sum(n for n, _ in results) / max(dt for _, dt in results)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=50, help="frames per process per measurement")
    ap.add_argument("--supersample", type=int, nargs="+", default=[1, 2, 3, 4], help="factors for the cost table")
    ap.add_argument("--scenes", type=int, default=5, help="scenes for the construction-time table")
    args = ap.parse_args()
    default_ss = RenderOptions().supersample

    gen, build = [], []
    for seed in tqdm(range(args.scenes), desc="scene construction", leave=False):
        t0 = time.perf_counter()
        spec = generate_scene(seed, 5)
        t1 = time.perf_counter()
        r = SceneRenderer(spec, CameraIntrinsics())
        t2 = time.perf_counter()
        r.close()
        gen.append(t1 - t0)
        build.append(t2 - t1)
    print(f"\nScene construction over {args.scenes} scenes (K=5), mean / max seconds:")
    print("| step | mean s | max s |\n|---|---|---|")
    print(f"| generate_scene | {np.mean(gen):.2f} | {np.max(gen):.2f} |")
    print(f"| SceneRenderer(...) build | {np.mean(build):.2f} | {np.max(build):.2f} |")

    rows = []
    jobs = [(p, g) for g in (False, True) for p in (1, 2)]
    for procs, with_grid in tqdm(jobs, desc="throughput", leave=False):
        rows.append((procs, with_grid, throughput(procs, args.frames, default_ss, with_grid)))
    print(f"\nFrames/s at 224x224, default options (supersample {default_ss}), {args.frames} frames per process:")
    print("| processes | render only | render + cell_label_image + cell_pixel_areas |\n|---|---|---|")
    for procs in (1, 2):
        a = next(f for p, g, f in rows if p == procs and not g)
        b = next(f for p, g, f in rows if p == procs and g)
        print(f"| {procs} | {a:.1f} | {b:.1f} |")

    print(f"\nRender cost vs supersampling (1 process, render only, {args.frames} frames):")
    print("| supersample | rendered px | frames/s | ms/frame |\n|---|---|---|---|")
    for ss in tqdm(args.supersample, desc="supersampling", leave=False):
        fps = throughput(1, args.frames, ss, False)
        print(f"| {ss} | {224 * ss}x{224 * ss} | {fps:.1f} | {1000 / fps:.0f} |")


if __name__ == "__main__":
    main()
