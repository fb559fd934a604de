"""Policy steps per second in teleport mode: cached views (training and evaluation) vs. live rendering.

    .venv/bin/python tools/bench_policy.py [--threads 1] [--live]

A policy step = one move of one episode (B episodes x (T - 1) moves per rollout). "cached" rows read the
frozen perception's outputs from a view cache with the real feature sizes (synthetic values: speed does
not depend on them); "live" runs one episode at a time on a TeleportVehicle that renders every view and
runs perception on it (a random-init PerceptionNet: same cost as a trained one).
"""

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))

from synthetic_views import synthetic_cache  # noqa: E402

from uavsearch.search.agents import new_agent  # noqa: E402
from uavsearch.search.config import SearchConfig  # noqa: E402
from uavsearch.search.perception import PerceptionConfig, PerceptionNet  # noqa: E402
from uavsearch.search.search_loop import CachedViews, LiveViews, run_search  # noqa: E402
from uavsearch.search.train_policy import Args, train  # noqa: E402
from uavsearch.search.views import TeleportVehicle  # noqa: E402
from uavsearch.world.scene import generate_scene  # noqa: E402


def timed(fn, repeat):
    fn()
    t = time.perf_counter()
    for _ in range(repeat):
        fn()
    return (time.perf_counter() - t) / repeat


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--live", action="store_true", help="also time live rendering (slow)")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    cfg, pc = SearchConfig(), PerceptionConfig()
    cache = synthetic_cache(20, 5, cell_dim=pc.cell_dim, global_dim=pc.global_dim)
    agent = new_agent("learned", cfg, pc.global_dim, pc.cell_dim)
    conf = agent.confidence.eval()
    agent.policy.eval()
    moves = cfg.budget_T - 1
    rows = []
    for B in (1, 128):
        src = CachedViews(cache, torch.arange(B) % 20, cfg, conf)
        gen = torch.Generator().manual_seed(0)
        with torch.no_grad():
            dt = timed(lambda: run_search(src, agent, generator=gen), 20 if B > 1 else 100)
        rows.append((f"cached, evaluation rollout, B={B}", B * moves / dt, dt * 1e3))
    args = Args(iterations=20, eval_every=10_000, scenes_per_batch=16, episodes_per_scene=8, progress=False,
                plot=False, runs_dir="/tmp/bench_policy_runs", threads=a.threads)
    res = train(args, caches=(cache, cache.subset([0, 1])))
    rows.append(("cached, training iteration (rollout + REINFORCE + Eq. 11), B=128", res.steps_per_s,
                 128 * moves / res.steps_per_s * 1e3))
    if a.live:
        net = PerceptionNet().eval()
        with TeleportVehicle(generate_scene(1200, 2), cfg) as vehicle:
            t = time.perf_counter()
            run_search(LiveViews(vehicle, net), agent, generator=torch.Generator().manual_seed(0))
            dt = time.perf_counter() - t
        rows.append(("live teleport: render + perception per view, B=1", moves / dt, dt * 1e3))
    print(f"{'mode':70s} {'policy steps/s':>15s} {'ms per rollout/iteration':>25s}")
    for name, sps, ms in rows:
        print(f"{name:70s} {sps:15.0f} {ms:25.1f}")


if __name__ == "__main__":
    main()
