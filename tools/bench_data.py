"""Times building a wide family's view and perception caches for N scenes into a temporary folder: the
renders (every lattice position of each scene, `workers` processes) and then the perception cache over them.
Prints views rendered/s and perceived/s, CPU seconds per scene (this process and its children), wall, the
wall projected for 100 scenes on 2 cores (from CPU seconds) and the load beside them.

    .venv/bin/python tools/bench_data.py --scenes 4
    .venv/bin/python tools/bench_data.py --scenes 2 --out cache/bench_data   # keep the caches (byte checks)
"""

from __future__ import annotations

import argparse
import ctypes
import os
import tempfile
import time

import torch

from uavsearch.parallel import process_tree_cpu_s
from uavsearch.search.data.view_cache import CacheKey, build_view_cache, render_lattice_views, world_tag
from uavsearch.search.perception import PerceptionConfig, PerceptionNet


def _adopt_orphans() -> None:
    """Make this process the reaper of its orphaned descendants (Linux): a render pool's processes end
    before their render workers, whose CPU seconds then count in this tree once reaped (_reap)."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(36, 1, 0, 0, 0)  # PR_SET_CHILD_SUBREAPER
    except (OSError, AttributeError):
        pass


def _reap(seconds: float = 3.0) -> None:
    """Reap the adopted render workers as they exit (they stop once their pool process is gone)."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            pid, _ = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            return
        if pid == 0:
            time.sleep(0.1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=4, help="the first N scenes of the part")
    ap.add_argument("--family", default="wide", help="scene family")
    ap.add_argument("--part", default="val", help="part whose first scenes are built")
    ap.add_argument("--workers", type=int, default=2, help="local render processes")
    ap.add_argument("--out", default=None, help="cache folder to build into (kept); default a temporary one")
    args = ap.parse_args()
    _adopt_orphans()
    if args.scenes < 1:
        ap.error("--scenes must be at least 1")
    torch.manual_seed(0)  # a seeded stand-in net: the shipped one's architecture and cost, reproducible bytes
    net = PerceptionNet(PerceptionConfig(num_cells=900, altitude_feature=True)).eval()
    key = CacheKey(args.family, "large", args.part, limit=args.scenes)
    scenes = key.scenes()
    views = len(scenes) * key.search_config.lattice.num_positions
    with tempfile.TemporaryDirectory() as tmp:
        cache_dir = args.out or tmp
        load0 = os.getloadavg()[0]
        t0, c0 = time.perf_counter(), process_tree_cpu_s()
        world = world_tag(key.search_config, key.family)  # the folder build_view_cache reads its renders from
        render_lattice_views(key, scenes, root=f"{cache_dir}/lattice_views/{world}/{key.part_name}",
                             workers=args.workers, progress=True)
        t1 = time.perf_counter()
        _reap()
        c1, t1_reaped = process_tree_cpu_s(), time.perf_counter()
        path = build_view_cache(net, key, scenes, cache_dir=cache_dir, workers=args.workers, progress=True)
        t2, c2 = time.perf_counter(), process_tree_cpu_s()
        load1 = os.getloadavg()[0]
    render_s, render_cpu = t1 - t0, c1 - c0
    perceive_s, perceive_cpu = t2 - t1_reaped, c2 - c1  # the renders above are reused: this is perception
    cpu_per_scene = (render_cpu + perceive_cpu) / len(scenes)
    print(f"\n{args.family} {args.part}: {len(scenes)} scenes x {key.search_config.lattice.num_positions} views, "
          f"{args.workers} render workers, cache {path if args.out else '(temporary)'}")
    print("| scenes | views rendered/s | views perceived/s | CPU s per scene (render + perceive) | wall s "
          "| projected wall, 100 scenes on 2 cores | load (1 min, start/end) |")
    print("|---|---|---|---|---|---|---|")
    print(f"| {len(scenes)} | {views / render_s:.1f} | {views / perceive_s:.1f} | {cpu_per_scene:.2f} "
          f"({render_cpu / len(scenes):.2f} + {perceive_cpu / len(scenes):.2f}) | {render_s + perceive_s:.1f} "
          f"| {100 * cpu_per_scene / 2 / 60:.1f} min | {load0:.1f} / {load1:.1f} |")


if __name__ == "__main__":
    main()
