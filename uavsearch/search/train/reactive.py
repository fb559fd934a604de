"""The reactive view-selection policy (reactive.ReactivePolicyNet): DAgger from a label-peeking teacher, then REINFORCE.

CleanRL-style: `Args`, then `train(args)` does everything (the loop is train/dagger.py's, shared with the map
policy). Perception and the confidence net are FROZEN: the confidence net is the paper method's (learned fusion's,
from `--confidence`), its scores of every (scene, position) are computed once, and every episode is a few gathers
(search_loop.run_search on CachedViews).

1. DAgger (`dagger_iterations`): roll out a mixture, per episode and step the teacher
   (reactive.LabelGreedyTeacher, one-step lookahead on the labels) with probability beta (1, then times
   `beta_decay` per iteration) else the net (sampled); keep every (state, teacher move); fit the net to the
   aggregate by cross-entropy (`dagger_epochs` passes per iteration), each minibatch mirrored east-west and
   / or north-south at random (`mirror`; reactive.mirror_states): 500 scenes are then 2000.
2. REINFORCE (`pg_iterations`) with a PER-STEP reward: after each new view, the change of N_tp - N_fp of the
   learned-fusion map (plus R_re per revisit). The return to go of each move is baselined by the COVERAGE
   ROUTE's return to go on the same scene from the same step (policy.CoverageRoute, computed once per
   scene): the advantage says "better than flying the lawnmower from here". Advantages are normalised over
   the batch; an entropy bonus decays linearly from `entropy_start` to `entropy_end`; an imitation term
   (`imitation_coef`, cross-entropy on a minibatch of the DAgger aggregate) keeps the teacher's lessons.
3. Selection: after DAgger and every `eval_every` iterations, the net's argmax moves on the validation
   scenes; the checkpoint kept is the one with the best (AF1 - coverage route's AF1), then Aacc.

Output: runs/<name>__<seed>__<unix time>/ with args.json (first), metrics.csv (losses/, charts/, eval/),
learning_curve.png, model.pt (the best checkpoint: the net and the frozen confidence net, so it is
self-contained) and summary.json. `--out PATH` or `--ship` (models/search_s<K>_learned_reactive.pt) copies it.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import NamedTuple

import torch
from torch.nn import functional as F

from uavsearch.cli_args import add_dataclass_args, dataclass_from_args, opt
from uavsearch.devices import resolve_device, to_device
from uavsearch.errors import UavsearchError, run_command
from uavsearch.viz import pyplot

from ..checkpoints import checkpoint_path, shipped_perception
from ..config import SearchConfig, config_to_dict
from ..fusion import LearnedFusion
from ..policy import ArgmaxPolicy, CoverageRoute, load_search_model, save_search_model
from ..reactive import LabelGreedyTeacher, ReactiveConfig, ReactivePolicyNet, mirror_states, score_table
from ..scoring import evaluate_agent
from ..search_loop import R_RE, Agent, CachedViews, classification_reward, run_search
from .dagger import DaggerPolicy, ReinforceLoss, check_dagger_args, dagger_reinforce
from .runs import (MetricsCsv, RunArgs, copy_checkpoint, finish_curves, imitation_panel, load_caches, returns_to_go,
                   start_run, start_training)

FUSION = "learned"


@dataclass
class Args(RunArgs):
    setting: int = opt(2, "paper setting 1 | 2 | 3 (2, 5, 10 occupied cells)")
    split: str = opt("large", "scene split: trains on its train part, selects on its val part")
    perception: str = opt(str(shipped_perception()), "frozen stage-1 checkpoint (builds the view caches)")
    confidence: str | None = opt(None, "learned-fusion checkpoint whose frozen confidence net fuses the views "
                                       "(default models/search_s<setting>_learned.pt)")
    out: str | None = opt(None, "also copy the best checkpoint here (it always stays in the run directory)")
    ship: bool = opt(False, "copy the best checkpoint over the shipped models/search_s<setting>_learned_reactive.pt")
    name: str | None = opt(None, "run name (default reactive_s<setting>)")
    seed: int = opt(0, "seeds random, numpy, torch and the episode sampling")
    # 1. DAgger
    dagger_iterations: int = opt(8, "DAgger iterations (rollout, aggregate, fit)")
    dagger_episodes: int = opt(1000, "episodes rolled out per DAgger iteration (scenes drawn with replacement)")
    beta_decay: float = opt(0.5, "teacher probability: 1 in the first iteration, times this per iteration")
    dagger_epochs: int = opt(3, "passes over the aggregate per DAgger iteration")
    batch_size: int = opt(256, "states per cross-entropy minibatch")
    lr: float = opt(1e-3, "Adam, imitation")
    mirror: bool = opt(True, "imitate on randomly mirrored states too (east-west, north-south, moves swapped alike)")
    # 2. REINFORCE
    pg_iterations: int = opt(1500, "policy-gradient iterations after DAgger")
    scenes_per_batch: int = opt(32, "training scenes per policy-gradient batch (drawn with replacement)")
    episodes_per_scene: int = opt(4, "episodes per scene per policy-gradient batch")
    lr_pg: float = opt(1e-3, "Adam, policy gradient")
    weight_decay: float = opt(1e-5, "Adam L2")
    r_re: float = opt(R_RE, "reward per revisit (the per-step reward also counts the change of N_tp - N_fp)")
    entropy_start: float = opt(0.02, "entropy bonus at the first policy-gradient iteration")
    entropy_end: float = opt(0.0, "entropy bonus at the last (linear in between)")
    imitation_coef: float = opt(0.0, "weight of the cross-entropy on the DAgger aggregate during REINFORCE")
    # architecture (reactive.ReactiveConfig)
    channels: int = opt(32, "conv channels")
    conv_layers: int = opt(3, "3x3 conv layers")
    hidden: int = opt(64, "FC head width")
    eval_every: int = opt(25, "policy-gradient iterations between validations")


class TrainResult(NamedTuple):
    run_dir: Path
    checkpoint: Path
    best: dict  # validation metrics of the saved checkpoint
    table: list[dict]  # validation rows: coverage route, reactive policy, label-greedy teacher
    seconds: float


def check_args(args: Args) -> None:
    check_dagger_args(args, "episodes_per_scene", "channels", "conv_layers", "hidden")


class ScoreLookup(torch.nn.Module):
    """The confidence net of a `scored` cache: its cell features ARE the frozen net's scores."""

    def forward(self, x):
        return x[..., 0]


def scored(cache, scores):
    """The view cache with each cell feature replaced by its (precomputed, frozen) confidence score."""
    return cache._replace(cell_features=scores[..., None])


def imitation_loss(net, states, masks, targets, mirror: torch.Generator | None = None,
                   config: SearchConfig | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Cross-entropy of the net's masked logits against the teacher's moves, and the agreement (argmax);
    with `mirror` (a generator) the batch is first mirrored east-west and / or north-south at random."""
    if mirror is not None:
        ew, ns = (torch.rand(2, generator=mirror, device=mirror.device) < 0.5).tolist()
        states, masks, targets = mirror_states(states, masks, targets, config or net.cfg.search_config(), ew, ns)
    logits = net(states, masks)
    return F.cross_entropy(logits, targets), (logits.argmax(-1) == targets).float().mean()


def step_returns(maps, labels, revisit, r_re: float) -> torch.Tensor:
    """(B, T-1) return to go of each move: the change of N_tp - N_fp from the map after view t to the last
    map, plus r_re per revisit still to come (the shaped step_rewards of the views after view 0)."""
    return returns_to_go(maps, labels, revisit, r_re=r_re, shaped=True)


def _validate(val, agent: Agent, config) -> dict:
    sc = evaluate_agent(val, agent, 1, seed=0, config=config)
    return {"af1": float(sc.f1[:, -1].mean()), "aacc": float(sc.acc[:, -1].mean()), "revisit": sc.revisit_rate}


def _plot(rows: list[dict], path: Path, title: str) -> None:
    plt = pyplot()
    ev = [r for r in rows if r["eval/af1_vs_coverage"] is not None]
    pg = [r for r in rows if r["phase"] == "pg"]
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.8), layout="constrained")
    imitation_panel(ax[0], rows)
    ax[1].plot([r["iteration"] for r in ev], [r["eval/af1_vs_coverage"] for r in ev], "o-")
    ax[1].axhline(0.0, color="k", lw=0.6)
    ax[1].set_title("validation: AF1 - coverage AF1 (argmax)")
    ax[2].plot([r["iteration"] for r in pg], [r["charts/advantage_vs_coverage"] for r in pg], lw=0.8,
               label="return - coverage return (per episode)")
    ax[2].plot([r["iteration"] for r in pg], [r["charts/entropy"] for r in pg], lw=0.8, label="entropy (nats)")
    ax[2].set_title("REINFORCE")
    ax[2].legend(fontsize=8)
    finish_curves(fig, ax, title, path)


def train(args: Args, caches=None) -> TrainResult:
    """Train the reactive policy; `caches` = (train, val) ViewCaches to skip loading perception (tests)."""
    check_args(args)
    t_start = time.perf_counter()
    device = resolve_device(args.device)
    gen = start_training(args.threads, args.seed, device)
    conf_path = Path(args.confidence) if args.confidence else checkpoint_path(args.setting, FUSION)
    fusion, _, conf_extra = load_search_model(conf_path, device)
    if not fusion.trainable:
        raise UavsearchError(f"{conf_path} holds no confidence network ({fusion.name} fusion); give a learned-fusion "
                             "checkpoint with --confidence")
    name = args.name or f"reactive_s{args.setting}"
    run_dir = start_run(args, name, args.seed)

    train_cache, val_cache = (to_device(c, device) for c in (caches if caches is not None else load_caches(args)))
    tag = conf_extra.get("perception_tag") if isinstance(conf_extra, dict) else None
    if tag and tag != train_cache.perception_tag:
        print(f"uavsearch: warning: {conf_path}'s confidence net was trained on perception {tag}, the view cache "
              f"holds perception {train_cache.perception_tag}", file=sys.stderr)
    config = train_cache.config
    T, S = config.budget_T, train_cache.num_scenes
    train_scores, val_scores = score_table(train_cache, fusion.scorer), score_table(val_cache, fusion.scorer)
    train_s, val_s = scored(train_cache, train_scores), scored(val_cache, val_scores)
    lookup = ScoreLookup()
    on_scores = LearnedFusion(lookup)  # learned fusion reading the scored caches
    net = ReactivePolicyNet(ReactiveConfig(grid_size=config.grid.n, num_positions=config.lattice.num_positions,
                                           num_actions=len(config.actions), budget_T=T, step_m=config.step_m,
                                           channels=args.channels, conv_layers=args.conv_layers, hidden=args.hidden,
                                           search=config_to_dict(config))).to(device)

    with torch.no_grad():  # the coverage route: return to go per (train scene, step), and the validation bar
        cov = run_search(CachedViews(train_s, torch.arange(S), config, lookup), Agent(on_scores, CoverageRoute(config)))
        cov_returns = step_returns(cov.maps, cov.labels, cov.revisit, args.r_re)  # (S, T-1)
    cov_val = _validate(val_s, Agent(on_scores, CoverageRoute(config)), config)
    teacher_val = _validate(val_s, Agent(on_scores, LabelGreedyTeacher(val_s, torch.arange(val_s.num_scenes), lookup,
                                                                     config)), config)

    best, best_key = {}, (-float("inf"), -float("inf"))
    ckpt = run_dir / "model.pt"
    metrics = MetricsCsv(run_dir / "metrics.csv")
    rows = metrics.rows
    meta = {"args": asdict(args), "confidence": str(conf_path), "perception_tag": train_cache.perception_tag,
            "search_config": config_to_dict(config)}
    mirror = gen if args.mirror else None

    def validate(row: dict, it: int) -> dict:
        nonlocal best, best_key
        v = _validate(val_s, Agent(on_scores, ArgmaxPolicy(net)), config)
        row["eval/af1"], row["eval/aacc"], row["eval/af1_vs_coverage"] = v["af1"], v["aacc"], v["af1"] - cov_val["af1"]
        key = (row["eval/af1_vs_coverage"], v["aacc"])
        if key > best_key:
            best_key = key
            best = {"iteration": it, "phase": row["phase"], "val_af1": v["af1"], "val_aacc": v["aacc"],
                    "val_revisit": v["revisit"], "val_af1_vs_coverage": row["eval/af1_vs_coverage"]}
            save_search_model(ckpt, fusion, net, {**meta, "best": best})
        return {"vs_coverage": f"{row['eval/af1_vs_coverage']:+.3f}", "best": f"{best_key[0]:+.3f}"}

    def blank(it: int, phase: str) -> dict:
        return {"iteration": it, "phase": phase, "losses/imitation": None, "losses/policy": None,
                "charts/teacher_agreement": None, "charts/beta": None, "charts/aggregate": None,
                "charts/return": None, "charts/advantage_vs_coverage": None, "charts/train_cls_reward": None,
                "charts/revisit_rate": None, "charts/entropy": None, "charts/entropy_coef": None,
                "eval/af1": None, "eval/aacc": None, "eval/af1_vs_coverage": None}

    def reinforce_loss(ep, rows_b) -> ReinforceLoss:
        """Each move's return to go against the coverage route's from the same scene and step."""
        G = step_returns(ep.maps.detach(), ep.labels, ep.revisit, args.r_re)
        adv = G - cov_returns[rows_b]
        adv_n = (adv - adv.mean()) / (adv.std() + 1e-8)
        charts = {"charts/return": float(G[:, 0].mean()), "charts/advantage_vs_coverage": float(adv[:, 0].mean()),
                  "charts/train_cls_reward": float(classification_reward(ep.maps[:, -1].detach(), ep.labels).float()
                                                    .mean()),
                  "charts/revisit_rate": float(ep.revisit[:, 1:].float().mean())}
        return ReinforceLoss(-(ep.log_prob * adv_n).mean(), ep.entropy.mean(), charts, float(G.numel()))

    dagger_reinforce(DaggerPolicy(
        net, on_scores, views=lambda rows_b: CachedViews(train_s, rows_b, config, lookup),
        teacher=lambda rows_b: LabelGreedyTeacher(train_s, rows_b, lookup, config, scores=train_scores),
        imitation_loss=lambda batch, g: imitation_loss(net, *batch, mirror, config), reinforce_loss=reinforce_loss,
        validate=validate, blank=blank, validate_each_dagger=False), args, S, gen, metrics.log, name)
    metrics.close()
    if args.plot:
        _plot(rows, run_dir / "learning_curve.png", f"{name}, seed {args.seed}")
    out = copy_checkpoint(ckpt, args.out, args.ship, checkpoint_path(args.setting, FUSION, policy="reactive"))
    seconds = time.perf_counter() - t_start
    table = [{"method": "learned fusion + coverage route", **cov_val},
             {"method": f"learned fusion + reactive policy (iteration {best.get('iteration')})",
              "af1": best.get("val_af1"), "aacc": best.get("val_aacc"), "revisit": best.get("val_revisit")},
             {"method": "learned fusion + label-greedy teacher (peeks at labels)", **teacher_val}]
    summary = {"best": best, "validation": table, "seconds": seconds, "checkpoint": str(out or ckpt)}
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=1))
    return TrainResult(run_dir, out or ckpt, best, table, seconds)


def format_table(table: list[dict], scenes: str = "validation scenes") -> str:
    lines = [f"| method ({scenes}, argmax moves) | AF1 | Aacc (%) | revisit rate |", "|---|---|---|---|"]
    for r in table:
        lines.append(f"| {r['method']} | {r['af1']:.3f} | {100 * r['aacc']:.2f} | {r['revisit']:.3f} |")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------------
# CLI


def add_train_reactive_parser(subparsers) -> None:
    """`uavsearch train reactive ...` (subparsers: the `train` command's); one flag per Args field."""
    p = subparsers.add_parser("reactive", help="the reactive view-selection policy: DAgger + REINFORCE (beyond the "
                                               "paper)",
                              description="A conv-net policy on the map of what each view said, imitating a "
                                          "label-peeking teacher, then REINFORCE against the coverage route; see "
                                          "uavsearch/search/train/reactive.py.")
    add_dataclass_args(p, Args)
    p.set_defaults(func=cmd_train_reactive)


def cmd_train_reactive(args) -> int:
    res = train(dataclass_from_args(Args, args))
    print(format_table(res.table))
    print(f"best validation: {json.dumps(res.best)}")
    print(f"{res.seconds:.0f} s; run {res.run_dir}; checkpoint {res.checkpoint}")
    return 0


if __name__ == "__main__":  # python -m uavsearch.search.train.reactive [flags] = uavsearch train reactive [flags]
    raise SystemExit(run_command(cmd_train_reactive, add_dataclass_args(argparse.ArgumentParser(
        prog="python -m uavsearch.search.train.reactive"), Args).parse_args()))
