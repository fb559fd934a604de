"""The wide-area search's learned view aggregation (neighbour_fusion.NeighbourFusion): a small conv net that
corrects the calibrated fusion's map after every view from each cell's views and its neighbours'.

CleanRL-style: `Args`, then `train(args)` does everything. Perception is FROZEN (its view caches) and so is the
base fusion (Table III's for the budget, `calibrated:GAMMA` fitted on the first `calibration_scenes` training
scenes).

1. Rollouts: on every training scene, `rollouts` episodes of the rule (Table III's variant, chosen on validation
   scenes): the first as the rule flies, the others with `noise` of their moves random (seeded by the rollout's
   index), so the net sees maps the rule alone would not reach. Of each episode the map after its last view and
   after two views drawn at random (the fusion corrects the map after every view) are kept as
   neighbour_fusion.view_planes, with the occupancy as the target. With `--features` each map also carries the
   views' mean cell features per altitude layer (neighbour_fusion.feature_planes, read from the caches' feature
   stores; float16, about 0.4 MB a map) and the net reduces them (FeatureCorrectionNet).
2. Fit: cross-entropy of the corrected log-odds against the occupancy, Adam with its rate annealed to zero
   (cosine: with a constant rate the last epoch landed wherever the rate left it, 0.06 AF1 off its neighbours),
   every minibatch under a random symmetry of the square (without them a net that sees a neighbourhood memorises
   where each scene's clutter lies). The decision threshold (a log-odds shift) is the one of `SHIFTS` with the
   best AF1 on the final training maps. Each epoch is checkpointed (`train_state.pt`): a rerun with `--resume RUN_DIR` continues
   where it stopped (killed, or `--stop-after N` to split a fit over sessions); the rollouts are seeded and
   rebuilt, so it continues on the same data and the same schedule: the same weights as one uninterrupted run.
3. Validation, logged every `eval_every` epochs: the rule flies the validation scenes with the corrected map (it
   reads it to choose its descents), paired against the rule on the base fusion. Nothing is chosen on it: the
   checkpoint is the last epoch's, so the validation figures are not selected on the scenes that report them.

Output: runs/fusion_<family>_<budget>__<seed>__<unix time>/ with args.json, metrics.csv, learning_curve.png,
model.pt (save_neighbour; the spec `neighbour:PATH` names it everywhere a fusion is named) and summary.json
(with the weights' SHA-256: the same seed and threads give the same bits). `--out PATH` copies model.pt.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch import nn

from uavsearch.cli_args import add_dataclass_args, dataclass_from_args, opt
from uavsearch.errors import UavsearchError, run_command
from uavsearch.paths import display_path
from uavsearch.viz import pyplot

from ..agents import make_fusion
from ..map_policy import BUDGETS
from ..metrics import bootstrap_ci, map_f1
from ..neighbour_fusion import (PLANES, CorrectionNet, FeatureCorrectionNet, NeighbourFusion, episode_planes,
                                feature_planes, save_neighbour)
from ..search_loop import Agent, CachedViews, run_search
from ..symmetry import square_symmetry
from ..table3_choices import table3_choice
from ..wide_policies import NoisyRule, choose_rule, lowest_layer, rule_policy
from .map_policy import _caches, budget_config
from .runs import MetricsCsv, RunArgs, copy_checkpoint, finish_curves, start_run, start_training

SHIFTS = np.arange(-2.0, 2.01, 0.25)  # decision thresholds tried, as log-odds shifts


@dataclass
class Args(RunArgs):
    family: str = opt("wide", "scene family (wide | wide-uniform)")
    budget: str = opt("8", "Table III's budget: 8 (views) or 240 (seconds of flight)", choices=BUDGETS)
    perception: str | None = opt(None, "frozen perception (default the family's shipped net)")
    fusion: str | None = opt(None, "the base fusion the net corrects (default Table III's for the budget)")
    train_scenes: int = opt(300, "training scenes, the first N of the part (views are rendered where missing, "
                                 "resumable)")
    val_scenes: int = opt(50, "validation scenes (logged, never chosen on)")
    calibration_scenes: int = opt(20, "training scenes the calibrated base fusion is fitted on (Table III's)")
    rollouts: int = opt(10, "episodes per training scene: the rule, then the rule with --noise random moves")
    noise: float = opt(0.3, "share of random moves in every rollout after the first")
    epochs: int = opt(20, "passes over the training maps")
    batch_size: int = opt(64, "maps per minibatch")
    lr: float = opt(3e-3, "Adam's first learning rate")
    cosine: bool = opt(True, "anneal the learning rate to zero over the epochs (cosine): the last epoch, which is "
                             "the checkpoint, is a settled one rather than wherever a constant rate left it")
    weight_decay: float = opt(1e-4, "Adam L2")
    kernel: int = opt(5, "the net's conv kernel: 5 sees each cell's 5 x 5 neighbourhood twice over, 1 the cell alone")
    features: bool = opt(False, "also read the views' cell features (per altitude layer their mean, reduced by a "
                                "learned 1 x 1 convolution): what perception saw, not only its scores")
    reduce: int = opt(8, "channels the cell features are reduced to (with --features)")
    hidden: int = opt(24, "conv channels")
    symmetries: bool = opt(True, "fit every minibatch under a random symmetry of the square")
    eval_every: int = opt(5, "epochs between validations")
    out: str | None = opt(None, "also copy model.pt here (it always stays in the run directory)")
    name: str | None = opt(None, "run name (default fusion_<family>_<budget>)")
    resume: str | None = opt(None, "continue this run directory from its last finished epoch")
    stop_after: int | None = opt(None, "end after this epoch (the schedule still spans --epochs); --resume continues")
    seed: int = opt(0, "seeds the net's initial weights, the minibatches and their symmetries")


class TrainResult(NamedTuple):
    run_dir: Path
    checkpoint: Path
    table: list[dict]  # validation rows: the rule on the base fusion, the rule on the learned one
    seconds: float


def check_args(args: Args) -> None:
    for name in ("train_scenes", "val_scenes", "calibration_scenes", "rollouts", "epochs", "batch_size",
                 "hidden", "eval_every", "reduce"):
        if getattr(args, name) < 1:
            raise UavsearchError(f"--{name.replace('_', '-')} must be at least 1")
    if args.kernel < 1 or args.kernel % 2 == 0:
        raise UavsearchError(f"--kernel must be odd and positive, got {args.kernel}")
    if not 0.0 <= args.noise <= 1.0:
        raise UavsearchError(f"--noise is a share of moves in [0, 1], got {args.noise}")
    if args.budget not in BUDGETS:
        raise UavsearchError(f"--budget must be one of {', '.join(BUDGETS)}")


def weights_sha(net: nn.Module) -> str:
    """SHA-256 of the weights' bytes, in state_dict order: two fits are the same fit iff these are equal."""
    h = hashlib.sha256()
    for k, v in net.state_dict().items():
        h.update(k.encode())
        h.update(v.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()


class RolloutMaps(NamedTuple):
    """The training maps: `planes` (M, C, n, n) after the last and two random views of every rollout, `targets`
    (M, n, n) their occupancy, `final` (M,) bool the maps after an episode's last view (in rollout order)."""

    planes: torch.Tensor
    targets: torch.Tensor
    final: torch.Tensor


def rollout_planes(cache, fusion, config, rule, rollouts: int, noise: float, features: bool = False) -> RolloutMaps:
    """view_planes of the rollouts on every scene of `cache` after each episode's last view and two random ones;
    with `features` feature_planes beside them, all in float16 (about 0.4 MB a map)."""
    rows = np.arange(cache.num_scenes)
    lowest, n = lowest_layer(config), config.grid.n
    every, final = [], []
    for k in range(rollouts):
        gen = torch.Generator().manual_seed(k)
        with torch.no_grad():
            ep = run_search(CachedViews(cache, rows, config), Agent(fusion, NoisyRule(rule, noise if k else 0.0, gen)),
                            generator=torch.Generator().manual_seed(0))
        last = ep.lattice_idx.shape[1] - 1
        for t in sorted({last} | set(torch.randint(last + 1, (2,), generator=gen).tolist())):
            x = episode_planes(cache, rows, ep, fusion.coef, lowest, n, t)
            if features:
                x = torch.cat([x.half(), feature_planes(cache, rows, ep, lowest, n, t)], 1)
            every.append(x)
            final.append(torch.full((len(rows),), t == last))
    occupancy = cache.occupancy.float().view(-1, n, n)
    return RolloutMaps(torch.cat(every), occupancy.repeat(len(every), 1, 1), torch.cat(final))


def net_logits(net: nn.Module, planes: torch.Tensor, chunk: int = 500) -> np.ndarray:
    """(M, n*n) the net's log-odds of the maps, `chunk` maps at a time (float16 maps become float32 only there)."""
    with torch.no_grad():
        return np.concatenate([_flat(net(planes[j:j + chunk])) for j in range(0, len(planes), chunk)])


def best_shift(logits: np.ndarray, labels: np.ndarray) -> float:
    """The log-odds shift of SHIFTS with the best mean F1 of the maps."""
    return float(max(SHIFTS, key=lambda s: map_f1(1 / (1 + np.exp(-(logits + s))), labels).mean()))


def _flat(t: torch.Tensor) -> np.ndarray:
    return t.reshape(len(t), -1).numpy()


def _plot(rows: list[dict], path: Path, title: str) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(10, 3.8), layout="constrained")
    ax[0].plot([r["epoch"] for r in rows], [r["losses/train"] for r in rows], "o-", lw=0.8)
    ax[0].set_title("cross-entropy, training maps")
    ev = [r for r in rows if r["eval/val_vs_base"] is not None]
    ax[1].plot([r["epoch"] for r in ev], [r["eval/val_vs_base"] for r in ev], "o-", label="the rule, validation")
    ax[1].axhline(0.0, color="k", lw=0.6)
    ax[1].set_title("AF1 - the rule's on the base fusion")
    ax[1].legend(fontsize=8)
    finish_curves(fig, ax, title, path, xlabel="epoch")


def train(args: Args, caches=None) -> TrainResult:
    """Fit the neighbour fusion; `caches` = (train, val) ViewCaches skips loading perception (tests)."""
    check_args(args)
    t_start = time.perf_counter()
    gen = start_training(args.threads, args.seed)
    train_cache, val_cache = caches if caches is not None else _caches(args)
    if train_cache.config.move_set != "any":
        raise UavsearchError(f"the neighbour fusion is the wide family's: {args.family!r} is not a wide family")
    config = budget_config(train_cache.config, args.budget)
    base_spec = args.fusion or table3_choice(args.family, args.budget).fusion
    base = make_fusion(base_spec, train_cache.subset(np.arange(min(args.calibration_scenes, train_cache.num_scenes))))
    if not hasattr(base, "coef"):
        raise UavsearchError(f"the neighbour fusion corrects a calibrated fusion (calibrated:GAMMA), not {base_spec!r}")
    variant, _ = choose_rule(val_cache, config, base)
    rule = rule_policy(config, variant)
    if args.resume:
        run_dir = Path(args.resume)
        if not (run_dir / "train_state.pt").is_file():
            raise UavsearchError(f"--resume {args.resume}: no train_state.pt there (not a fusion run, or no epoch "
                                 "finished)")
    else:
        run_dir = start_run(args, args.name or f"fusion_{args.family}_{args.budget}", args.seed)

    maps = rollout_planes(train_cache, base, config, rule, args.rollouts, args.noise, args.features)
    XS, YS = maps.planes, maps.targets
    torch.manual_seed(args.seed)
    net = FeatureCorrectionNet(XS.shape[1] - PLANES, args.kernel, args.reduce, args.hidden) if args.features else \
        CorrectionNet(XS.shape[1], args.kernel, args.hidden)
    opt_ = torch.optim.Adam(net.parameters(), lr=args.lr, weight_decay=args.weight_decay)
    steps = args.epochs * -(-len(XS) // args.batch_size)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt_, (lambda i: 0.5 * (1.0 + np.cos(np.pi * min(i, steps) / steps))) if args.cosine else (lambda i: 1.0))
    first, rows = 0, []
    if args.resume:
        state = torch.load(run_dir / "train_state.pt", weights_only=False)
        net.load_state_dict(state["net"])
        opt_.load_state_dict(state["optimizer"])
        sched.load_state_dict(state["scheduler"])
        gen.set_state(state["generator"])
        first, rows = state["epoch"], state["rows"]
        if state.get("epochs", args.epochs) != args.epochs:
            raise UavsearchError(f"--resume {args.resume}: that run was started for {state['epochs']} epochs, not "
                                 f"{args.epochs} (its learning rate's schedule spans them)")
    val_rows = np.arange(val_cache.num_scenes)

    def val_f1(fusion) -> np.ndarray:
        with torch.no_grad():
            ep = run_search(CachedViews(val_cache, val_rows, config), Agent(fusion, rule),
                            generator=torch.Generator().manual_seed(0))
        return map_f1(ep.maps[:, -1].numpy(), val_cache.occupancy.numpy())

    base_f1 = val_f1(base)
    X, yt = XS[maps.final], _flat(YS[maps.final])

    def fitted() -> NeighbourFusion:
        net.eval()
        return NeighbourFusion.around(base, net, best_shift(net_logits(net, X), yt), config)

    from tqdm import tqdm

    metrics = MetricsCsv(run_dir / "metrics.csv")
    for r in rows:  # a resumed run's csv holds every epoch, the earlier ones too
        metrics.log(r)
    bar = tqdm(range(first, args.epochs), initial=first, total=args.epochs, desc="fusion", unit="epoch",
               disable=not args.progress)
    for epoch in bar:
        net.train()
        losses = []
        perm = torch.randperm(len(XS), generator=gen)
        for j in range(0, len(XS), args.batch_size):
            b = perm[j:j + args.batch_size]
            k = int(torch.randint(8, (), generator=gen)) if args.symmetries else 0
            loss = nn.functional.binary_cross_entropy_with_logits(net(square_symmetry(XS[b], k)),
                                                                  square_symmetry(YS[b], k))
            opt_.zero_grad()
            loss.backward()
            opt_.step()
            sched.step()
            losses.append(float(loss.detach()))
        row = {"epoch": epoch + 1, "seconds": round(time.perf_counter() - t_start, 1),
               "losses/train": float(np.mean(losses)), "lr": opt_.param_groups[0]["lr"], "shift": None,
               "eval/val_af1": None, "eval/val_vs_base": None}
        if (epoch + 1) % args.eval_every == 0 or epoch + 1 == args.epochs:
            fusion = fitted()
            f1 = val_f1(fusion)
            row.update({"shift": fusion.shift, "eval/val_af1": float(f1.mean()),
                        "eval/val_vs_base": float((f1 - base_f1).mean())})
            bar.set_postfix(val_vs_base=f"{row['eval/val_vs_base']:+.3f}")
        metrics.log(row)
        rows.append(row)
        torch.save({"net": net.state_dict(), "optimizer": opt_.state_dict(), "scheduler": sched.state_dict(),
                    "generator": gen.get_state(),
                    "epoch": epoch + 1, "epochs": args.epochs, "rows": rows}, run_dir / "train_state.pt")
        if args.stop_after is not None and epoch + 1 >= args.stop_after and epoch + 1 < args.epochs:
            break
    bar.close()
    metrics.close()
    if rows[-1]["epoch"] < args.epochs:  # --stop-after: no fusion yet, only the state to resume from
        return TrainResult(run_dir, run_dir / "train_state.pt", [], time.perf_counter() - t_start)
    fusion = fitted()
    f1 = val_f1(fusion)
    sha = weights_sha(net)
    seconds = time.perf_counter() - t_start
    meta = {"args": asdict(args), "base": base_spec, "rule": variant, "shift": fusion.shift, "weights_sha256": sha,
            "perception_tag": train_cache.perception_tag, "train_scenes": train_cache.num_scenes}
    ckpt = save_neighbour(fusion, run_dir / "model.pt", meta)
    if args.plot:
        _plot(rows, run_dir / "learning_curve.png", f"{run_dir.name.split('__')[0]}, seed {args.seed}")
    out = copy_checkpoint(ckpt, args.out, False, ckpt)
    d, lo, hi = bootstrap_ci(f1 - base_f1)
    table = [{"method": f"the rule ({variant}), {base_spec}", "af1": float(base_f1.mean()), "vs_base": 0.0,
              "ci": (0.0, 0.0)},
             {"method": f"the rule ({variant}), neighbour fusion{' with cell features' if args.features else ''}",
              "af1": float(f1.mean()), "vs_base": d,
              "ci": (lo, hi)}]
    summary = {"validation": table, "rule": variant, "base": base_spec, "seconds": seconds,
               "checkpoint": display_path(out or ckpt),
               "weights_sha256": sha, "shift": fusion.shift, "per_scene_f1": {"base": base_f1.tolist(),
                                                                              "neighbour": f1.tolist()},
               "scenes": {"train": train_cache.num_scenes, "val": val_cache.num_scenes, "maps": len(XS)}}
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=1))
    return TrainResult(run_dir, out or ckpt, table, seconds)


def format_table(table: list[dict], scenes: str) -> str:
    lines = [f"| method ({scenes}) | AF1 | − the base fusion [95% CI] |", "|---|---|---|"]
    lines += [f"| {r['method']} | {r['af1']:.3f} | {r['vs_base']:+.3f} [{r['ci'][0]:+.3f}, {r['ci'][1]:+.3f}] |"
              for r in table]
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------------
# CLI


def add_train_fusion_parser(subparsers) -> None:
    """`uavsearch train fusion ...` (subparsers: the `train` command's); one flag per Args field."""
    p = subparsers.add_parser("fusion", help="the wide-area search's learned view aggregation (neighbour fusion)",
                              description="A conv net correcting the calibrated fusion's map from each cell's views "
                                          "and its neighbours', fitted on rule rollouts; see "
                                          "uavsearch/search/train/fusion.py.")
    add_dataclass_args(p, Args)
    p.set_defaults(func=cmd_train_fusion)


def cmd_train_fusion(args) -> int:
    res = train(dataclass_from_args(Args, args))
    if not res.table:
        print(f"stopped after epoch {args.stop_after}; continue with --resume {res.run_dir}")
        return 0
    print(format_table(res.table, "validation scenes, last epoch"))
    print(f"{res.seconds:.0f} s; run {res.run_dir}; checkpoint {res.checkpoint} (spec neighbour:{res.checkpoint})")
    return 0


if __name__ == "__main__":  # python -m uavsearch.search.train.fusion [flags] = uavsearch train fusion [flags]
    raise SystemExit(run_command(cmd_train_fusion, add_dataclass_args(argparse.ArgumentParser(
        prog="python -m uavsearch.search.train.fusion"), Args).parse_args()))
