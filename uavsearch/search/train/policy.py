"""Stage 2 (paper Sec. V-B): the confidence net by backprop through learned fusion, the policy by REINFORCE.

CleanRL-style: `Args`, then `train(args)` does everything. Perception (backbone + classifier) is frozen:
its per-view outputs for every (scene, lattice position) come from the view cache (view_cache.py), so
a batch of episodes is a few tensor gathers and nothing is rendered.

Per iteration: `scenes_per_batch` training scenes x `episodes_per_scene` episodes of T views each
(search_loop.run_search), then
- confidence net (learned fusion only), Eq. 11: the softmax (binary NLL) loss of the final fused map
  M-bar^T against the ground truth, backpropagated through the fusion's softmax over views;
- policy + state + embedding, Eq. 12: REINFORCE, sum_t log p(a^t | s^t) (R^t - b^t), where R^t is the
  return from step t: the revisit penalties still to come (Eq. 15, R_re per revisit) plus the
  classification reward at T (Eq. 14, N_tp R_tp + N_fp R_fp of the final map). Baseline b^t
  (`baseline`): "loo" = the mean return of the other episodes of the SAME scene in the batch (the
  scene decides most of the reward, so this removes most of the variance), or "ema" = a moving average
  per step. Advantages are normalised over the batch; an entropy bonus keeps early exploration.

For the "+ policy" baselines, `fusion` is the fusion the policy sees (M-bar^t in its state) and is
rewarded with; only learned fusion has a confidence net to train. (For oracle fusion M-bar^t uses the
ground truth, as the oracle does: that row is a bound, not a method.)

Output: runs/<name>__<seed>__<unix time>/ with args.json (first), metrics.csv (losses/, charts/, eval/),
learning_curve.png and model.pt, the checkpoint with the best validation AF1 (validation scenes of the
same setting, never the test scenes). Only `--out PATH` or `--ship` (models/search_s<K>_<fusion>.pt,
the shipped model Table II and the default mission use) copies it elsewhere.
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import NamedTuple

import torch
from tqdm import tqdm

from uavsearch.cli_args import add_dataclass_args, dataclass_from_args, opt
from uavsearch.devices import resolve_device, to_device
from uavsearch.errors import UavsearchError, run_command
from uavsearch.viz import pyplot

from ..agents import check_names, new_agent
from ..checkpoints import checkpoint_path, shipped_perception
from ..config import config_to_dict
from ..fusion import BY_NAME, Fusion
from ..metrics import map_f1
from ..policy import save_search_model
from ..scoring import evaluate_agent
from ..search_loop import R_FP, R_RE, R_TP, Agent, CachedViews, classification_reward, run_search
from .runs import RunArgs, copy_checkpoint, load_caches, returns_to_go, start_run, start_training


@dataclass
class Args(RunArgs):
    setting: int = opt(2, "paper setting 1 | 2 | 3 (2, 5, 10 occupied cells)")
    fusion: str = opt("learned", "fusion the policy is trained with and rewarded through",
                      choices=BY_NAME)
    # scene split: train on its train part, select on its val part. "large" (500 + 50 scenes per setting)
    # for the shipped models: on the paper's 20 training scenes the confidence net and policy overfit
    # within 50-150 iterations (train AF1 0.7, validation falling).
    split: str = opt("large", "scene split: trains on its train part, selects on its val part")
    perception: str = opt(str(shipped_perception()), "frozen stage-1 checkpoint")
    out: str | None = opt(None, "also copy the best checkpoint here (it always stays in the run directory)")
    ship: bool = opt(False, "copy the best checkpoint over the shipped models/search_s<setting>_<fusion>.pt")
    name: str | None = opt(None, "run name (default policy_s<setting>_<fusion>)")
    seed: int = opt(0, "seeds random, numpy, torch and the episode sampling")
    iterations: int = opt(1200, "optimiser steps (large split: validation AF1 still rises slowly at 1000)")
    scenes_per_batch: int = opt(16, "training scenes per batch (drawn with replacement)")
    episodes_per_scene: int = opt(8, "episodes per scene per batch (>= 2 for the \"loo\" baseline)")
    lr_policy: float = opt(1e-3, "Adam, policy + state + embedding")
    lr_confidence: float = opt(1e-3, "Adam, confidence net")
    weight_decay: float = opt(1e-6, "Adam L2 (the paper's alpha)")
    r_tp: float = opt(R_TP, "R_tp, reward per true positive cell at T (Eq. 14)")
    r_fp: float = opt(R_FP, "R_fp, reward per false positive cell at T (Eq. 14)")
    r_re: float = opt(R_RE, "R_re, reward per revisit (Eq. 15)")
    baseline: str = opt("loo", "loo (other episodes of the same scene) | ema (moving average per step)")
    ema_decay: float = opt(0.95, "decay of the \"ema\" baseline")
    entropy_coef: float = opt(0.01, "entropy bonus weight")
    conf_pos_weight: float = opt(3.0, "weight of occupied cells in the confidence loss (F1 needs the few positives)")
    conf_episodes: int = opt(32, "episodes of each batch the confidence loss is taken over (dropout is costly)")
    state_extras: bool = opt(True, "position / visited / step in the policy state (see policy.py)")
    eval_every: int = opt(25, "iterations between validations")
    eval_episodes: int = opt(8, "episodes per validation scene")


class TrainResult(NamedTuple):
    run_dir: Path
    checkpoint: Path
    best: dict  # validation metrics of the saved checkpoint
    seconds: float
    steps_per_s: float  # policy steps (episodes x moves) per second of training
    cpu_steps_per_s: float = 0.0  # the same per second of this process's CPU time (steadier on a shared machine)


def check_args(args: Args) -> None:
    check_names(fusion=args.fusion)
    if args.baseline not in ("loo", "ema"):
        raise UavsearchError(f"unknown baseline {args.baseline!r}; choose loo or ema")
    if args.baseline == "loo" and args.episodes_per_scene < 2:
        raise UavsearchError("the loo baseline needs --episodes-per-scene >= 2")
    if min(args.iterations, args.scenes_per_batch, args.episodes_per_scene, args.eval_every, args.eval_episodes) < 1:
        raise UavsearchError("iterations, batch sizes, eval_every and eval_episodes must be positive")


def returns(ep, args: Args) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, T-1) return from each move (Eq. 13-15, undiscounted) and the (B,) classification reward."""
    maps = ep.maps.detach()
    r_cls = classification_reward(maps[:, -1], ep.labels, args.r_tp, args.r_fp).float()
    return returns_to_go(maps, ep.labels, ep.revisit, r_tp=args.r_tp, r_fp=args.r_fp, r_re=args.r_re), r_cls


def confidence_loss(fusion: Fusion, cache, rows, lattice_idx, pos_weight: float) -> torch.Tensor:
    """Eq. 11: binary NLL of the trainable fusion's map at T, re-fused in train mode (dropout).

    The views come as one batch with each distinct (scene, position)'s cell features once (episodes of one
    scene share the start view and often more): learned fusion runs its net's first (largest) layer once per
    row and dropout and the rest per episode and view, so every term draws its own dropout masks.
    """
    fused = fusion.fuse(CachedViews(cache, rows).fusion_views(lattice_idx)).clamp(1e-6, 1 - 1e-6)
    y = cache.occupancy[rows]
    w = torch.where(y, torch.full_like(fused, pos_weight), torch.ones_like(fused))
    return -(w * torch.where(y, fused.log(), (1 - fused).log())).sum() / w.sum()


def _plot(rows: list[dict], path: Path, title: str) -> None:
    plt = pyplot()
    it = [r["iteration"] for r in rows]
    ev = [r for r in rows if r.get("eval/af1") is not None]
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.6))
    ax[0].plot(it, [r["charts/return"] for r in rows], lw=0.8)
    ax[0].set_title("training return (R_cls + revisits)")
    ax[1].plot(it, [r["charts/train_af1"] for r in rows], lw=0.8, label="train AF1 (batch)")
    ax[1].plot([r["iteration"] for r in ev], [r["eval/af1"] for r in ev], "o-", label="validation AF1")
    ax[1].set_title("AF1 at T")
    ax[1].legend(fontsize=8)
    ax[2].plot(it, [r["charts/revisit_rate"] for r in rows], lw=0.8, label="revisit rate")
    ax[2].plot(it, [r["charts/entropy"] for r in rows], lw=0.8, label="policy entropy (nats)")
    ax[2].legend(fontsize=8)
    for a in ax:
        a.set_xlabel("iteration")
        a.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def train(args: Args, caches=None) -> TrainResult:
    """Train one policy (and, for learned fusion, its confidence net); `caches` = (train, val) ViewCaches
    to skip loading perception (tests)."""
    check_args(args)
    t_start = time.perf_counter()
    device = resolve_device(args.device)
    gen = start_training(args.threads, args.seed, device)
    name = args.name or f"policy_s{args.setting}_{args.fusion}"
    run_dir = start_run(args, name, args.seed)

    train_cache, val_cache = (to_device(c, device) for c in (caches if caches is not None else load_caches(args)))
    config = train_cache.config
    agent = new_agent(args.fusion, config, int(train_cache.global_feature.shape[-1]),
                      int(train_cache.cell_features.shape[-1]), args.state_extras)  # evaluation
    policy, fusion = agent.policy.to(device), agent.fusion
    if isinstance(fusion, torch.nn.Module):
        fusion.to(device)
    groups = [{"params": policy.parameters(), "lr": args.lr_policy}]
    if fusion.trainable:
        groups.append({"params": fusion.parameters(), "lr": args.lr_confidence})
    opt = torch.optim.Adam(groups, weight_decay=args.weight_decay)
    rollout_agent = Agent(fusion.frozen(), policy)
    T, S = config.budget_T, train_cache.num_scenes
    ema = torch.zeros(T - 1, device=device)
    rows: list[dict] = []
    best, best_key = {}, (-1.0, -1.0)
    ckpt = run_dir / "model.pt"
    csv_f = (run_dir / "metrics.csv").open("w", newline="")
    writer = None
    steps, roll_s, roll_cpu = 0, 0.0, 0.0
    bar = tqdm(range(1, args.iterations + 1), desc=name, disable=not args.progress, unit="it")
    for it in bar:
        policy.train()
        if fusion.trainable:
            fusion.train()
        t0, c0 = time.perf_counter(), time.process_time()
        scenes = torch.randint(S, (args.scenes_per_batch,), generator=gen, device=device)
        rows_b = scenes.repeat_interleave(args.episodes_per_scene)
        ep = run_search(CachedViews(train_cache, rows_b, config, rollout_agent.fusion.scorer), rollout_agent,
                        generator=gen)
        y = ep.labels
        final = ep.maps[:, -1]
        R, r_cls = returns(ep, args)
        if args.baseline == "loo":
            g = R.view(args.scenes_per_batch, args.episodes_per_scene, -1)
            b = (g.sum(1, keepdim=True) - g) / (args.episodes_per_scene - 1)
            adv = (g - b).reshape_as(R)
        else:
            adv = R - ema
            ema = args.ema_decay * ema + (1 - args.ema_decay) * R.mean(0)
        adv = (adv - adv.mean()) / (adv.std() + 1e-8)
        loss_pg = -(ep.log_prob * adv).mean()
        loss_ent = -ep.entropy.mean()
        loss = loss_pg + args.entropy_coef * loss_ent
        loss_conf = torch.zeros((), device=device)
        if fusion.trainable:
            n = min(args.conf_episodes, len(rows_b))
            loss_conf = confidence_loss(fusion, train_cache, rows_b[:n], ep.lattice_idx[:n], args.conf_pos_weight)
            loss = loss + loss_conf
        opt.zero_grad()
        loss.backward()
        opt.step()
        roll_s += time.perf_counter() - t0
        roll_cpu += time.process_time() - c0
        steps += ep.actions.numel()
        f1 = map_f1(final.detach().cpu().numpy(), y.cpu().numpy())
        row = {"iteration": it, "losses/policy": float(loss_pg.detach()), "losses/entropy": float(-loss_ent.detach()),
               "losses/confidence": float(loss_conf.detach()), "charts/return": float(R[:, 0].mean()),
               "charts/r_cls": float(r_cls.mean()), "charts/train_af1": float(f1.mean()),
               "charts/revisit_rate": float(ep.revisit[:, 1:].float().mean()), "charts/entropy": float(-loss_ent.detach()),
               "charts/steps_per_s": steps / roll_s, "eval/aacc": None, "eval/af1": None}
        if it % args.eval_every == 0 or it == args.iterations:
            sc = evaluate_agent(val_cache, agent, args.eval_episodes, seed=10_000 + args.seed, config=config)
            row["eval/aacc"], row["eval/af1"] = float(sc.acc[:, -1].mean()), float(sc.f1[:, -1].mean())
            key = (row["eval/af1"], row["eval/aacc"])
            if key > best_key:
                best_key = key
                best = {"iteration": it, "val_aacc": row["eval/aacc"], "val_af1": row["eval/af1"],
                        "val_revisit": sc.revisit_rate}
                save_search_model(ckpt, fusion, policy,
                                  {"args": asdict(args), "best": best, "perception_tag": train_cache.perception_tag,
                                   "search_config": config_to_dict(config)})
            bar.set_postfix(val_af1=f"{row['eval/af1']:.3f}", best=f"{best_key[0]:.3f}")
        rows.append(row)
        if writer is None:
            writer = csv.DictWriter(csv_f, fieldnames=list(row))
            writer.writeheader()
        writer.writerow(row)
    csv_f.close()
    bar.close()
    if args.plot:
        _plot(rows, run_dir / "learning_curve.png", f"{name}, seed {args.seed}")
    out = copy_checkpoint(ckpt, args.out, args.ship, checkpoint_path(args.setting, args.fusion))
    seconds = time.perf_counter() - t_start
    summary = {"best": best, "seconds": seconds, "train_steps_per_s": steps / max(roll_s, 1e-9),
               "train_steps_per_cpu_s": steps / max(roll_cpu, 1e-9),
               "checkpoint": str(out or ckpt)}
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=1))
    return TrainResult(run_dir, out or ckpt, best, seconds, steps / max(roll_s, 1e-9), steps / max(roll_cpu, 1e-9))


# --------------------------------------------------------------------------------------------------
# CLI


def add_train_policy_parser(subparsers) -> None:
    """`uavsearch train policy ...` (subparsers: the `train` command's); one flag per Args field."""
    p = subparsers.add_parser("policy", help="stage 2: confidence fusion + REINFORCE view-selection policy",
                              description="Stage 2 (paper Sec. V-B) on cached teleport views; see "
                                          "uavsearch/search/train/policy.py.")
    add_dataclass_args(p, Args)
    p.set_defaults(func=cmd_train_policy)


def cmd_train_policy(args) -> int:
    res = train(dataclass_from_args(Args, args))
    print(f"best validation: {json.dumps(res.best)}")
    print(f"{res.seconds:.0f} s, {res.steps_per_s:.0f} policy steps/s in training; run {res.run_dir}; "
          f"checkpoint {res.checkpoint}")
    return 0


if __name__ == "__main__":  # python -m uavsearch.search.train.policy [flags] = uavsearch train policy [flags]
    raise SystemExit(run_command(cmd_train_policy, add_dataclass_args(argparse.ArgumentParser(
        prog="python -m uavsearch.search.train.policy"), Args).parse_args()))
