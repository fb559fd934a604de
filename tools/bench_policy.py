"""Policy steps per second in teleport mode: cached views (training and evaluation) vs. live rendering.

    .venv/bin/python tools/bench_policy.py [--threads 1] [--iterations 40] [--live]

A policy step = one move of one episode (B episodes x (T - 1) moves per rollout). "cached" rows read the
frozen perception's outputs from a view cache with the real feature sizes (synthetic values: speed does
not depend on them); "live" runs one episode at a time on a TeleportVehicle that renders every view and
runs perception on it (a random-init PerceptionNet: same cost as a trained one).

Every figure is printed beside its limit measured in the same run, as a ratio: a training iteration
(rollout + REINFORCE + Eq. 11, learned fusion) against the no-grad rollout of the same batch (B = 128,
confidence scores included), which is what an iteration would cost if its updates were free. Rates
are given per second of wall time and per second of this process's CPU time (`time.process_time`),
which a shared machine disturbs less; the load average is printed with them.
"""

import argparse
import os
import time

import torch

from uavsearch.search.agents import new_agent
from uavsearch.search.config import SearchConfig
from uavsearch.search.perception import PerceptionConfig, PerceptionNet
from uavsearch.search.search_loop import CachedViews, LiveViews, run_search
from uavsearch.search.train.policy import Args, train
from uavsearch.search.views import TeleportVehicle
from uavsearch.testing.synthetic_views import synthetic_cache
from uavsearch.world.scene import generate_scene


def timed(fn, repeat):
    """(wall s, CPU s) per call, after one warm-up call."""
    fn()
    t, c = time.perf_counter(), time.process_time()
    for _ in range(repeat):
        fn()
    return (time.perf_counter() - t) / repeat, (time.process_time() - c) / repeat


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--iterations", type=int, default=40, help="training iterations timed (default 40)")
    ap.add_argument("--live", action="store_true", help="also time live rendering (slow)")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    load0 = os.getloadavg()[0]
    cfg, pc = SearchConfig(), PerceptionConfig()
    cache = synthetic_cache(20, 5, cell_dim=pc.cell_dim, global_dim=pc.global_dim)
    agent = new_agent("learned", cfg, pc.global_dim, pc.cell_dim)
    conf = agent.fusion.eval().scorer
    agent.policy.eval()
    moves = cfg.budget_T - 1
    rows = []  # (name, steps/s wall, steps/s CPU, limit row or None)
    for B in (1, 128):
        src = CachedViews(cache, torch.arange(B) % 20, cfg, conf)
        gen = torch.Generator().manual_seed(0)
        with torch.no_grad():
            w, c = timed(lambda: run_search(src, agent, generator=gen), 20 if B > 1 else 100)
        rows.append((f"cached, evaluation rollout, B={B} (scores kept)", B * moves / w, B * moves / c, None))
    # the training batch: 16 scenes x 8 episodes, scores computed afresh each time as training must
    scenes = torch.arange(16).repeat_interleave(8)
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        w, c = timed(lambda: run_search(CachedViews(cache, scenes, cfg, conf), agent, generator=gen), 20)
    rows.append(("cached, no-grad rollout of a training batch, B=128", 128 * moves / w, 128 * moves / c, None))
    limit = len(rows) - 1
    args = Args(iterations=a.iterations, eval_every=10_000, scenes_per_batch=16, episodes_per_scene=8,
                progress=False, plot=False, runs_dir="/tmp/bench_policy_runs", threads=a.threads)
    res = train(args, caches=(cache, cache.subset([0, 1])))
    rows.append(("cached, training iteration (rollout + REINFORCE + Eq. 11), B=128", res.steps_per_s,
                 res.cpu_steps_per_s, limit))
    if a.live:
        net = PerceptionNet().eval()
        with TeleportVehicle(generate_scene(1200, 2), cfg) as vehicle:
            t, c = time.perf_counter(), time.process_time()
            run_search(LiveViews(vehicle, net), agent, generator=torch.Generator().manual_seed(0))
            w, c = time.perf_counter() - t, time.process_time() - c
        rows.append(("live teleport: render + perception per view, B=1 (CPU: this process only)", moves / w, moves / c,
                     None))
    print(f"torch threads {a.threads}; load average {load0:.2f} at start, {os.getloadavg()[0]:.2f} at end "
          f"({os.cpu_count()} CPUs)")
    print(f"{'mode':76s} {'steps/s wall':>13s} {'steps/s CPU':>12s} {'of limit (CPU)':>15s}")
    for name, sw, sc, lim in rows:
        ratio = f"{sc / rows[lim][2]:.2f}" if lim is not None else ""
        print(f"{name:76s} {sw:13.0f} {sc:12.0f} {ratio:>15s}")


if __name__ == "__main__":
    main()
