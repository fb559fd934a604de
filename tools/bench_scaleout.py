"""Views per second of the per-scene render task on each executor, each beside its limit, in one run.

Rows: SceneRenderer.render alone (one process, the same views, scenes built outside the clock); the
task (dataset.render_scene_shard: scene build, renders, cell geometry, shard bytes) on 1 and on 2 local
processes; the same task on a 2-node Ray cluster on this machine (ray.cluster_utils, 1 CPU per node,
loopback; its start-up is printed, not counted; its workers start inside the clock, as the local pool's).

The limit of a row with N workers is N cores' worth of render() alone: N / (its CPU s per view). CPU s /
view sums the CPU of each task's process and its render worker, so it holds on a busy machine; "cores
used" = CPU s / wall s shows how much of the machine a row got (the load average is printed: other jobs
share the cores). 1,000 views cost 1,000 times the CPU s / view.

    .venv/bin/python tools/bench_scaleout.py                    # 6 scenes x 25 views (the view cache's)
    .venv/bin/python tools/bench_scaleout.py --scenes 4 --views 10 --no-ray
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time

from uavsearch.geometry import nadir_camera_pose
from uavsearch.parallel import Executor, Store, map_scenes, process_tree_cpu_s
from uavsearch.search.config import SearchConfig
from uavsearch.search.data.dataset import ViewSetSpec, perception_scenes, positions_for_scene, render_scene_shard, render_tag
from uavsearch.world.render import SceneRenderer
from uavsearch.world.scene import generate_scene


def raw_rate(spec: ViewSetSpec) -> tuple[float, float, int]:
    """(views/s wall, CPU s per view, views) of SceneRenderer.render alone, one process (with its worker)."""
    config = SearchConfig()
    lattice = config.lattice.positions_enu
    wall = cpu = 0.0
    n = 0
    for s, k in spec.scenes:
        idx = positions_for_scene(spec, s, k, len(lattice))
        r = SceneRenderer(generate_scene(s, k), config.intrinsics, config.render)
        try:
            r.render(nadir_camera_pose(lattice[idx[0]]))  # warm: the scene is loaded in the worker
            t0, c0 = time.perf_counter(), process_tree_cpu_s()
            for i in idx:
                r.render(nadir_camera_pose(lattice[i]))
            wall += time.perf_counter() - t0
            cpu += process_tree_cpu_s() - c0
            n += len(idx)
        finally:
            r.close()
    return n / wall, cpu / n, n


def task_rate(spec: ViewSetSpec, executor: Executor) -> tuple[float, float, int, float]:
    """(views/s wall, CPU s per view, views, wall s) of render_scene_shard over the spec's scenes."""
    root = tempfile.mkdtemp(prefix="bench_scaleout_")
    try:
        jobs = [(spec.to_json(), Store(root), s, k, render_tag()) for s, k in spec.scenes]
        t0 = time.perf_counter()
        out = map_scenes(render_scene_shard, jobs, executor, progress=False)
        wall = time.perf_counter() - t0
    finally:
        shutil.rmtree(root, ignore_errors=True)
    views = sum(e["views"] for e in out)
    return views / wall, sum(e["cpu_s"] for e in out) / views, views, wall


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", type=int, default=6, help="scenes per row (default 6)")
    ap.add_argument("--views", type=int, default=25, help="lattice positions per scene (default 25, all)")
    ap.add_argument("--no-ray", action="store_true", help="leave out the Ray cluster row")
    a = ap.parse_args()
    spec = ViewSetSpec("bench", perception_scenes("train", a.scenes, 11), views_per_scene=a.views, seed=0)
    render_tag()  # the probe render, outside every clock
    load0 = os.getloadavg()
    rows = []
    raw, raw_cpu, n = raw_rate(spec)
    rows.append(("render() alone, 1 process", raw, raw_cpu, n, n / raw, 1 / raw_cpu))
    for jobs in (1, 2):
        r, c, v, w = task_rate(spec, Executor("local", jobs))
        rows.append((f"task, {jobs} local process{'es' if jobs > 1 else ''}", r, c, v, w, jobs / raw_cpu))
    if not a.no_ray:
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
        os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
        import ray
        from ray.cluster_utils import Cluster

        t0 = time.perf_counter()
        cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
        try:
            cluster.add_node(num_cpus=1)
            cluster.wait_for_nodes()
            start_s = time.perf_counter() - t0
            r, c, v, w = task_rate(spec, Executor("ray", address=cluster.address))
            rows.append((f"task, Ray 2 nodes x 1 CPU (cluster start {start_s:.0f} s)", r, c, v, w, 2 / raw_cpu))
        finally:
            ray.shutdown()
            cluster.shutdown()
    load1 = os.getloadavg()
    print(f"{a.scenes} scenes x {a.views} views per row; {os.cpu_count()} cores; load average "
          f"{load0[0]:.1f} at start, {load1[0]:.1f} at end (other jobs share the cores)\n")
    print(f"| {'run':<46} | views/s | limit views/s | cores used | CPU s / view | views | wall s |")
    print(f"|{'-' * 48}|---------|---------------|------------|--------------|-------|--------|")
    for name, rate, cpu, views, wall, limit in rows:
        print(f"| {name:<46} | {rate:7.2f} | {limit:13.2f} | {views * cpu / wall:10.2f} | {cpu:12.3f} | {views:5d} | "
              f"{wall:6.1f} |")
    cpu_task = rows[1][2]
    print(f"\ncost per 1,000 views (1 local process): {1000 * cpu_task:.0f} CPU s = {1000 * cpu_task / 3600:.2f} core-hours")


if __name__ == "__main__":
    main()
