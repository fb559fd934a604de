"""The feature store's size and read speed at the wide family's real feature sizes, as one table.

    .venv/bin/python tools/bench_feature_store.py [--scenes 12] [--batch 64] [--repeat 30]

Writes `--scenes` scenes of random float16 features (73 viewpoints x 900 cells x the shipped wide
perception's cell_dim; values do not change sizes or speed) to a temporary store, then times what a
consumer does: one batch of B (scene, view) pairs over all scenes, one scene's every view, a cache's
features_at, and a CachedViews step with and without its features. Reads are from a warm page cache
(the files were just written); a cold read adds the disk's time for 187 KB per view. Sizes per 100
scenes and for the 500 training scenes are the per-scene file size times the count.
"""

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from uavsearch.search.config import setting_config
from uavsearch.search.data.feature_store import FeatureStore
from uavsearch.search.perception import load_perception
from uavsearch.search.search_loop import CachedViews
from uavsearch.paths import REPO_ROOT
from uavsearch.testing.synthetic_views import synthetic_cache


def timed(fn, repeat: int) -> float:
    """Milliseconds per call, after one warm-up call."""
    fn()
    t = time.perf_counter()
    for _ in range(repeat):
        fn()
    return (time.perf_counter() - t) / repeat * 1e3


def rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", type=int, default=12, help="scenes written to the temporary store")
    ap.add_argument("--batch", type=int, default=64, help="(scene, view) pairs per batch")
    ap.add_argument("--repeat", type=int, default=30, help="timed calls per row")
    args = ap.parse_args()
    torch.set_num_threads(1)

    config = setting_config("wide")
    net, _ = load_perception(REPO_ROOT / "models" / "perception_wide.pt")
    P, N, D = config.lattice.num_positions, config.grid.num_cells, net.cfg.cell_dim
    rng = np.random.default_rng(0)
    base = synthetic_cache(args.scenes, 10, cell_dim=2, config=config)
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-features-") as tmp:
        store = FeatureStore(Path(tmp) / "fs", "bench")
        t = time.perf_counter()
        for s in range(args.scenes):
            outputs = {k: getattr(base, k)[s].numpy() for k in ("log_probs", "global_feature", "cell_area_px", "valid")}
            store.write(s, rng.standard_normal((P, N, D), np.float32), outputs)
        write_ms = (time.perf_counter() - t) / args.scenes * 1e3
        scene_bytes = (Path(tmp) / "fs" / "0.npy").stat().st_size
        outputs_bytes = (Path(tmp) / "fs" / "0.npz").stat().st_size
        cache = base._replace(cell_features=torch.zeros(args.scenes, P, N, 0), feature_store=FeatureStore(Path(tmp) / "fs"))

        rows += [("bytes per view (float16)", f"{N * D * 2:,}", f"{N} cells x {D} features"),
                 ("bytes per scene (.npy)", f"{scene_bytes:,}", f"{P} views + header"),
                 ("per 100 wide scenes", f"{scene_bytes * 100 / 1e9:.2f} GB", "float32: twice that"),
                 ("500 training scenes", f"{scene_bytes * 500 / 1e9:.2f} GB", "mapped: page cache, not process memory"),
                 ("other outputs per scene (.npz)", f"{outputs_bytes:,}", "log-probs, areas, validity, global"),
                 ("write one scene", f"{write_ms:.1f} ms", "")]

        seeds = rng.integers(0, args.scenes, args.batch)
        views = torch.as_tensor(rng.integers(0, P, args.batch))
        before = rss_mb()
        ms = timed(lambda: store.gather(seeds, views), args.repeat)
        rows.append((f"gather a batch of {args.batch} views", f"{ms:.2f} ms",
                     f"{args.batch * N * D * 2 / ms / 1e6:.2f} GB/s; RSS +{rss_mb() - before:.0f} MB"))
        ms = timed(lambda: store.read(0, torch.arange(P)), args.repeat)
        rows.append((f"read one scene's {P} views", f"{ms:.2f} ms", f"{P * N * D * 2 / ms / 1e6:.2f} GB/s"))
        r = torch.as_tensor(seeds)
        ms = timed(lambda: cache.features_at(r, views).float(), args.repeat)
        rows.append((f"features_at, {args.batch} views, float32", f"{ms:.2f} ms", "what CachedViews serves"))
        for features in (False, True):
            src = CachedViews(cache, seeds, config, features=features)
            ms = timed(lambda: src.observe(views), args.repeat)
            rows.append((f"CachedViews.observe, features={features}", f"{ms:.2f} ms", f"B = {args.batch}"))
        rows.append(("process RSS at the end", f"{rss_mb():.0f} MB",
                     f"the store holds {args.scenes * scene_bytes / 1e6:.0f} MB"))

    w = max(len(a) for a, _, _ in rows)
    v = max(len(b) for _, b, _ in rows)
    print(f"{'':<{w}}  {'':>{v}}  (torch threads 1; {args.scenes} scenes of ({P}, {N}, {D}))")
    for a, b, c in rows:
        print(f"{a:<{w}}  {b:>{v}}  {c}")


if __name__ == "__main__":
    main()
