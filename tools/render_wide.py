"""Render every viewpoint (72 + the start) of the wide families' scenes into the view-cache store, part by
part: test first, then val, then train (resumable: finished shards are skipped). Prints the wall time per
scene and the folder sizes; the perception caches are built from these renders by `uavsearch eval search`.

    nohup .venv/bin/python tools/render_wide.py --workers 2 > runs/render_wide.log 2>&1 &
    .venv/bin/python tools/render_wide.py --parts test --families wide --scenes 10
"""

from __future__ import annotations

import argparse
import subprocess
import time

from uavsearch.search.data.view_cache import CacheKey, render_lattice_views


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--families", default="wide,wide-uniform", help="comma-separated scene families")
    ap.add_argument("--parts", default="test,val,train", help="parts in the order to render them")
    ap.add_argument("--scenes", type=int, default=None, help="only the first N scenes of each part")
    ap.add_argument("--workers", type=int, default=2, help="local render processes")
    args = ap.parse_args()
    for part in args.parts.split(","):
        for family in args.families.split(","):
            key = CacheKey(family, "large", part)
            scenes = key.scenes()[: args.scenes]
            t0 = time.perf_counter()
            root = render_lattice_views(key, scenes, workers=args.workers, progress=True)
            dt = time.perf_counter() - t0
            size = subprocess.run(["du", "-sh", str(root)], capture_output=True, text=True).stdout.split()[0]
            print(f"{family} {part}: {len(scenes)} scenes x {key.search_config.lattice.num_positions} views in "
                  f"{dt:.0f} s ({dt / len(scenes):.1f} s wall per scene, {args.workers} workers; resumed scenes "
                  f"count as 0), {size} at {root}", flush=True)


if __name__ == "__main__":
    main()
