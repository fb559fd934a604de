"""Stage 1 (paper Sec. V-A): one-view training of the perception backbone, its person head and the cell classifier.

CleanRL-style: an Args dataclass, `train(args)` does everything. The net is any registered perception kind
(`--net cnn`, the shipped nets' kind, or `--net resnet`), built and used only through the perception contract
(search/perception.py: `build_perception`, `forward_all`, `dense_loss`, `shift_logit_margin`, `arguments`).

Data: every lattice view of the large split's training scenes, the very renders the stage-2 view caches
are built from (view_cache.render_lattice_views: 500 scenes x 25 positions x 3 settings = 37,500 views,
rendered once and shared), validated on the large split's validation scenes. Views are drawn at random
(with the 8 flips/rotations of image, cell labels and person map together: the heading is fixed north,
so this only adds orientation variety) and trained on random `crop` x `crop` windows: a third of the
pixels per step for the same number of cells seen, while each cell keeps the geometry features
(pixel count, centroid) of the whole view, which is what inference sees.

Loss, per mini-batch of `batch_size` crops:
- cells: the softmax (NLL of the log-softmax) loss over every cell with at least `min_cell_px` pixels in
  the crop, the occupied class weighted by `pos_weight` (only 2-10 of 100 cells hold a person; unweighted
  training learns "always empty" for a long time, full inverse-frequency weighting floods maps with
  false alarms); and empty cells weighted up by `hard_negative_weight` x the share of their earlier
  views in which they were false alarms: a bench or a dark window that fools the net from every
  position is a persistent false alarm no second view can correct, so it is mined and weighted;
- pixels: `person_weight` x the kind's dense loss (both kinds: the binary cross-entropy of the person head
  against the renderer's per-pixel person fraction; dense supervision: every person pixel is a label, where a
  cell is one label per 200 pixels), positives weighted by `person_pos_weight`.

The checkpoint kept is the one with the best validation cell average precision (threshold-free); at the
end its decision threshold is calibrated on the validation views: a shift of the classifier's logit
margin, chosen for validation AF1 at the paper's fixed 0.5 threshold, is folded into the last layer's
bias (`calibration_shift` in the checkpoint's metadata).

Output: runs/<exp_name>__<seed>__<unix time>/ with args.json (written first), metrics.csv (grouped
names: losses/, charts/, eval/), learning_curve.png and the best checkpoint. Only `--out PATH` or
`--ship` (models/perception.pt, the shipped net) copies it elsewhere. A rerun with the same run name
(`--resume DIR`) continues from the last periodic checkpoint.
"""

from __future__ import annotations

import csv
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from uavsearch.cli_args import add_dataclass_args, dataclass_from_args, opt
from uavsearch.devices import cpu_state, device_of, resolve_device
from uavsearch.errors import UavsearchError
from uavsearch.parallel import Executor, ScaleOutArgs, Store
from uavsearch.paths import MODELS_DIR, RUNS_DIR
from uavsearch.viz import pyplot, save_figure
from uavsearch.world.settings import parse_settings

from ..data.dataset import ViewSet, concat_views, load_views
from ..data.view_cache import CACHE_DIR, CacheKey, render_lattice_views, world_tag
from ..fusion import DEFAULT_PRIOR
from ..metrics import average_metrics, average_precision, cell_correct
from ..perception import (
    PERCEPTIONS,
    TrainablePerception,
    build_perception,
    cell_pooling,
    images_to_tensor,
    load_perception,
    save_perception,
)
from ..scoring import predict_views
from ..symmetry import square_symmetry
from .runs import copy_checkpoint, seed_everything


@dataclass
class Args(ScaleOutArgs):
    exp_name: str = opt("perception", "the run's name in runs/")
    seed: int = opt(1, "seeds numpy, torch and the batch draw")
    split: str = opt("large", "scene split whose lattice views train (train part) and validate (val part)")
    settings: str = opt("1,2,3", "comma-separated settings whose scenes are used (K = 2, 5, 10 people), or a scene "
                                 "family (wide: every viewpoint of its lattice, both altitudes)")
    train_scenes: int = opt(500, "training scenes per setting (large split: 500 = all, 37,500 views)")
    val_scenes: int = opt(10, "validation scenes per setting, every lattice position")
    data_dir: str | None = opt(None, "where lattice views are rendered and cached (default cache/, shared with the "
                                     "stage-2 view caches; a folder or an fsspec URL)")
    steps: int = opt(5000, "optimiser steps (~4 per second on two idle cores: 21 min)")
    batch_size: int = opt(32, "crops per mini-batch (paper: 32 views)")
    crop: int = opt(128, "square crop side in pixels (a multiple of the net's stride; 0 = whole views)")
    lr: float = opt(2e-3, "Adam learning rate (cosine-decayed to 5% of it); from scratch, not fine-tuning")
    weight_decay: float = opt(1e-5, "Adam L2 (paper's alpha: 1e-6)")
    pos_weight: float = opt(3.0, "loss weight of the occupied class (class imbalance; see module docstring)")
    hard_negative_weight: float = opt(2.0, "extra weight of an empty cell x its false-alarm share so far")
    person_weight: float = opt(1.0, "weight of the dense person loss (0: no person supervision)")
    person_pos_weight: float = opt(20.0, "weight of person pixels in the dense loss")
    augment: bool = opt(True, "random flips / 90-degree rotations of image + label image + person map")
    min_cell_px: float = opt(16.0, "cells with fewer pixels in the crop are not trained on")
    positive_share: float = opt(0.0, "share of each batch drawn from views where an occupied cell shows a person, the "
                                     "crop centred on that cell (sparse people: the wide family's 10 of 900 cells)")
    calibrate: bool = opt(True, "fold the validation-chosen logit shift into the classifier (module docstring)")
    eval_every: int = opt(500, "steps between validations (and resumable checkpoints)")
    threads: int = opt(2, "torch CPU threads")
    resume: str | None = opt(None, "a run directory to continue (its args are kept; --steps may grow)")
    out: str | None = opt(None, "also copy the best checkpoint here (it always stays in the run directory)")
    ship: bool = opt(False, "copy the best checkpoint over the shipped models/perception.pt")
    runs_dir: str = opt(str(RUNS_DIR), "parent of the run directory")
    progress: bool = opt(True, "tqdm bars")
    altitude_feature: bool = opt(False, "the camera altitude as a cell feature (for nets trained across altitudes)")
    init: str | None = opt(None, "start from this perception checkpoint's weights (e.g. the paper's models/perception.pt "
                                 "to fine-tune across altitudes) instead of from scratch")
    net: str = opt("cnn", "perception kind to train (the registry in search/perception.py; cnn: the shipped nets')",
                   choices=sorted(PERCEPTIONS))
    net_args: dict = opt(factory=dict, help="the kind's constructor arguments (default: its own defaults)", cli=False)


def augment_batch(rng: np.random.Generator, *arrays: np.ndarray) -> list[np.ndarray]:
    """Apply one of the square's 8 symmetries (symmetry.square_symmetry) per view to every (V, H, W, ...) array
    alike (image, cell label image, person map)."""
    outs = [x.copy() for x in arrays]
    for b in range(len(arrays[0])):
        k, flip = int(rng.integers(4)), bool(rng.integers(2))
        for x, o in zip(arrays, outs):
            o[b] = square_symmetry(x[b], k + 4 * flip, axes=(0, 1))
    return outs


def random_crops(rng: np.random.Generator, size: int, step: int, *arrays: np.ndarray, centres=None) -> list[np.ndarray]:
    """One random size x size window per view (offsets on the `step` grid, so feature pixels stay aligned),
    the same window in every (V, H, W, ...) array. `centres` (V, 2) image (u, v) in [-1, 1], NaN where
    none: those views' windows are centred there instead (as near as the image edge allows)."""
    V, H, W = arrays[0].shape[:3]
    if size <= 0 or size >= min(H, W):
        return list(arrays)
    r0 = rng.integers(0, (H - size) // step + 1, V) * step
    c0 = rng.integers(0, (W - size) // step + 1, V) * step
    if centres is not None:
        c = np.asarray(centres, dtype=float)
        ok = np.isfinite(c).all(1)
        at = lambda x, n: np.clip(np.round(((x + 1) / 2 * n - size / 2) / step) * step, 0, n - size)  # noqa: E731
        r0 = np.where(ok, at(np.nan_to_num(c[:, 1]), H), r0).astype(int)
        c0 = np.where(ok, at(np.nan_to_num(c[:, 0]), W), c0).astype(int)
    return [np.stack([x[b, r0[b]:r0[b] + size, c0[b]:c0[b] + size] for b in range(V)]) for x in arrays]


# Constructor arguments a checkpoint may differ in from the net it initialises: no weight's shape depends on them,
# or init_from widens the layers that read the new inputs.
INIT_FREE_ARGUMENTS = ("num_cells", "altitude_feature", "dropout")


def init_from(net: TrainablePerception, path) -> None:
    """Copy a checkpoint's weights into `net` (the same kind and architecture). Layers of the same shape are
    copied whole; a layer that reads more inputs than the checkpoint's (the classifier's first layer once the
    altitude feature is added) gets the checkpoint's weights for the inputs both have and zeros for the new
    ones, so the net starts out computing exactly what the checkpoint did."""
    src, _ = load_perception(path)
    mine, theirs = net.arguments(), src.arguments()
    differ = sorted(k for k in {*mine, *theirs} - set(INIT_FREE_ARGUMENTS) if mine.get(k) != theirs.get(k))
    if src.kind != net.kind or differ:
        raise UavsearchError(f"--init {path}: its net ({src.kind}: " + ", ".join(f"{k}={theirs.get(k)}" for k in differ)
                             + f") differs from this run's ({net.kind}: "
                             + ", ".join(f"{k}={mine.get(k)}" for k in differ) + ")")
    own = net.state_dict()
    for k, v in src.state_dict().items():
        if k not in own:
            continue
        if own[k].shape == v.shape:
            own[k] = v.clone()
        elif own[k].dim() == 2 and own[k].shape[0] == v.shape[0] and own[k].shape[1] > v.shape[1]:
            w = torch.zeros_like(own[k])
            w[:, : v.shape[1]] = v
            own[k] = w
        else:
            raise UavsearchError(f"--init {path}: {k} has shape {tuple(v.shape)}, this net {tuple(own[k].shape)}")
    net.load_state_dict(own)


def positive_centres(rng: np.random.Generator, n: int, occupancy: np.ndarray, person_px: np.ndarray, pooling):
    """(V, 2) crop centres: for each of the first `n` views, the image centroid of one occupied cell showing a
    person (drawn at random); NaN elsewhere. None when n is 0."""
    if not n:
        return None
    out = np.full((len(occupancy), 2), np.nan)
    for b in range(n):
        cand = np.flatnonzero((occupancy[b] == 1) & (person_px[b] > 0) & (pooling.pixels[b].numpy() > 0))
        if len(cand):
            out[b] = pooling.centroid[b, int(rng.choice(cand))].numpy()
    return out


class HardNegatives:
    """Per (scene, cell): how often an empty cell was a false alarm in the views trained on so far. Its
    share is the extra loss weight of that cell (persistent false alarms are mined as they happen, no
    extra pass over the data)."""

    def __init__(self, num_scenes: int, num_cells: int):
        self.false_alarms = np.zeros((num_scenes, num_cells), np.float32)
        self.seen = np.zeros((num_scenes, num_cells), np.float32)

    def weights(self, scene_rows: np.ndarray, empty: np.ndarray, scale: float) -> np.ndarray:
        share = self.false_alarms[scene_rows] / np.maximum(self.seen[scene_rows], 1.0)
        return 1.0 + scale * np.where(empty & (self.seen[scene_rows] >= 2), share, 0.0)

    def update(self, scene_rows: np.ndarray, empty: np.ndarray, alarm: np.ndarray) -> None:
        np.add.at(self.seen, scene_rows, empty.astype(np.float32))
        np.add.at(self.false_alarms, scene_rows, (empty & alarm).astype(np.float32))


def batch_loss(net: TrainablePerception, images, labels, occupancy, args: Args, person=None, geometry=None,
               negative_weight=None, altitude_m=None):
    """Stage 1's loss on a batch: weighted cell NLL (+ hard negatives) + the dense person loss.
    Returns (loss, parts dict, log_probs, trained-cell mask)."""
    dev = device_of(net)
    lab = torch.as_tensor(np.asarray(labels), device=dev)
    y = torch.as_tensor(np.asarray(occupancy), dtype=torch.long, device=dev)
    B, N = y.shape
    keys = (torch.arange(B, device=dev)[:, None, None] * (N + 1) + lab.long() + 1).reshape(-1)
    in_crop = torch.bincount(keys, minlength=B * (N + 1)).view(B, N + 1)[:, 1:]
    mask = in_crop >= args.min_cell_px
    out = net.forward_all(images, lab, geometry, altitude_m, cells=mask)
    nll = F.nll_loss(out.log_probs.reshape(-1, 2), y.reshape(-1), reduction="none").view_as(y)
    w = torch.where(y == 1, torch.full_like(nll, args.pos_weight), torch.ones_like(nll))
    if negative_weight is not None:
        w = w * torch.as_tensor(negative_weight, dtype=w.dtype, device=dev)
    w = w * mask
    loss_cells = (nll * w).sum() / w.sum().clamp(min=1.0)
    dense = net.dense_loss(out, person, args.person_pos_weight) if person is not None and args.person_weight > 0 else None
    loss_person = torch.zeros((), device=loss_cells.device) if dense is None else dense
    loss = loss_cells + args.person_weight * loss_person
    return loss, {"cells": float(loss_cells.detach()), "person": float(loss_person.detach())}, out.log_probs, mask


def evaluate(net: TrainablePerception, views: ViewSet, centre_index: int) -> dict[str, float]:
    """Single-view Aacc/AF1 on every view and on the start views only, plus cell-level numbers (average
    precision over the cells in view, false alarms per view, precision and recall at 0.5)."""
    p, _ = predict_views(net, views)
    return view_metrics(p, views.occupancy, views.cells_in_view, views.lattice_index == centre_index)


def view_metrics(p: np.ndarray, y: np.ndarray, seen: np.ndarray, start: np.ndarray) -> dict[str, float]:

    aacc, af1 = average_metrics(p, y)
    s_aacc, s_af1 = average_metrics(p[start], y[start]) if start.any() else (float("nan"), float("nan"))
    pos, pred = (y == 1) & seen, (p > 0.5) & seen
    return {
        "eval/aacc": aacc, "eval/af1": af1, "eval/start_aacc": s_aacc, "eval/start_af1": s_af1,
        "eval/cell_acc": float(cell_correct(p, y)[seen].mean()),
        "eval/recall": float((pos & pred).sum() / max(pos.sum(), 1)),
        "eval/precision": float((pos & pred).sum() / max(pred.sum(), 1)),
        "eval/cell_ap": average_precision(p[seen], y[seen] == 1),
        "eval/false_alarms_per_view": float((pred & (y == 0)).sum() / max(len(p), 1)),
    }


def calibration_shift(net: TrainablePerception, views: ViewSet, shifts=np.linspace(-3.0, 3.0, 61)) -> tuple[float, float]:
    """The logit-margin shift with the best single-view AF1 at 0.5 on these (validation) views: (shift, AF1)."""
    p, _ = predict_views(net, views)
    z = np.log(np.clip(p, 1e-7, 1.0)) - np.log(np.clip(1.0 - p, 1e-7, 1.0))
    seen, y = views.cells_in_view, views.occupancy
    best = max(((average_metrics(np.where(seen, 1.0 / (1.0 + np.exp(-(z + b))), DEFAULT_PRIOR), y)[1], -abs(b), b)
                for b in shifts))
    return float(best[2]), float(best[0])


def shipped_path(settings: str) -> Path:
    """Where --ship puts the net: models/perception.pt for the paper's settings, models/perception_<family>.pt
    for a scene family's (the paper's stage-2 models read the features of the paper's net, so a net of
    another setting never replaces it)."""
    fams = [s for s in parse_settings(settings, "--settings", families=True) if isinstance(s, str)]
    return MODELS_DIR / (f"perception_{fams[0]}.pt" if fams else "perception.pt")


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
    """Render (or reuse) the lattice views of the chosen scenes; returns (train, val, start-view index).
    The renders are the stage-2 view caches' own (view_cache.render_lattice_views): made once for both."""
    store, executor = Store(args.data_dir if args.data_dir is not None else CACHE_DIR), Executor.from_args(args)
    t0 = time.perf_counter()
    sets = {}
    for part, n in (("train", args.train_scenes), ("val", args.val_scenes)):
        loaded = []
        for setting in parse_settings(args.settings, "--settings", families=True):
            key = CacheKey(setting, args.split, part)
            scenes = key.scenes()
            if not 1 <= n <= len(scenes):
                raise UavsearchError(f"--{part}-scenes {n}: the {args.split} split has {len(scenes)} {part} scenes per "
                                     f"setting; give --{part}-scenes 1..{len(scenes)} (or another --split)")
            world = world_tag(key.search_config, key.family)
            root = render_lattice_views(key, scenes[:n], root=store.path(f"lattice_views/{world}/{key.name}"),
                                        progress=args.progress, executor=executor)
            loaded.append(load_views(root, scenes[:n], person_frac=part == "train"))
        sets[part] = loaded[0] if len(loaded) == 1 else concat_views(loaded)
        del loaded
    print(f"data: {len(sets['train'])} training views, {len(sets['val'])} validation views of the {args.split} "
          f"split, settings {args.settings} ({time.perf_counter() - t0:.0f} s to render / load from {store.url})")
    return sets["train"], sets["val"], key.search_config.lattice.start_index


def train(args: Args, views: tuple[ViewSet, ViewSet, int] | None = None) -> dict:
    """Run stage 1; returns the final report (validation metrics of the best checkpoint, times, paths).
    `views` (train, val, start-view index) replaces the split's rendered views (prepare_data), e.g. a few
    views a test makes."""
    if args.batch_size < 1 or args.steps < 1:
        raise UavsearchError("batch_size and steps must be positive")
    torch.set_num_threads(max(1, args.threads))
    device = resolve_device(args.device)
    # the kind's constructor arguments; num_cells follows the views trained on (below), and the altitude is
    # asked of a kind only when wanted, so a kind that cannot read it still trains without
    net_args = {**args.net_args, **({"altitude_feature": True} if args.altitude_feature else {})}
    stride = build_perception(args.net, **net_args).stride  # before seeding: checks the arguments early
    if args.crop and args.crop % stride:
        raise UavsearchError(f"--crop {args.crop} must be a multiple of the net's stride {stride}")
    rng = seed_everything(args.seed)
    if args.resume:
        run_dir = Path(args.resume)
        if not (run_dir / "last.pt").is_file():
            raise UavsearchError(f"{run_dir} has no last.pt to resume from")
    else:
        run_dir = Path(args.runs_dir) / f"{args.exp_name}__{args.seed}__{int(time.time())}"
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / "args.json").write_text(json.dumps(asdict(args), indent=1))
    t_start = time.perf_counter()
    train_set, val_set, centre = prepare_data(args) if views is None else views
    t_data = time.perf_counter() - t_start
    scene_row = np.unique(train_set.scene_seed, return_inverse=True)[1]
    shows = np.flatnonzero(((train_set.occupancy == 1) & (train_set.person_px > 0)).any(1))  # views showing a person
    n_pos = int(round(args.positive_share * args.batch_size)) if len(shows) else 0
    num_cells = int(train_set.occupancy.shape[1])  # the grid of the views trained on
    hard = HardNegatives(int(scene_row.max()) + 1, num_cells)

    net = build_perception(args.net, **net_args, num_cells=num_cells)
    if args.init:
        init_from(net, args.init)
    net.to(device)
    opt = torch.optim.Adam(net.parameters(), lr=args.lr, weight_decay=args.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: 0.05 + 0.95 * 0.5 * (1 + np.cos(np.pi * min(s, args.steps) / args.steps)))
    rows: list[dict] = []
    best: dict = {"eval/cell_ap": -1.0}
    ckpt, last = run_dir / "perception.pt", run_dir / "last.pt"
    csv_path = run_dir / "metrics.csv"
    fields = ["step", "time_s", "losses/train_loss", "losses/cells", "losses/person", "charts/lr",
              "charts/views_per_s", "eval/aacc", "eval/af1", "eval/start_aacc", "eval/start_af1", "eval/cell_acc",
              "eval/recall", "eval/precision", "eval/cell_ap", "eval/false_alarms_per_view"]
    first, t_before = 1, 0.0
    if args.resume:
        st = torch.load(last, map_location=device, weights_only=False)
        net.load_state_dict(st["net"]), opt.load_state_dict(st["opt"]), sched.load_state_dict(st["sched"])
        rng.bit_generator.state = st["rng"]
        torch.set_rng_state(st["torch_rng"].cpu())
        if device.type == "cuda" and st.get("cuda_rng") is not None:  # dropout's masks on the GPU
            torch.cuda.set_rng_state(st["cuda_rng"].cpu(), device)
        hard.false_alarms, hard.seen = st["hard"]
        rows, best, first, t_before = st["rows"], st["best"], st["step"] + 1, st["time_s"]
        print(f"resuming {run_dir} at step {first}")
    with open(csv_path, "w", newline="") as fh:  # rewritten whole: a resumed run's file has no gap or repeat
        w = csv.DictWriter(fh, fields)
        w.writeheader()
        w.writerows(rows)

    def log(row):
        rows.append(row)
        with open(csv_path, "a", newline="") as fh:
            csv.DictWriter(fh, fields).writerow(row)

    t_train = time.perf_counter() - t_before
    bar = tqdm(range(first, args.steps + 1), desc="train perception", unit="step", disable=not args.progress,
               initial=first - 1, total=args.steps)
    for step in bar:
        net.train()
        rows_b = rng.integers(0, len(train_set), args.batch_size)
        if n_pos:
            rows_b[:n_pos] = rng.choice(shows, n_pos)
        imgs, labs, pers = train_set.images[rows_b], train_set.label_images(rows_b), train_set.person_frac[rows_b]
        if args.augment:
            imgs, labs, pers = augment_batch(rng, imgs, labs, pers)
        pooling = cell_pooling(torch.as_tensor(np.ascontiguousarray(labs)), net.stride, net.num_cells)
        y = train_set.occupancy[rows_b]
        imgs, labs, pers = random_crops(rng, args.crop, net.stride, imgs, labs, pers,
                                        centres=positive_centres(rng, n_pos, y, train_set.person_px[rows_b], pooling))
        sr = scene_row[rows_b]
        neg_w = hard.weights(sr, y == 0, args.hard_negative_weight)
        loss, parts, log_probs, mask = batch_loss(
            net, images_to_tensor(np.ascontiguousarray(imgs)).to(device), np.ascontiguousarray(labs), y, args,
            person=np.ascontiguousarray(pers), geometry=(pooling.pixels.to(device), pooling.centroid.to(device)),
            negative_weight=neg_w,
            altitude_m=train_set.position_enu[rows_b, 2])
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        m = mask.cpu().numpy()
        hard.update(sr, (y == 0) & m, (log_probs[..., 1].detach().exp().cpu().numpy() > 0.5) & m)
        elapsed = time.perf_counter() - t_train
        row = {"step": step, "time_s": round(elapsed, 2), "losses/train_loss": loss.item(),
               "losses/cells": parts["cells"], "losses/person": parts["person"], "charts/lr": sched.get_last_lr()[0],
               "charts/views_per_s": (step - first + 1) * args.batch_size / max(elapsed - t_before, 1e-9)}
        if step % args.eval_every == 0 or step == args.steps:
            row.update(evaluate(net, val_set, centre))
            bar.set_postfix(ap=f"{row['eval/cell_ap']:.3f}", af1=f"{row['eval/af1']:.3f}",
                            fa=f"{row['eval/false_alarms_per_view']:.2f}")
            if row["eval/cell_ap"] > best["eval/cell_ap"]:
                best = {**row}
                save_perception(net, ckpt, extra={"args": asdict(args), "step": step,
                                                  "val": {k: v for k, v in row.items() if k.startswith("eval/")}})
            log(row)
            torch.save({"net": cpu_state(net), "opt": opt.state_dict(), "sched": sched.state_dict(),
                        "rng": rng.bit_generator.state, "torch_rng": torch.get_rng_state(),
                        "cuda_rng": torch.cuda.get_rng_state(device) if device.type == "cuda" else None,
                        "hard": (hard.false_alarms, hard.seen), "rows": rows, "best": best, "step": step,
                        "time_s": time.perf_counter() - t_train}, last)
        else:
            log(row)
    bar.close()
    train_s = time.perf_counter() - t_train
    net, extra = load_perception(ckpt, device)
    shift, cal_af1 = (calibration_shift(net, val_set) if args.calibrate else (0.0, best["eval/af1"]))
    if shift:
        net.shift_logit_margin(shift)
        val = {**extra["val"], **evaluate(net, val_set, centre)}
        save_perception(net, ckpt, extra={**extra, "calibration_shift": shift, "val": val,
                                          "val_before_calibration": extra["val"]})
        best.update(val)
    _plot_curves(rows, run_dir / "learning_curve.png")
    out = copy_checkpoint(ckpt, args.out, args.ship, shipped_path(args.settings))
    report = {
        "best_step": best["step"], **{k: best[k] for k in best if k.startswith("eval/")},
        "calibration_shift": shift, "train_views": len(train_set), "val_views": len(val_set), "data_s": t_data,
        "train_s": train_s, "run_dir": str(run_dir), "checkpoint": str(out or ckpt),
    }
    (run_dir / "report.json").write_text(json.dumps(report, indent=1))
    _print_report(report)
    return report


def _print_report(r: dict) -> None:
    print("\nstage 1 perception: validation of the best checkpoint (single view, threshold 0.5)")
    print(f"| {'metric':<22} | {'value':>10} |\n|{'-' * 24}|{'-' * 12}|")
    for k in ("eval/aacc", "eval/af1", "eval/start_aacc", "eval/start_af1", "eval/cell_acc", "eval/recall",
              "eval/precision", "eval/cell_ap", "eval/false_alarms_per_view", "calibration_shift"):
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
