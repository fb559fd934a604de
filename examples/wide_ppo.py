"""PPO on the wide family (WideSearch-v0, Table III's task at T = 8 views), scored on validation scenes against
Table III's rule and its best fixed route with the paired 95% bootstrap interval.

    python examples/wide_ppo.py                  # brief: 5 training scenes, 5 validation scenes, a few CPU-minutes
    python examples/wide_ppo.py --long           # 50 training scenes, all 50 validation scenes, 10x the steps

Training is examples/cleanrl_ppo.py's PPO on the native vector env of the family's first training scenes
(rendered on first use, about 5 s a scene on 2 cores: search_env.WIDE_SCENE_S); the best fixed route is Table
III's view set searched on those same training scenes (evaluate/wide.py fixed_agents); the rule and the route
are played through the same env as the PPO actor (search_env.LoopPolicyPlayer), so all three are scored on the
same maps.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch
from gymnasium.spaces import flatten

sys.path.insert(0, str(Path(__file__).resolve().parent))
import cleanrl_ppo  # noqa: E402

from uavsearch.search.envs.search_env import TABLE3, LoopPolicyPlayer, WideSearchEnv, play_scenes  # noqa: E402
from uavsearch.search.metrics import bootstrap_ci  # noqa: E402
from uavsearch.search.evaluate.wide import LABELS, fixed_agents  # noqa: E402
from uavsearch.search.policy import load_search_model  # noqa: E402


def play(env, act, desc: str) -> np.ndarray:
    """Final F1 per validation scene of a policy act(obs, info) -> action, played through the env."""
    return np.asarray(play_scenes(env, act, env.scenes.seeds, desc)[0])


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--long", action="store_true", help="50 training scenes, 50 validation scenes, 10x the steps")
    ap.add_argument("--train-scenes", type=int, default=None)
    ap.add_argument("--val-scenes", type=int, default=None)
    ap.add_argument("--total-timesteps", type=int, default=None)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--runs-dir", default=None)
    a = ap.parse_args(argv)
    train_n = a.train_scenes or (50 if a.long else 5)
    val_n = a.val_scenes or (50 if a.long else 5)
    steps = a.total_timesteps or (300_000 if a.long else 30_000)
    budget = "8"
    args = cleanrl_ppo.Args(env_id="uavsearch/WideSearch-v0", setting="wide", limit=train_n, total_timesteps=steps,
                            seed=a.seed, num_envs=32, num_steps=16, **({"runs_dir": a.runs_dir} if a.runs_dir else {}))
    print(f"training PPO on the first {train_n} training scenes of the wide family for {steps} steps "
          f"(T = 8 views, fusion {TABLE3[budget].fusion})", flush=True)
    out = cleanrl_ppo.train(args)
    _, actor, _ = load_search_model(out["checkpoint"], "cpu")
    actor.eval()
    train_env = WideSearchEnv(part="train", limit=train_n, budget=budget)
    val = WideSearchEnv(part="val", limit=val_n, budget=budget)
    agents, _ = fixed_agents(val.config, val.fusion, train_env.scenes.cache)
    best = TABLE3[budget].best_fixed
    from uavsearch.search.wide_policies import rule_policy

    def ppo(obs, info):
        with torch.no_grad():
            x = torch.as_tensor(flatten(val.observation_space, obs), dtype=torch.float32)[None]
            return int(actor(x).argmax(1))

    f1 = {"PPO (this run)": play(val, ppo, "PPO on validation"),
          "the rule": play(val, LoopPolicyPlayer(rule_policy(val.config, TABLE3[budget].rule), val.config).act,
                           "the rule on validation"),
          "best fixed route": play(val, LoopPolicyPlayer(agents[best].policy, val.config).act,
                                   "best fixed route on validation")}
    print(f"\ncompared on the first {val_n} validation scenes (T = 8 views, {val.fusion.spec}): Table III's rule "
          f"('{TABLE3[budget].rule}') and its best fixed route ({LABELS[best]}, searched on the same {train_n} "
          "training scenes); Δ: per-scene final F1 minus the reference's, mean [95% bootstrap interval over scenes]")
    for name, v in f1.items():
        print(f"  {name:<18} AF1 {v.mean():.3f}")
    result = {}
    for ref in ("the rule", "best fixed route"):
        mean, lo, hi = bootstrap_ci(f1["PPO (this run)"] - f1[ref])
        result[ref] = (mean, lo, hi)
        print(f"  PPO vs {ref:<16} Δ AF1 {mean:+.3f} [{lo:+.3f}, {hi:+.3f}]")
    return {"af1": {k: float(v.mean()) for k, v in f1.items()}, "delta": result, **out}


if __name__ == "__main__":
    main()
