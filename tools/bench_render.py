"""Render throughput at 224 x 224, each figure beside the limit it is measured against in the same run.

Tables: scene construction; where one frame's CPU time goes (time.process_time, so less sensitive to
other load than wall time), per ground mode, with each step's ratio to its limit (the full render vs
TinyRenderer's getCameraImage alone on the same bodies; TinyRenderer vs an empty world, its fixed
clear-and-copy cost; the downsampling vs the float mean it replaced); frames/s with 1 and 2 processes
(wall clock, render worker processes as the product runs them); the cost of supersampling.

Views are the 25 lattice positions {-20..20}^2 at 70 m, nadir, cycled.

    .venv/bin/python tools/bench_render.py            # default settings
    .venv/bin/python tools/bench_render.py --frames 50 --supersample 1 2 3
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from uavsearch.geometry import CameraIntrinsics, Grid, cell_label_image, cell_pixel_areas, nadir_camera_pose
from uavsearch.world.render import (
    RenderOptions,
    SceneRenderer,
    _block_share,
    _majority,
    _World,
    area_downsample,
    pb,
    projection_matrix,
    view_matrix,
)
from uavsearch.world.scene import generate_scene

LATTICE = [(x, y) for y in range(20, -21, -10) for x in range(-20, 21, 10)]
POSES = [nadir_camera_pose((float(x), float(y), 70.0)) for x, y in LATTICE]


def _cpu_ms(fn, frames: int) -> float:
    """CPU ms per call of fn(pose) over `frames` calls cycling the lattice (one warm-up lap first)."""
    for pose in POSES[:3]:
        fn(pose)
    t0 = time.process_time()
    for i in range(frames):
        fn(POSES[i % len(POSES)])
    return (time.process_time() - t0) / frames * 1e3


def _raw(world: _World, w: int, h: int, proj=None):
    """getCameraImage alone (TinyRenderer on the bodies as they are shown now), same arguments as capture."""
    o = world.options

    def call(pose):
        return pb.getCameraImage(w, h, view_matrix(pose), proj or world._proj, renderer=pb.ER_TINY_RENDERER,
                                 shadow=0, lightDirection=world._light, lightAmbientCoeff=o.ambient,
                                 lightDiffuseCoeff=o.diffuse, lightSpecularCoeff=0.0,
                                 physicsClientId=world._client)  # fmt: skip

    return call


def _show_only(world: _World, which: np.ndarray) -> None:
    """Show exactly the bodies flagged in `which` (alpha 0 hides a body from TinyRenderer)."""
    for i, b in enumerate(world._bodies):
        pb.changeVisualShape(int(b), -1, rgbaColor=[1, 1, 1, float(which[i])], physicsClientId=world._client)
    world._shown = which.copy()


def frame_breakdown(ground: str, frames: int, seed: int = 1) -> list[tuple[str, float, str, float]]:
    """(step, CPU ms, limit name, limit CPU ms) rows for one ground mode, in this process."""
    intr = CameraIntrinsics()
    opts = RenderOptions(ground=ground, isolate=False)
    s = opts.supersample
    world = _World(generate_scene(seed, 5), intr, opts)
    ss = intr.scaled(s)
    w, h = ss.width_px, ss.height_px
    try:
        full = _cpu_ms(lambda p: world.render(p.position_enu, p.R_enu_from_cam), frames)
        capture = _cpu_ms(world.capture, frames)
        raw = _raw(world, w, h)

        def raw_culled(pose):  # TinyRenderer on exactly the bodies the composite path draws for this view
            if world._ground is not None:
                world._cull(pose, ss)
            return raw(pose)

        gci = _cpu_ms(raw_culled, frames)
        rows = [("full render (render())", full, "TinyRenderer alone, same bodies", gci),
                ("capture (supersampled frame)", capture, "TinyRenderer alone, same bodies", gci)]  # fmt: skip
        tiny = _cpu_ms(_raw(world, 16, 16, projection_matrix(CameraIntrinsics(16, 16, intr.hfov_deg))), frames)
        rows.append(("TinyRenderer at 16 px (per-triangle work)", tiny, f"TinyRenderer at {w} px", gci))
        if world._ground is not None:
            cull = _cpu_ms(lambda p: world._cull(p, ss), frames)
            rows.append(("culling (which bodies to hide)", cull, "TinyRenderer alone, same bodies", gci))
            _, _, rgba, depth, seg = raw_culled(POSES[0])
            rgba = np.ascontiguousarray(rgba).reshape(h, w, 4)
            depth = np.asarray(depth, np.float32).reshape(h, w)
            pidx = world._seg_lut[np.clip(np.asarray(seg).reshape(h, w), -1, len(world._seg_lut) - 2)]
            comp = _cpu_ms(lambda p: world._ground.composite(rgba.copy(), depth, pidx.copy(), p, ss), frames)
            rows.append(("ground composite (warp + depth test)", comp, "TinyRenderer alone, same bodies", gci))
            # the bodies by group, culled as for the first view: where TinyRenderer's time goes
            world._cull(POSES[12], ss)
            shown = world._shown.copy()
            n_people = int(np.count_nonzero(world._seg_lut >= 0))
            is_person = np.arange(len(world._bodies)) < n_people
            centre = lambda fn: _cpu_ms(lambda p: fn(POSES[12]), frames)  # noqa: E731
            for name, which in (("people only", shown & is_person), ("static only", shown & ~is_person),
                                ("no bodies (clear + copy)", np.zeros_like(shown))):  # fmt: skip
                _show_only(world, which)
                rows.append((f"TinyRenderer centre view, {name}", centre(raw), "all shown bodies", 0.0))
            _show_only(world, shown)
            allb = centre(raw)
            rows = [(a, b, c, allb if c == "all shown bodies" else d) for a, b, c, d in rows]
        rgb, pidx = world.capture(POSES[0])
        ds = _cpu_ms(lambda p: area_downsample(rgb, s), frames)
        ref = _cpu_ms(lambda p: rgb.reshape(h // s, s, w // s, s, 3).astype(np.float32).mean(axis=(1, 3)), frames)
        rows.append(("area downsample (integer sums)", ds, "float mean (before)", ref))

        def people(p):
            frac = _block_share(pidx >= 0, s)
            _majority(pidx, s, frac > 0)

        rows.append(("person fraction + majority index", _cpu_ms(people, frames), "full render", full))
    finally:
        world.close()
    return rows


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a live process (Linux /proc), e.g. a render worker."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _run(seed: int, frames: int, supersample: int, ground: str, with_grid: bool, barrier=None, queue=None):
    """Render `frames` views through a render worker; returns (frames, wall s, CPU s of this process and
    its worker together)."""
    intr = CameraIntrinsics()
    spec = generate_scene(seed, 5)
    grid = Grid()
    with SceneRenderer(spec, intr, RenderOptions(supersample=supersample, ground=ground)) as r:
        r.render(POSES[0])  # warm-up
        if barrier is not None:
            barrier.wait()
        worker = r._worker.proc.pid
        t0, c0 = time.perf_counter(), time.process_time() + _cpu_s(worker)
        for i in range(frames):
            pose = POSES[i % len(POSES)]
            r.render(pose)
            if with_grid:
                cell_label_image(grid, intr, pose)
                cell_pixel_areas(grid, intr, pose)
        dt, cpu = time.perf_counter() - t0, time.process_time() + _cpu_s(worker) - c0
    if queue is not None:
        queue.put((frames, dt, cpu))
    return frames, dt, cpu


def throughput(procs: int, frames: int, supersample: int, ground: str, with_grid: bool) -> tuple[float, float]:
    """Frames/s over all processes (wall clock) and CPU ms per frame (each process with its worker)."""
    if procs == 1:
        results = [_run(1, frames, supersample, ground, with_grid)]
    else:
        ctx = mp.get_context("fork")
        barrier, queue = ctx.Barrier(procs), ctx.Queue()
        ps = [ctx.Process(target=_run, args=(1 + i, frames, supersample, ground, with_grid, barrier, queue))
              for i in range(procs)]  # fmt: skip
        for p in ps:
            p.start()
        results = [queue.get() for _ in ps]
        for p in ps:
            p.join()
    n = sum(r[0] for r in results)
    return n / max(r[1] for r in results), sum(r[2] for r in results) / n * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=50, help="frames per process per measurement")
    ap.add_argument("--supersample", type=int, nargs="+", default=[1, 2, 3], help="factors for the cost table")
    ap.add_argument("--scenes", type=int, default=3, help="scenes for the construction-time table")
    args = ap.parse_args()
    default_ss = RenderOptions().supersample
    print(f"load average at start: {' '.join(f'{v:.2f}' for v in os.getloadavg())} on {os.cpu_count()} cores")

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
    print(f"\nScene construction over {args.scenes} scenes (K=5), mean / max wall seconds:")
    print("| step | mean s | max s |\n|---|---|---|")
    print(f"| generate_scene | {np.mean(gen):.2f} | {np.max(gen):.2f} |")
    print(f"| SceneRenderer(...) build | {np.mean(build):.2f} | {np.max(build):.2f} |")

    for ground in ("composite", "mesh"):
        rows = frame_breakdown(ground, args.frames)
        print(f"\nOne frame, ground={ground!r}, supersample {default_ss}, CPU ms (time.process_time), in-process:")
        print("| step | ms | limit | limit ms | ratio |\n|---|---|---|---|---|")
        for name, ms, limit, lim_ms in rows:
            print(f"| {name} | {ms:.2f} | {limit} | {lim_ms:.2f} | {ms / lim_ms:.2f} |")

    print(f"\nThroughput at 224x224 through render workers, supersample {default_ss}, {args.frames} frames per "
          "process: wall frames/s (load-sensitive) and CPU ms per frame (process + its worker); ratio: 2 processes "
          "vs twice 1 (wall):")  # fmt: skip
    print("| ground | processes | render fps | render CPU ms | + grid projection fps | + grid CPU ms | ratio |")
    print("|---|---|---|---|---|---|---|")
    for ground in ("composite", "mesh"):
        f = {(p, g): throughput(p, args.frames, default_ss, ground, g) for p in (1, 2) for g in (False, True)}
        for p in (1, 2):
            ratio = f"{f[2, False][0] / (2 * f[1, False][0]):.2f}" if p == 2 else ""
            print(f"| {ground} | {p} | {f[p, False][0]:.1f} | {f[p, False][1]:.1f} | {f[p, True][0]:.1f} | "
                  f"{f[p, True][1]:.1f} | {ratio} |")  # fmt: skip

    rows = []
    for ss in tqdm(args.supersample, desc="supersampling", leave=False):
        rows.append((ss, throughput(1, args.frames, ss, "composite", False), throughput(1, args.frames, ss, "mesh", False)))
    print(f"\nRender cost vs supersampling (1 process, render only, {args.frames} frames), CPU ms per frame:")
    print("| supersample | rendered px | composite ms | mesh ms | composite / mesh |\n|---|---|---|---|---|")
    for ss, (_, c), (_, m) in rows:
        print(f"| {ss} | {224 * ss}x{224 * ss} | {c:.1f} | {m:.1f} | {c / m:.2f} |")
    print(f"\nload average at end: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()
