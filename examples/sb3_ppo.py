"""Stable-Baselines3 PPO on uavsearch's search env (cached "cells" observations), exported for `uavsearch eval search`.

    pip install -e .[sb3]
    python examples/sb3_ppo.py --setting 2 --total-timesteps 200000          # a few CPU-minutes
    python examples/sb3_ppo.py --setting 2 --ship                              # and copy it to models/
    uavsearch eval search --setting 2 --out results/eval_ppo                   # Table II's "PPO (external)" row

SB3 steps uavsearch's native vector env (``gym.make_vec(..., vectorization_mode="vector_entry_point")``, flattened
by gymnasium's vector FlattenObservation) through `NativeVecEnv`, a small SB3 VecEnv adapter: SB3 resets an
ended episode in the same step (the final observation in ``info["terminal_observation"]``), which the adapter
does with the vector env's ``reset(options={"reset_mask": ended})``. ``--single`` uses SB3's own DummyVecEnv of
single envs instead (slower: one Python env step per episode step). SB3's MlpPolicy reads the flattened
observation; at the end its actor (the policy MLP and the action head) is copied into uavsearch's
`ExternalPolicyNet`, whose checkpoint ``search_s<K>_<fusion>_external.pt`` needs no SB3 to load. The run writes ``runs/<name>__<seed>__<time>/``:
args.json, SB3's own ``ppo.zip`` and the checkpoint; ``--ship`` copies the checkpoint to models/.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from gymnasium.wrappers import FlattenObservation
from torch import nn

import uavsearch.envs  # noqa: F401 - registers the ids
from uavsearch.cli_args import add_dataclass_args, dataclass_from_args, opt
from uavsearch.paths import MODELS_DIR, RUNS_DIR
from uavsearch.search.agents import checkpoint_path
from uavsearch.search.config import config_to_dict
from uavsearch.search.external_policy import ExternalPolicyNet
from uavsearch.search.policy import save_search_model
from uavsearch.search.train.runs import seed_everything


@dataclass
class Args:
    env_id: str = opt("uavsearch/ActiveSearch-v0", "the gymnasium id")
    setting: str = opt("2", "paper setting 1 | 2 | 3")
    reward: str = opt("shaped", "the env's reward: shaped (per step) or terminal (the same sum)")
    limit: int = opt(0, "train on the part's first scenes only (0: all)")
    seed: int = opt(1, "seeds random, numpy, torch, the envs and SB3")
    total_timesteps: int = opt(200_000, "env steps in all")
    n_envs: int = opt(16, "episodes stepped together")
    single: bool = opt(False, "SB3's DummyVecEnv of single envs instead of the native vector env")
    n_steps: int = opt(128, "steps per env per rollout")
    batch_size: int = opt(256, "SB3's minibatch")
    n_epochs: int = opt(4, "epochs per rollout")
    learning_rate: float = opt(3e-4, "Adam's")
    gamma: float = opt(1.0, "discount (episodes are a handful of steps)")
    ent_coef: float = opt(0.01, "entropy bonus")
    hidden: str = opt("64,64", "the actor's and critic's hidden layers (tanh)")
    threads: int = opt(1, "torch CPU threads")
    runs_dir: str = opt(str(RUNS_DIR), "parent of the run directory")
    ship: bool = opt(False, "copy the checkpoint to models/ (what `uavsearch eval search` reads)")


def export_actor(model, config) -> ExternalPolicyNet:
    """SB3's actor (FlattenExtractor -> policy MLP -> action_net) as an ExternalPolicyNet with the same weights."""
    pol = model.policy
    hidden = tuple(m.out_features for m in pol.mlp_extractor.policy_net if isinstance(m, nn.Linear))
    actor = ExternalPolicyNet.for_config(config, hidden, trainer="sb3")
    src = [m for m in pol.mlp_extractor.policy_net if isinstance(m, nn.Linear)] + [pol.action_net]
    dst = [m for m in actor.mlp if isinstance(m, nn.Linear)]
    with torch.no_grad():
        for a, b in zip(src, dst, strict=True):
            b.weight.copy_(a.weight)
            b.bias.copy_(a.bias)
    return actor.eval()


def native_vec_env(env_id: str, n_envs: int, seed: int, **kw):
    """uavsearch's vector env as an SB3 VecEnv (module docstring)."""
    from gymnasium.wrappers.vector import FlattenObservation as FlattenVector
    from stable_baselines3.common.vec_env import VecEnv, VecMonitor

    class NativeVecEnv(VecEnv):
        def __init__(self):
            self.venv = FlattenVector(gym.make_vec(env_id, num_envs=n_envs, vectorization_mode="vector_entry_point",
                                                   **kw))
            super().__init__(n_envs, self.venv.single_observation_space, self.venv.single_action_space)
            self._actions = None

        def reset(self):
            seeds = self._seeds if any(s is not None for s in self._seeds) else None
            obs, _ = self.venv.reset(seed=seeds)
            self._reset_seeds()
            return obs

        def step_async(self, actions):
            self._actions = actions

        def step_wait(self):
            obs, rew, term, trunc, info = self.venv.step(self._actions)
            done = term | trunc
            infos = [{"f1": float(info["f1"][i])} for i in range(self.num_envs)]
            if done.any():
                for i in np.flatnonzero(done):
                    infos[i]["terminal_observation"] = obs[i].copy()
                    infos[i]["TimeLimit.truncated"] = bool(trunc[i] and not term[i])
                fresh, _ = self.venv.reset(options={"reset_mask": done})
                obs = np.where(done[:, None], fresh, obs)
            return obs, rew.astype(np.float32), done, infos

        def close(self):
            self.venv.close()

        def get_attr(self, attr_name, indices=None):
            return [getattr(self.venv.unwrapped, attr_name)] * len(self._get_indices(indices))

        def set_attr(self, attr_name, value, indices=None):
            raise NotImplementedError("the vector env's episodes share their attributes")

        def env_method(self, method_name, *method_args, indices=None, **method_kwargs):
            raise NotImplementedError("the vector env's episodes have no methods of their own")

        def env_is_wrapped(self, wrapper_class, indices=None):
            return [False] * len(self._get_indices(indices))

    venv = NativeVecEnv()
    venv.seed(seed)
    return VecMonitor(venv), venv.venv.unwrapped


COMPARED_WITH = ("what it is compared with: the final F1 above is on the training scenes; `uavsearch eval search "
                 "--setting {setting}` (the checkpoint in models/, --ship) scores it on the test scenes as Table II's "
                 "'PPO (external)' row, paired against the coverage route (docs/learning.md: setting 2's coverage route "
                 "0.716 test AF1)")


def progress_callback(total: int):
    """SB3's own progress_bar needs rich besides tqdm; this one needs tqdm only: env steps, and the mean final F1
    of the episodes that ended in the last rollout."""
    from stable_baselines3.common.callbacks import BaseCallback
    from tqdm import tqdm

    class TqdmCallback(BaseCallback):
        def _on_training_start(self):
            self.bar, self.f1 = tqdm(total=total, desc="PPO", unit="step"), []

        def _on_step(self):
            self.bar.update(self.training_env.num_envs)
            self.f1 += [i["f1"] for i, d in zip(self.locals["infos"], self.locals["dones"]) if d]
            return True

        def _on_rollout_end(self):
            if self.f1:
                self.bar.set_postfix_str(f"final F1 on training scenes {np.mean(self.f1):.3f}")
            self.f1 = []

        def _on_training_end(self):
            self.bar.close()

    return TqdmCallback()


def train(args: Args) -> dict:
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env

    torch.set_num_threads(args.threads)
    seed_everything(args.seed)
    run_dir = Path(args.runs_dir) / f"sb3_ppo_s{args.setting}__{args.seed}__{int(time.time())}"
    run_dir.mkdir(parents=True)
    (run_dir / "args.json").write_text(json.dumps(asdict(args), indent=1))
    kw = {"obs": "cells", "reward": args.reward, "setting": int(args.setting), **({"limit": args.limit} if args.limit else {})}
    if args.single:
        venv = make_vec_env(lambda: FlattenObservation(gym.make(args.env_id, **kw)), n_envs=args.n_envs, seed=args.seed)
        env = venv.envs[0].unwrapped
    else:
        venv, env = native_vec_env(args.env_id, args.n_envs, args.seed, **kw)
    hidden = [int(h) for h in args.hidden.split(",")]
    model = PPO("MlpPolicy", venv, n_steps=args.n_steps, batch_size=args.batch_size, n_epochs=args.n_epochs,
                learning_rate=args.learning_rate, gamma=args.gamma, ent_coef=args.ent_coef, seed=args.seed, verbose=0,
                policy_kwargs={"net_arch": {"pi": hidden, "vf": hidden}, "activation_fn": nn.Tanh}, device="cpu")
    t0 = time.perf_counter()
    model.learn(total_timesteps=args.total_timesteps, callback=progress_callback(args.total_timesteps))
    wall = time.perf_counter() - t0
    model.save(run_dir / "ppo.zip")
    actor = export_actor(model, env.config)
    name = checkpoint_path(env.setting, env.fusion.name, run_dir, policy="external").name
    ckpt = save_search_model(run_dir / name, env.fusion, actor, {
        "search_config": config_to_dict(env.config), "perception_tag": env.scenes.cache.perception_tag,
        "trainer": "examples/sb3_ppo.py", "args": asdict(args), "steps": int(model.num_timesteps), "wall_s": wall})
    print(f"wrote {ckpt} ({model.num_timesteps} steps, {wall:.0f} s of training)")
    print(COMPARED_WITH.format(setting=args.setting))
    if args.ship:
        shutil.copyfile(ckpt, MODELS_DIR / name)
        print(f"copied to {MODELS_DIR / name}")
    venv.close()
    return {"checkpoint": ckpt, "run_dir": run_dir, "wall_s": wall, "steps": int(model.num_timesteps)}


def parse_args(argv=None) -> Args:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    return dataclass_from_args(Args, add_dataclass_args(p, Args).parse_args(argv))


if __name__ == "__main__":
    import sys

    try:
        import stable_baselines3  # noqa: F401
    except ModuleNotFoundError:
        sys.exit("examples/sb3_ppo.py needs Stable-Baselines3: pip install -e '.[sb3]'")
    train(parse_args())
