"""PPO in one file (CleanRL style) on uavsearch's native vector env: cached "cells" observations, many episodes a step.

    python examples/cleanrl_ppo.py --setting 2 --total-timesteps 300000            # a few CPU-minutes
    python examples/cleanrl_ppo.py --setting 2 --ship                                # and copy it to models/
    uavsearch eval search --setting 2 --out results/eval_ppo                         # Table II's "PPO (external)" row

The actor is uavsearch's `ExternalPolicyNet` (an MLP on the flattened observation); the run writes
``runs/<name>__<seed>__<time>/`` (args.json first, metrics.csv with losses/ and charts/ columns) and the checkpoint
``search_s<K>_<fusion>_external.pt`` there; ``--ship`` copies it to models/, where the evaluation looks.
"""

from __future__ import annotations

import argparse
import csv
import json
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from gymnasium.wrappers.vector import FlattenObservation
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
    env_id: str = opt("uavsearch/ActiveSearch-v0", "the gymnasium id (uavsearch/WideSearch-v0: the wide family)")
    setting: str = opt("2", "paper setting 1 | 2 | 3, or a scene family (wide) for WideSearch-v0")
    fusion: str = opt("", "the env's fusion (default: learned for 1-3, bayes for the families)")
    reward: str = opt("shaped", "the env's reward: shaped (per step) or terminal (the same sum)")
    limit: int = opt(0, "train on the part's first scenes only (0: all)")
    seed: int = opt(1, "seeds random, numpy, torch and the envs")
    total_timesteps: int = opt(300_000, "env steps in all (over every env)")
    num_envs: int = opt(64, "episodes stepped together")
    num_steps: int = opt(32, "steps per env per rollout")
    learning_rate: float = opt(2.5e-4, "Adam's, annealed linearly to 0")
    gamma: float = opt(1.0, "discount (episodes are a handful of steps)")
    gae_lambda: float = opt(0.95, "GAE's lambda")
    num_minibatches: int = opt(4, "minibatches per epoch")
    update_epochs: int = opt(4, "epochs per rollout")
    clip_coef: float = opt(0.2, "the surrogate's clip")
    ent_coef: float = opt(0.01, "entropy bonus")
    vf_coef: float = opt(0.5, "value loss weight")
    max_grad_norm: float = opt(0.5, "gradient clip")
    hidden: str = opt("64,64", "the actor's (and critic's) hidden layers")
    threads: int = opt(1, "torch CPU threads")
    runs_dir: str = opt(str(RUNS_DIR), "parent of the run directory")
    ship: bool = opt(False, "copy the checkpoint to models/ (what `uavsearch eval search` reads)")


def critic(obs_dim: int, hidden: tuple[int, ...]) -> nn.Module:
    layers, prev = [], obs_dim
    for h in hidden:
        layers += [nn.Linear(prev, h), nn.Tanh()]
        prev = h
    return nn.Sequential(*layers, nn.Linear(prev, 1))


def make_envs(args: Args):
    kw = {"obs": "cells", "reward": args.reward, "setting": args.setting if not args.setting.isdigit() else int(args.setting)}
    if args.fusion:
        kw["fusion"] = args.fusion
    if args.limit:
        kw["limit"] = args.limit
    envs = gym.make_vec(args.env_id, num_envs=args.num_envs, vectorization_mode="vector_entry_point", **kw)
    return envs, FlattenObservation(envs)


def train(args: Args) -> dict:
    torch.set_num_threads(args.threads)
    seed_everything(args.seed)
    run_dir = Path(args.runs_dir) / f"cleanrl_ppo_s{args.setting}__{args.seed}__{int(time.time())}"
    run_dir.mkdir(parents=True)
    (run_dir / "args.json").write_text(json.dumps(asdict(args), indent=1))
    raw, envs = make_envs(args)
    base = raw.unwrapped
    hidden = tuple(int(h) for h in args.hidden.split(","))
    actor = ExternalPolicyNet.for_config(base.config, hidden, trainer="cleanrl")
    value = critic(actor.cfg.obs_dim, hidden)
    params = list(actor.parameters()) + list(value.parameters())
    opt = torch.optim.Adam(params, lr=args.learning_rate, eps=1e-5)
    N, S, D = args.num_envs, args.num_steps, actor.cfg.obs_dim
    batch = N * S
    mb = batch // args.num_minibatches
    updates = max(1, args.total_timesteps // batch)
    obs_b = torch.zeros(S, N, D)
    act_b = torch.zeros(S, N, dtype=torch.long)
    logp_b, rew_b, done_b, val_b, valid_b = (torch.zeros(S, N) for _ in range(5))
    next_obs, _ = envs.reset(seed=args.seed)
    next_obs = torch.as_tensor(next_obs, dtype=torch.float32)
    next_done = torch.zeros(N)
    resetting = torch.zeros(N, dtype=torch.bool)  # next-step autoreset: this step only resets the env
    log = open(run_dir / "metrics.csv", "w", newline="")
    writer = csv.writer(log)
    writer.writerow(["global_step", "charts/episodic_return", "charts/final_f1", "charts/sps", "losses/policy",
                     "losses/value", "losses/entropy", "losses/approx_kl"])
    t0, step = time.perf_counter(), 0
    ret = torch.zeros(N)
    for update in range(updates):
        for g in opt.param_groups:
            g["lr"] = args.learning_rate * (1.0 - update / updates)
        episodic, finals = [], []
        for s in range(S):
            obs_b[s], done_b[s], valid_b[s] = next_obs, next_done, (~resetting).float()
            with torch.no_grad():
                logits = actor(next_obs)
                dist = torch.distributions.Categorical(logits=logits)
                a = dist.sample()
                logp_b[s], val_b[s] = dist.log_prob(a), value(next_obs).squeeze(-1)
            act_b[s] = a
            o, r, term, trunc, info = envs.step(a.numpy())
            step += N
            rew_b[s] = torch.as_tensor(r, dtype=torch.float32)
            ended = torch.as_tensor(term | trunc)
            ret = ret + rew_b[s]
            if ended.any():
                episodic += ret[ended].tolist()
                finals += np.asarray(info["f1"])[ended.numpy()].tolist()
                ret[ended] = 0.0
            next_obs, next_done, resetting = torch.as_tensor(o, dtype=torch.float32), ended.float(), ended
        with torch.no_grad():  # GAE; a done step never bootstraps, and a reset step is masked out of the loss
            next_value = value(next_obs).squeeze(-1)
            adv = torch.zeros(S, N)
            last = torch.zeros(N)
            for s in reversed(range(S)):
                nv, nd = (next_value, next_done) if s == S - 1 else (val_b[s + 1], done_b[s + 1])
                delta = rew_b[s] + args.gamma * nv * (1.0 - nd) - val_b[s]
                last = delta + args.gamma * args.gae_lambda * (1.0 - nd) * last
                adv[s] = last
            ret_b = adv + val_b
        flat = lambda x: x.reshape(batch, *x.shape[2:])  # noqa: E731
        b_obs, b_act, b_logp, b_adv, b_ret, b_valid = map(flat, (obs_b, act_b, logp_b, adv, ret_b, valid_b))
        keep = b_valid.nonzero().squeeze(-1)
        for _ in range(args.update_epochs):
            perm = keep[torch.randperm(len(keep))]
            for i in range(0, len(perm), mb):
                j = perm[i:i + mb]
                dist = torch.distributions.Categorical(logits=actor(b_obs[j]))
                logp = dist.log_prob(b_act[j])
                ratio = (logp - b_logp[j]).exp()
                a_ = b_adv[j]
                a_ = (a_ - a_.mean()) / (a_.std() + 1e-8)
                pg = torch.max(-a_ * ratio, -a_ * ratio.clamp(1 - args.clip_coef, 1 + args.clip_coef)).mean()
                v_loss = 0.5 * ((value(b_obs[j]).squeeze(-1) - b_ret[j]) ** 2).mean()
                ent = dist.entropy().mean()
                loss = pg - args.ent_coef * ent + args.vf_coef * v_loss
                opt.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(params, args.max_grad_norm)
                opt.step()
                approx_kl = float(((ratio - 1) - (logp - b_logp[j])).mean().detach())
        sps = step / (time.perf_counter() - t0)
        writer.writerow([step, np.mean(episodic) if episodic else "", np.mean(finals) if finals else "", round(sps),
                         float(pg.detach()), float(v_loss.detach()), float(ent.detach()), approx_kl])
        if update % 10 == 0 or update == updates - 1:
            print(f"step {step:>8}  return {np.mean(episodic) if episodic else float('nan'):6.2f}  final F1 on training scenes "
                  f"{np.mean(finals) if finals else float('nan'):.3f}  {sps:,.0f} steps/s", flush=True)
    log.close()
    envs.close()
    fusion = base.fusion
    setting = base.setting
    name = checkpoint_path(setting, fusion.name, run_dir, policy="external").name if str(setting).isdigit() else \
        f"search_{setting}_{fusion.name}_external.pt"
    ckpt = save_search_model(run_dir / name, fusion, actor, {
        "search_config": config_to_dict(base.config), "perception_tag": base.scenes.cache.perception_tag,
        "trainer": "examples/cleanrl_ppo.py", "args": asdict(args), "steps": step,
        "wall_s": time.perf_counter() - t0})
    print(f"wrote {ckpt} ({step} steps, {time.perf_counter() - t0:.0f} s)")
    if str(setting).isdigit():
        print("what it is compared with: the final F1 above is on the training scenes; `uavsearch eval search "
              f"--setting {setting}` (the checkpoint in models/, --ship) scores it on the test scenes as Table II's "
              "'PPO (external)' row, paired against the coverage route (docs/learning.md: setting 2's coverage route "
              "0.716 test AF1)")
    else:
        print("what it is compared with: the final F1 above is on the training scenes; examples/wide_ppo.py scores "
              "such an actor on validation scenes against Table III's rule and best fixed route")
    if args.ship:
        shutil.copyfile(ckpt, MODELS_DIR / name)
        print(f"copied to {MODELS_DIR / name}")
    return {"checkpoint": ckpt, "run_dir": run_dir, "steps": step}


def parse_args(argv=None) -> Args:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    return dataclass_from_args(Args, add_dataclass_args(p, Args).parse_args(argv))


if __name__ == "__main__":
    train(parse_args())
