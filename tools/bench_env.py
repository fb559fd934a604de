"""Steps per second of the gymnasium envs, beside the project's own no-grad rollout (the limit), as one table.

    python tools/bench_env.py [--setting 2] [--fusion learned] [--seconds 5] [--threads 1]

Rows: the single env with images rendered live and from the caches, with "cells" observations; the native vector
env at 1 / 16 / 256 episodes; and `run_search` on `CachedViews` (256 episodes of random moves, no grad), the rate
the project's own trainer rolls out at. With the wide family's caches (``--team-scenes N``, 0: skip): the single wide env
and the PettingZoo team env (3 vehicles, 80 s), whose row counts vehicle-steps (one vehicle decides a step), each also beside
one busy neighbour (a spinning process). Every env row steps uniformly random actions and resets ended episodes
(the vector env autoresets). The load average is printed at the start and the end: run it on a quiet machine.

A second table runs the 256-env vector env as a user does: at torch's default thread count on its own, beside one
busy neighbour (a spinning process the bench starts and stops), and at one thread, with the load beside each row;
and one thread beside the neighbour; the line under it checks busy >= 0.8x one thread, >= 20,000 steps/s and
>= 1000x the live-rendering env.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

import numpy as np
import torch

import uavsearch.envs  # noqa: F401 - registers the ids
import gymnasium as gym

from uavsearch.search.envs.search_env import ActiveSearchEnv
from uavsearch.search.policy import RandomPolicy
from uavsearch.search.search_loop import Agent, CachedViews, run_search


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def bench_single(env, seconds: float, max_steps: int | None = None) -> tuple[float, int, float]:
    rng = np.random.default_rng(0)
    env.reset(seed=0)
    env.step(int(rng.integers(env.action_space.n)))  # warm: the caches are loaded by the first reset
    env.reset(seed=1)
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds and (max_steps is None or n < max_steps):
        _, _, term, trunc, _ = env.step(int(rng.integers(env.action_space.n)))
        n += 1
        if term or trunc:
            env.reset()
    dt = time.perf_counter() - t0
    return n / dt, n, dt


def bench_vector(env_id: str, num_envs: int, seconds: float, **kw) -> tuple[float, int, float]:
    env = gym.make_vec(env_id, num_envs=num_envs, vectorization_mode="vector_entry_point", **kw)
    rng = np.random.default_rng(0)
    env.reset(seed=0)
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        env.step(rng.integers(env.single_action_space.n, size=num_envs))
        n += num_envs
    dt = time.perf_counter() - t0
    env.close()
    return n / dt, n, dt


def bench_team(env, seconds: float) -> tuple[float, int, float]:
    """Vehicle-steps/s of the team env: the deciding vehicle picks a viewpoint its mask allows, uniformly."""
    rng = np.random.default_rng(0)
    obs, _ = env.reset(seed=0)
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        d = env.deciding_agent
        acts = {a: env.KEEP_GOING for a in env.agents}
        acts[d] = int(rng.choice(np.flatnonzero(obs[d]["action_mask"][:-1])))
        obs, *_ = env.step(acts)
        n += 1
        if not env.agents:
            obs, _ = env.reset()
    dt = time.perf_counter() - t0
    return n / dt, n, dt


@torch.no_grad()
def bench_limit(cache, fusion, batch: int, seconds: float) -> tuple[float, int, float]:
    agent = Agent(fusion.frozen(), RandomPolicy(cache.config.num_actions))
    gen = torch.Generator().manual_seed(0)
    rows = np.arange(batch) % cache.num_scenes
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        ep = run_search(CachedViews(cache, rows, cache.config, agent.fusion.scorer), agent, generator=gen)
        n += batch * (ep.lattice_idx.shape[1] - 1)  # moves: what an env counts as steps
    dt = time.perf_counter() - t0
    return n / dt, n, dt


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--setting", default="2", help="paper setting 1 | 2 | 3")
    p.add_argument("--fusion", default=None, help="the envs' fusion (default: learned for the paper's settings)")
    p.add_argument("--seconds", type=float, default=5.0, help="seconds per row")
    p.add_argument("--live-steps", type=int, default=12, help="steps of the live-rendering row at most")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's own, as users run)")
    p.add_argument("--team-scenes", type=int, default=5, help="wide training scenes of the team rows (0: skip them)")
    a = p.parse_args(argv)
    if a.threads:
        torch.set_num_threads(a.threads)
    threads = torch.get_num_threads()
    env_id, setting = "uavsearch/ActiveSearch-v0", int(a.setting)
    kw = {"setting": setting, "progress": False, **({"fusion": a.fusion} if a.fusion else {})}
    start_load = _load()
    rows = []
    cells = ActiveSearchEnv(obs="cells", **kw)
    cells.reset(seed=0)  # loads (or builds) the caches once, before any clock runs
    cache, fusion = cells.scenes.cache, cells.fusion
    rows.append(("run_search on CachedViews, 256 episodes, no grad (the limit)", bench_limit(cache, fusion, 256, a.seconds)))
    live = ActiveSearchEnv(obs="image", views="live", **kw)
    rows.append(("single env, image, rendered live", bench_single(live, a.seconds, a.live_steps)))
    live.close()
    rows.append(("single env, image, cached views", bench_single(ActiveSearchEnv(obs="image", **kw), a.seconds)))
    rows.append(("single env, cells", bench_single(cells, a.seconds)))
    for n in (1, 16, 256):
        rows.append((f"native vector env, cells, {n} envs", bench_vector(env_id, n, a.seconds, obs="cells", **kw)))
    if a.team_scenes:
        from uavsearch.search.envs.search_env import WideSearchEnv
        from uavsearch.envs import team_parallel_env

        wide = WideSearchEnv(limit=a.team_scenes, progress=False)
        rows.append(("single wide env, cells (steps/s)", bench_single(wide, a.seconds)))
        rows.append(("single wide env, cells, one busy neighbour", beside_busy(lambda: bench_single(wide, a.seconds))))
        team = team_parallel_env(limit=a.team_scenes, progress=False)
        rows.append(("team env (PettingZoo, 3 vehicles, 80 s), vehicle-steps/s", bench_team(team, a.seconds)))
        rows.append(("team env, vehicle-steps/s, one busy neighbour", beside_busy(lambda: bench_team(team, a.seconds))))
    limit = rows[0][1][0]
    print(f"\nsetting {setting}, {fusion.name} fusion, {threads} torch thread(s); load average (1/5/15 min) "
          f"{start_load} at the start, {_load()} at the end, {os.cpu_count()} CPUs\n")
    print("| run | steps/s | share of the limit | steps | s |")
    print("|---|---|---|---|---|")
    for name, (rate, n, dt) in rows:
        print(f"| {name} | {rate:,.0f} | {rate / limit:.3f} | {n} | {dt:.1f} |" if rate >= 100 else
              f"| {name} | {rate:.2f} | {rate / limit:.5f} | {n} | {dt:.1f} |")
    vec = bench_threads(env_id, a.seconds, threads, obs="cells", **kw)
    print("\n| native vector env, cells, 256 envs | steps/s | load (1 min) |\n|---|---|---|")
    for name, (rate, load) in vec.items():
        print(f"| {name} | {rate:,.0f} | {load:.2f} |")
    busy, one = vec[f"{threads} torch threads, one busy neighbour"][0], vec["1 torch thread"][0]
    live_rate = rows[1][1][0]
    same = vec["1 torch thread, one busy neighbour"][0]
    print(f"\nbusy neighbour / one thread {busy / one:.2f} (want >= 0.80; beside the same neighbour "
          f"{busy / same:.2f}: on a loaded machine the neighbour's share of the cores shows too); busy {busy:,.0f} steps/s (want >= 20,000); "
          f"busy / live rendering {busy / live_rate:,.0f}x (want >= 1000x)")
    return 0


def beside_busy(run):
    """run() while one other process spins a core (a user's learner, a browser, another seed)."""
    spin = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        return run()
    finally:
        spin.kill()
        spin.wait()


def bench_threads(env_id: str, seconds: float, threads: int, **kw) -> dict[str, tuple[float, float]]:
    """The 256-env vector env at `threads` on its own and beside one spinning process, then at one thread:
    {row: (steps/s, 1-min load at its end)}."""

    def rate() -> tuple[float, float]:
        return bench_vector(env_id, 256, seconds, **kw)[0], os.getloadavg()[0]

    out = {f"{threads} torch threads, on its own": rate(),
           f"{threads} torch threads, one busy neighbour": beside_busy(rate)}
    torch.set_num_threads(1)  # the reference rows; this script's own process
    try:
        out["1 torch thread"] = rate()
        out["1 torch thread, one busy neighbour"] = beside_busy(rate)
    finally:
        torch.set_num_threads(threads)
    return out


if __name__ == "__main__":
    raise SystemExit(main())
