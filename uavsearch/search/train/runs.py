"""What every trainer shares: seeding, the run directory, the view caches it trains on, and copying the
chosen checkpoint out (never over models/ unless asked)."""

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

from uavsearch.cli_args import opt
from uavsearch.devices import make_generator, to_device
from uavsearch.errors import UavsearchError
from uavsearch.parallel import Executor, ScaleOutArgs
from uavsearch.paths import RUNS_DIR

from ..data.view_cache import get_view_cache
from ..perception import load_perception
from ..search_loop import step_rewards


@dataclass
class RunArgs(ScaleOutArgs):
    """How a stage-2 training command runs and reports (train_policy, train_reactive)."""

    threads: int = opt(1, "torch CPU threads")
    cache_dir: str | None = opt(None, "view cache root (default cache/)")
    runs_dir: str = opt(str(RUNS_DIR), "parent of the run directory")
    progress: bool = opt(True, "progress bar")
    plot: bool = opt(True, "write learning_curve.png at the end")


def start_run(args: RunArgs, name: str, seed: int) -> Path:
    """runs/<name>__<seed>__<unix time>/, new, with args.json written first."""
    stamp = int(time.time())
    run_dir = Path(args.runs_dir) / f"{name}__{seed}__{stamp}"
    while run_dir.exists():  # two runs started within the same second
        stamp += 1
        run_dir = Path(args.runs_dir) / f"{name}__{seed}__{stamp}"
    run_dir.mkdir(parents=True)
    (run_dir / "args.json").write_text(json.dumps(asdict(args), indent=1))
    return run_dir


class MetricsCsv:
    """A run's metrics.csv: one row per iteration, the header from the first row, flushed row by row (a run cut
    short keeps what it logged). `rows` keeps them for the plots."""

    def __init__(self, path: Path):
        self.file = Path(path).open("w", newline="")
        self.writer: csv.DictWriter | None = None
        self.rows: list[dict] = []

    def log(self, row: dict) -> None:
        self.rows.append(row)
        if self.writer is None:
            self.writer = csv.DictWriter(self.file, fieldnames=list(row))
            self.writer.writeheader()
        self.writer.writerow(row)
        self.file.flush()

    def close(self) -> None:
        self.file.close()


def fit_minibatches(optimizer, n: int, epochs: int, batch_size: int, generator, loss_of) -> tuple[float, float]:
    """`epochs` passes over n examples in shuffled minibatches; loss_of(index tensor) -> (loss, agreement).
    Returns the mean loss and agreement of the last 10 minibatches (what a DAgger iteration logs)."""
    losses, agree = [], []
    for _ in range(epochs):
        perm = torch.randperm(n, generator=generator, device=generator.device)
        for j in range(0, n, batch_size):
            loss, acc = loss_of(perm[j:j + batch_size])
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            losses.append(float(loss.detach()))
            agree.append(float(acc))
    return float(np.mean(losses[-10:])), float(np.mean(agree[-10:]))


def returns_to_go(maps, labels, revisit, **reward) -> torch.Tensor:
    """(B, T-1) each move's return to go: the rewards (search_loop.step_rewards with `reward`'s weights) of the
    views from the one it lands on (move t lands on view t+1) to the last, undiscounted."""
    r = step_rewards(maps, labels, revisit, **reward)[:, 1:]
    return r.flip(1).cumsum(1).flip(1)


def start_training(threads: int, seed: int, device="cpu") -> torch.Generator:
    """Torch's CPU threads, every seed (seed_everything), and the generator a run draws its episodes from, on the
    run's device (devices.make_generator)."""
    torch.set_num_threads(int(threads))
    seed_everything(seed)
    return make_generator(seed, device)


def imitation_panel(ax, rows: list[dict]) -> None:
    """A learning curve's DAgger panel: imitation loss and agreement with the teacher, where logged."""
    il = [r for r in rows if r["losses/imitation"] is not None]
    ax.plot([r["iteration"] for r in il], [r["losses/imitation"] for r in il], lw=0.8, label="imitation loss")
    ax.plot([r["iteration"] for r in il], [r["charts/teacher_agreement"] for r in il], lw=0.8,
            label="agrees with the teacher")
    ax.set_title("imitation of the teacher")
    ax.legend(fontsize=8)


def finish_curves(fig, axes, title: str, path: Path, xlabel: str = "iteration (DAgger, then REINFORCE)") -> None:
    """Label and grid every panel of a learning curve, title it, and save it (viz.save_figure)."""
    from uavsearch.viz import save_figure

    for a in axes:
        a.set_xlabel(xlabel)
        a.grid(alpha=0.3)
    fig.suptitle(title)
    save_figure(fig, path)


def load_caches(args, device="cpu"):
    """The (train, val) view caches of args.setting / args.split under the frozen args.perception, on `device`."""

    net, _ = load_perception(args.perception)
    kw = dict(cache_dir=args.cache_dir, progress=args.progress, executor=Executor.from_args(args))
    return tuple(to_device(get_view_cache(net, args.setting, args.split, part, **kw), device) for part in ("train", "val"))


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


__all__ = ["MetricsCsv", "RunArgs", "finish_curves", "fit_minibatches", "imitation_panel", "start_training", "copy_checkpoint", "load_caches", "returns_to_go", "seed_everything",
           "start_run"]
