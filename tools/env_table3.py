"""Table III's rule played through WideSearch-v0 on the validation scenes it was chosen on, against the evaluation
code (run_search on the same view cache) and the figure results/search_wide/table3.md quotes.

    python tools/env_table3.py                 # T = 8 views, the 50 validation scenes (rendered first if missing)
    python tools/env_table3.py --budget 240 --scenes 5
    python tools/env_table3.py --budget 240 --scenes 10 --fusion neighbour:models/search_wide_240s_map.pt

`--fusion` plays the rule on another fusion (the learned stack's aggregation above: the env's buffered episodes
keep its running sums of cell features); the env's steps per second (one process, its torch threads) are printed.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from uavsearch.search.envs.search_env import TABLE3, LoopPolicyPlayer, WideSearchEnv, play_scenes
from uavsearch.search.scoring import score_episode
from uavsearch.search.search_loop import Agent, CachedViews, run_search
from uavsearch.search.wide_policies import rule_policy


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--budget", default="8", choices=sorted(TABLE3))
    ap.add_argument("--scenes", type=int, default=50, help="the first N validation scenes (Table III: all 50)")
    ap.add_argument("--fusion", default=None, help="the env's fusion spec (default: Table III's for the budget)")
    args = ap.parse_args(argv)
    env = WideSearchEnv(part="val", budget=args.budget, limit=args.scenes, render_all=True, fusion=args.fusion)
    task = TABLE3[args.budget]
    rule = rule_policy(env.config, task.rule)
    env.scenes.cache  # built (rendered) before the clock starts
    t0 = time.perf_counter()
    f1, routes = play_scenes(env, LoopPolicyPlayer(rule, env.config).act, env.scenes.seeds, "the rule through the env")
    steps_s = sum(len(r) - 1 for r in routes) / (time.perf_counter() - t0)
    cache = env.scenes.cache
    with torch.no_grad():
        ep = run_search(CachedViews(cache, np.arange(cache.num_scenes), env.config), Agent(env.fusion, rule))
    ref = score_episode(ep).f1[:, -1]
    same = sum(ep.lattice_idx[i, :len(r)].tolist() == r for i, r in enumerate(routes))
    print(f"budget {args.budget}, fusion {env.fusion.spec}, rule '{task.rule}', {len(f1)} validation scenes:")
    print(f"  env AF1 {np.mean(f1):.4f}; evaluation code AF1 {ref.mean():.4f}; same route on {same}/{len(f1)} scenes; "
          f"largest per-scene |difference| {np.abs(np.float32(f1) - np.float32(ref)).max():.2g}; "
          f"{steps_s:.0f} env steps/s ({torch.get_num_threads()} torch threads)")
    if len(f1) == 50 and args.fusion is None:
        print(f"  table3.md quotes {task.rule_val_af1:.3f} on all 50")
    return {"env": float(np.mean(f1)), "eval": float(ref.mean()), "same_routes": same, "steps_s": steps_s}


if __name__ == "__main__":
    main()
