"""Stage 1 (paper Sec. V-A): one-view training of the perception backbone and the cell classifier.

CleanRL-style: an Args dataclass, `train(args)` does everything. Each mini-batch is 32 views; the loss is
the softmax (NLL of the log-softmax) loss over every cell of every view that covers at least
`min_cell_px` pixels.

Class imbalance: only 1-12 of 100 cells hold a person. We weight the occupied class's loss by
`pos_weight` (default 4), a middle ground: unweighted training learns "always empty" for a long time
(Aacc ~0.95 at F1 ~0), while full inverse-frequency weighting (~15) floods maps with false positives.
The weight moves the decision threshold, so it is chosen for validation F1 at the fixed 0.5 threshold
of the paper's metric, and for what fusion needs: with weight 3 (400 steps) an occupied cell's mean
p(occupied) was 0.38, so averaging views pulled true positives under 0.5 and every multi-view fusion
lost F1 to the single view; with weight 4 (800 steps) it is 0.5-0.6 and averaging gains. Augmentation: the 8 flips/rotations of the image, applied to the image and its
cell label image together, which keeps every cell's ground truth (the heading is fixed north, so
this only adds orientation variety).

Output: runs/<exp_name>__<seed>__<unix time>/ with args.json (written first), metrics.csv (grouped
names: losses/, charts/, eval/), learning_curve.png and the best checkpoint (by validation AF1). Only
`--out PATH` or `--ship` (models/perception.pt, the shipped net) copies it elsewhere.
"""

from __future__ import annotations

import csv
import json
import random
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from uavsearch.cli_args import add_dataclass_args, dataclass_from_args, opt
from uavsearch.errors import UavsearchError
from uavsearch.parallel import Executor, ScaleOutArgs, Store
from uavsearch.paths import MODELS_DIR, RUNS_DIR
from uavsearch.viz import pyplot, save_figure

from .config import SearchConfig, lattice_positions
from .dataset import DATA_DIR, ViewSet, ViewSetSpec, generate_views, load_views, perception_scenes
from .fusion import DEFAULT_PRIOR
from .metrics import average_metrics, cell_correct
from .perception import PerceptionConfig, PerceptionNet, images_to_tensor, save_perception


@dataclass
class Args(ScaleOutArgs):
    exp_name: str = opt("perception", "the run's name in runs/")
    seed: int = opt(1, "seeds numpy, torch and the scene/position draw")
    train_scenes: int = opt(150, "training scenes (large-split train seeds of settings 1-3, K drawn in 1..12)")
    train_views_per_scene: int = opt(8, "distinct lattice positions rendered per training scene", flag="--train-views")
    val_scenes: int = opt(30, "validation scenes (large-split val seeds), K drawn in 1..12")
    val_views_per_scene: int = opt(4, "lattice positions per validation scene (the start view included)",
                                   flag="--val-views")
    data_dir: str = opt(str(DATA_DIR), "where rendered view sets are cached (a folder or an fsspec URL)")
    steps: int = opt(800, "optimiser steps")
    batch_size: int = opt(32, "views per mini-batch (paper: 32)")
    lr: float = opt(1e-3, "Adam learning rate (cosine-decayed to 5% of it); from scratch, not fine-tuning")
    weight_decay: float = opt(1e-5, "Adam L2 (paper's alpha: 1e-6)")
    pos_weight: float = opt(4.0, "loss weight of the occupied class (class imbalance; see module docstring)")
    augment: bool = opt(True, "random flips / 90-degree rotations of image + label image")
    min_cell_px: float = opt(16.0, "cells smaller than this in a view are not trained on")
    eval_every: int = opt(100, "steps between validations")
    threads: int = opt(2, "torch CPU threads")
    out: str | None = opt(None, "also copy the best checkpoint here (it always stays in the run directory)")
    ship: bool = opt(False, "copy the best checkpoint over the shipped models/perception.pt")
    runs_dir: str = opt(str(RUNS_DIR), "parent of the run directory")
    progress: bool = opt(True, "tqdm bars")
    layers: tuple = opt(factory=lambda: PerceptionConfig().layers, help="backbone (out, kernel, stride)", cli=False)


def copy_checkpoint(ckpt: Path, out, ship: bool, shipped: Path) -> Path | None:
    """Training writes into its run directory; only an explicit `out`, or `ship` (the shipped file in
    models/), copies the best checkpoint elsewhere. Returns where it went (None: nowhere)."""
    if ship and out and Path(out).resolve() != Path(shipped).resolve():
        raise UavsearchError(f"--ship writes {shipped}; drop --out {out} or --ship")
    target = Path(shipped) if ship else Path(out) if out else None
    if target is not None:
        target.parent.mkdir(parents=True, exist_ok=True)
        if target.resolve() != Path(ckpt).resolve():
            shutil.copyfile(ckpt, target)
    return target


def seed_everything(seed: int) -> np.random.Generator:
    """One call seeds numpy, torch and Python's random; returns the generator the run draws from."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)
    return np.random.default_rng(seed)


def augment_batch(images: np.ndarray, labels: np.ndarray, rng: np.random.Generator):
    """Apply one of the 8 dihedral transforms per view to the image and its label image alike."""
    imgs, labs = images.copy(), labels.copy()
    for b in range(len(images)):
        k, flip = int(rng.integers(4)), bool(rng.integers(2))
        im, lb = np.rot90(images[b], k, axes=(0, 1)), np.rot90(labels[b], k, axes=(0, 1))
        if flip:
            im, lb = im[:, ::-1], lb[:, ::-1]
        imgs[b], labs[b] = im, lb
    return imgs, labs


def batch_loss(net: PerceptionNet, images, labels, occupancy, min_px: float, pos_weight: float):
    """Weighted softmax loss over the trainable cells of a batch; returns (loss, log_probs, cell mask)."""
    out = net.forward_all(images, labels)
    y = torch.as_tensor(occupancy, dtype=torch.long)
    mask = out.cell_pixels >= min_px
    nll = F.nll_loss(out.log_probs.reshape(-1, 2), y.reshape(-1), reduction="none").view_as(y)
    w = torch.where(y == 1, torch.full_like(nll, pos_weight), torch.ones_like(nll)) * mask
    return (nll * w).sum() / w.sum().clamp(min=1.0), out.log_probs, mask


@torch.no_grad()
def predict_views(net: PerceptionNet, views: ViewSet, batch_size: int = 64, progress: bool = False):
    """Single-view occupancy maps p(y=1) (V, N*N) with the prior where a cell is out of view, + pixels."""
    net.eval()
    probs, pixels = [], []
    for i in tqdm(range(0, len(views), batch_size), desc="predict", disable=not progress, leave=False):
        rows = np.arange(i, min(i + batch_size, len(views)))
        out = net.forward_all(views.images[rows], views.label_images(rows))
        probs.append(out.log_probs[..., 1].exp().numpy())
        pixels.append(out.cell_pixels.numpy())
    p, px = np.concatenate(probs), np.concatenate(pixels)
    p = np.where(views.cells_in_view, p, DEFAULT_PRIOR)
    return p, px


def evaluate(net: PerceptionNet, views: ViewSet, centre_index: int) -> dict[str, float]:
    """Single-view Aacc/AF1 on every view and on the start views only, plus cell-level numbers."""
    p, _ = predict_views(net, views)
    y = views.occupancy
    aacc, af1 = average_metrics(p, y)
    start = views.lattice_index == centre_index
    s_aacc, s_af1 = average_metrics(p[start], y[start]) if start.any() else (float("nan"), float("nan"))
    seen = views.cells_in_view
    pos, pred = (y == 1) & seen, (p > 0.5) & seen
    return {
        "eval/aacc": aacc, "eval/af1": af1, "eval/start_aacc": s_aacc, "eval/start_af1": s_af1,
        "eval/cell_acc": float(cell_correct(p, y)[seen].mean()),
        "eval/recall": float((pos & pred).sum() / max(pos.sum(), 1)),
        "eval/precision": float((pos & pred).sum() / max(pred.sum(), 1)),
    }


def _plot_curves(rows: list[dict], path: Path) -> None:
    save_figure(curves_figure(rows), path)


def curves_figure(rows: list[dict]):
    """Stage 1's learning curves: training loss, validation metrics."""
    fig, (a, b) = pyplot().subplots(1, 2, figsize=(10, 3.8), layout="constrained")
    tr = [r for r in rows if r.get("losses/train_loss") not in (None, "")]
    if tr:
        st = np.array([r["step"] for r in tr])
        ls = np.array([r["losses/train_loss"] for r in tr], dtype=float)
        k = max(1, len(ls) // 50)
        sm = np.convolve(ls, np.ones(k) / k, mode="valid")
        a.plot(st, ls, alpha=0.3, lw=0.8, label="train loss")
        a.plot(st[k - 1 :], sm, lw=1.5, label=f"moving mean ({k})")
        a.set_xlabel("step"), a.set_ylabel("weighted softmax loss"), a.legend(), a.grid(alpha=0.3)
    ev = [r for r in rows if r.get("eval/aacc") not in (None, "")]
    if ev:
        st = [r["step"] for r in ev]
        for key, lab in (("eval/aacc", "Aacc (all views)"), ("eval/af1", "AF1 (all views)"),
                         ("eval/start_aacc", "Aacc (start view)"), ("eval/start_af1", "AF1 (start view)")):
            b.plot(st, [r[key] for r in ev], marker="o", ms=3, label=lab)
        b.set_xlabel("step"), b.set_ylabel("validation"), b.set_ylim(0, 1), b.legend(), b.grid(alpha=0.3)
    fig.suptitle("Stage 1: one-view perception training")
    return fig


def prepare_data(args: Args) -> tuple[ViewSet, ViewSet, int]:
    """Render (or reuse) the training and validation view sets; returns them and the start-view index."""
    train_spec = ViewSetSpec(f"train_v{args.train_views_per_scene}_s{args.seed}",
                             perception_scenes("train", args.train_scenes, args.seed),
                             views_per_scene=args.train_views_per_scene, seed=args.seed)
    val_spec = ViewSetSpec(f"val_v{args.val_views_per_scene}_s{args.seed}",
                           perception_scenes("val", args.val_scenes, args.seed),
                           views_per_scene=args.val_views_per_scene, seed=args.seed)
    root, executor = Store(args.data_dir), Executor.from_args(args)
    t0 = time.perf_counter()
    tr_root = generate_views(train_spec, root.path(train_spec.name), progress=args.progress, executor=executor)
    va_root = generate_views(val_spec, root.path(val_spec.name), progress=args.progress, executor=executor)
    render_s = time.perf_counter() - t0
    train, val = load_views(tr_root, train_spec.scenes), load_views(va_root, val_spec.scenes)
    print(f"data: {len(train)} training views of {args.train_scenes} scenes, {len(val)} validation views of "
          f"{args.val_scenes} scenes ({render_s:.0f} s to render / load from {root.url})")
    return train, val, len(lattice_positions(SearchConfig())) // 2


def train(args: Args) -> dict:
    """Run stage 1; returns the final report (validation metrics of the best checkpoint, times, paths)."""
    if args.batch_size < 1 or args.steps < 1:
        raise UavsearchError("batch_size and steps must be positive")
    torch.set_num_threads(max(1, args.threads))
    rng = seed_everything(args.seed)
    run_dir = Path(args.runs_dir) / f"{args.exp_name}__{args.seed}__{int(time.time())}"
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "args.json").write_text(json.dumps(asdict(args), indent=1))
    t_start = time.perf_counter()
    train_set, val_set, centre = prepare_data(args)
    t_data = time.perf_counter() - t_start

    net = PerceptionNet(PerceptionConfig(layers=tuple(tuple(x) for x in args.layers)))
    opt = torch.optim.Adam(net.parameters(), lr=args.lr, weight_decay=args.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: 0.05 + 0.95 * 0.5 * (1 + np.cos(np.pi * min(s, args.steps) / args.steps)))
    rows: list[dict] = []
    best: dict = {"eval/af1": -1.0}
    ckpt = run_dir / "perception.pt"
    csv_path = run_dir / "metrics.csv"
    fields = ["step", "time_s", "losses/train_loss", "charts/lr", "charts/views_per_s", "eval/aacc", "eval/af1",
              "eval/start_aacc", "eval/start_af1", "eval/cell_acc", "eval/recall", "eval/precision"]
    with open(csv_path, "w", newline="") as fh:
        csv.DictWriter(fh, fields).writeheader()

    def log(row):
        rows.append(row)
        with open(csv_path, "a", newline="") as fh:
            csv.DictWriter(fh, fields).writerow(row)

    t_train = time.perf_counter()
    bar = tqdm(range(1, args.steps + 1), desc="train perception", unit="step", disable=not args.progress)
    for step in bar:
        net.train()
        rows_b = rng.integers(0, len(train_set), args.batch_size)
        imgs, labs = train_set.images[rows_b], train_set.label_images(rows_b)
        if args.augment:
            imgs, labs = augment_batch(imgs, labs, rng)
        loss, _, _ = batch_loss(net, images_to_tensor(np.ascontiguousarray(imgs)), np.ascontiguousarray(labs),
                                train_set.occupancy[rows_b], args.min_cell_px, args.pos_weight)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        row = {"step": step, "time_s": round(time.perf_counter() - t_train, 2), "losses/train_loss": loss.item(),
               "charts/lr": sched.get_last_lr()[0],
               "charts/views_per_s": step * args.batch_size / (time.perf_counter() - t_train)}
        if step % args.eval_every == 0 or step == args.steps:
            row.update(evaluate(net, val_set, centre))
            bar.set_postfix(af1=f"{row['eval/af1']:.3f}", aacc=f"{row['eval/aacc']:.3f}")
            if row["eval/af1"] > best["eval/af1"]:
                best = {**row}
                save_perception(net, ckpt, extra={"args": asdict(args), "step": step,
                                                  "val": {k: v for k, v in row.items() if k.startswith("eval/")}})
        log(row)
    bar.close()
    train_s = time.perf_counter() - t_train
    _plot_curves(rows, run_dir / "learning_curve.png")
    out = copy_checkpoint(ckpt, args.out, args.ship, MODELS_DIR / "perception.pt")
    report = {
        "best_step": best["step"], **{k: best[k] for k in best if k.startswith("eval/")},
        "train_views": len(train_set), "val_views": len(val_set), "data_s": t_data, "train_s": train_s,
        "run_dir": str(run_dir), "checkpoint": str(out or ckpt),
    }
    (run_dir / "report.json").write_text(json.dumps(report, indent=1))
    _print_report(report)
    return report


def _print_report(r: dict) -> None:
    print("\nstage 1 perception: validation of the best checkpoint (single view, threshold 0.5)")
    print(f"| {'metric':<22} | {'value':>10} |\n|{'-' * 24}|{'-' * 12}|")
    for k in ("eval/aacc", "eval/af1", "eval/start_aacc", "eval/start_af1", "eval/cell_acc", "eval/recall",
              "eval/precision"):
        print(f"| {k:<22} | {r[k]:>10.3f} |")
    print(f"| {'best step':<22} | {r['best_step']:>10d} |")
    print(f"| {'train / val views':<22} | {str(r['train_views']) + ' / ' + str(r['val_views']):>10} |")
    print(f"| {'data time (s)':<22} | {r['data_s']:>10.0f} |\n| {'train time (s)':<22} | {r['train_s']:>10.0f} |")
    print(f"run: {r['run_dir']}\ncheckpoint: {r['checkpoint']}")


# --------------------------------------------------------------------------------------------------
# CLI hook: `uavsearch train perception ...` (wired in uavsearch/cli.py)


def add_train_perception_parser(subparsers) -> None:
    """Add `perception` to the `uavsearch train` subcommands; one flag per Args field."""
    p = subparsers.add_parser("perception", help="stage 1: train the per-cell perception (one-view training)")
    add_dataclass_args(p, Args)
    p.set_defaults(func=cmd_train_perception)


def cmd_train_perception(args) -> int:
    train(dataclass_from_args(Args, args))
    return 0
