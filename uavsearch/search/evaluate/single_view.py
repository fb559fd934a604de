"""Single-view evaluation (paper Sec. VII-C): Table I (Aacc / AF1 vs density) and Fig. 4 (accuracy vs cell size).

Test scenes: the density set of scenes/settings.yaml (seeds disjoint from every training and test split,
K = 1..12, `scenes_per_pair` per pair of densities; the paper uses 80). Table I scores the start view
(70 m above the centre) of each scene, as the paper does. Fig. 4 needs cells of many pixel sizes; with a
nadir camera over flat ground every fully visible 5 m cell covers the same ~196 px, and only cells cut
by the image border are smaller, so Fig. 4 pools every in-view cell of every rendered view (the start
view and `views_per_scene - 1` random lattice positions per scene).

Outputs in --out: table1.md, table1.csv, fig4.png (left: cell accuracy vs pixel area, with the number of
cells per bin, the paper's Fig. 4; middle: cell accuracy vs the cell's horizontal distance from the
camera, which is what varies between our views; right: accuracy on occupied cells vs how many pixels of
a person are visible in them, which is what limits recall: people are a few-pixel blobs at 70 m and
trees and buildings hide some of them).
"""

from __future__ import annotations

import csv
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from uavsearch.cli_args import add_dataclass_args, dataclass_from_args, opt
from uavsearch.devices import resolve_device
from uavsearch.errors import UavsearchError
from uavsearch.parallel import Executor, ScaleOutArgs, Store
from uavsearch.paths import MODELS_DIR, display_path
from uavsearch.viz import pyplot, save_figure
from uavsearch.world.settings import density_scenes

from ..config import SearchConfig
from ..data.dataset import DATA_DIR, ViewSetSpec, generate_views, load_views
from ..metrics import average_metrics, cell_correct, rate_by_bin
from ..perception import load_perception
from ..scoring import predict_views

PAPER_TABLE1 = {  # pair -> (Aacc, AF1), paper Table I
    (1, 2): (0.896, 0.201), (3, 4): (0.892, 0.356), (5, 6): (0.883, 0.445),
    (7, 8): (0.872, 0.494), (9, 10): (0.870, 0.562), (11, 12): (0.873, 0.614),
}
AREA_BINS = np.array([0, 20, 40, 60, 80, 100, 120, 140, 160, 180, 200])
PERSON_PX_BINS = np.array([0, 1, 2, 3, 5, 9, 17, 10_000])  # [lo, hi) visible person pixels


@dataclass
class EvalArgs(ScaleOutArgs):
    out: str = opt("runs/single_view", "directory for table1.md/.csv and fig4.png")
    checkpoint: str = opt(str(MODELS_DIR / "perception.pt"), "perception checkpoint")
    scenes_per_pair: int = opt(80, "test scenes per pair of densities (paper: 80)")
    views_per_scene: int = opt(3, "the start view + random lattice positions (for Fig. 4)")
    seed: int = opt(0, "draw of the extra lattice positions")
    data_dir: str = opt(str(DATA_DIR), "cache of rendered view sets (a folder or an fsspec URL)")
    threads: int = opt(2, "torch CPU threads")
    progress: bool = opt(True, "progress bars")


def density_test_scenes(scenes_per_pair: int) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """The first `scenes_per_pair` density-set scenes of each pair; returns (scenes, pair of each)."""
    allp = density_scenes()
    by_pair: dict[tuple[int, int], list] = {}
    for s, k in allp:
        pair = next(p for p in PAPER_TABLE1 if k in p)
        by_pair.setdefault(pair, []).append((s, k))
    if scenes_per_pair < 1 or scenes_per_pair > min(len(v) for v in by_pair.values()):
        raise UavsearchError(f"scenes per pair must be in 1..{min(len(v) for v in by_pair.values())}")
    scenes, pairs = [], []
    for pair in PAPER_TABLE1:
        chosen = by_pair[pair][:scenes_per_pair]
        scenes += chosen
        pairs += [pair] * len(chosen)
    return scenes, pairs


def evaluate_single_view(args: EvalArgs) -> dict:


    torch.set_num_threads(max(1, args.threads))
    net, extra = load_perception(args.checkpoint, resolve_device(getattr(args, "device", "auto")))
    scenes, _ = density_test_scenes(args.scenes_per_pair)
    spec = ViewSetSpec(f"density_v{args.views_per_scene}_s{args.seed}", tuple(scenes),
                       views_per_scene=args.views_per_scene, seed=args.seed)
    t0 = time.perf_counter()
    root = generate_views(spec, Store(args.data_dir).path(spec.name), progress=args.progress,
                          executor=Executor.from_args(args))
    views = load_views(root, scenes)
    t_data = time.perf_counter() - t0
    t0 = time.perf_counter()
    p, pixels = predict_views(net, views, progress=args.progress)
    t_pred = time.perf_counter() - t0
    centre = len(SearchConfig().lattice.positions_enu) // 2
    start = views.lattice_index == centre
    y = views.occupancy

    rows = []
    for pair, (paper_acc, paper_f1) in PAPER_TABLE1.items():
        sel = start & np.isin(views.occupied_cells, pair)
        aacc, af1 = average_metrics(p[sel], y[sel])
        rows.append({"occupied_cells": f"{pair[0]}-{pair[1]}", "scenes": int(sel.sum()), "Aacc": aacc, "AF1": af1,
                     "paper_Aacc": paper_acc, "paper_AF1": paper_f1})
    all_acc, all_f1 = average_metrics(p[start], y[start])

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "table1.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, list(rows[0]))
        w.writeheader()
        for r in rows:
            w.writerow({k: (f"{v:.3f}" if isinstance(v, float) else v) for k, v in r.items()})
    lines = [
        "# Table I: single-view performance vs pedestrian density (start view, 70 m)",
        "",
        f"checkpoint `{display_path(args.checkpoint)}`; {int(start.sum())} test scenes of the density set "
        f"({args.scenes_per_pair} per row, seed {args.seed} for the extra Fig. 4 views); threshold 0.5 (Eq. 16-19).",
        *_validation_line(extra),
        "",
        "| occupied cells | scenes | Aacc | AF1 | paper Aacc | paper AF1 |",
        "|---|---|---|---|---|---|",
    ]
    lines += [f"| {r['occupied_cells']} | {r['scenes']} | {r['Aacc']:.3f} | {r['AF1']:.3f} | {r['paper_Aacc']:.3f} | "
              f"{r['paper_AF1']:.3f} |" for r in rows]
    lines += [f"| all | {int(start.sum())} | {all_acc:.3f} | {all_f1:.3f} | | |", ""]
    (out / "table1.md").write_text("\n".join(lines))

    seen = views.cells_in_view & (pixels > 0)
    correct = cell_correct(p, y)
    grid = SearchConfig().grid
    dist = np.linalg.norm(views.position_enu[:, None, :2] - grid.centers_enu[None, :, :2], axis=-1)
    fig = _plot_fig4(views.cell_area_px[seen], correct[seen], dist[seen], views.person_px[seen & (y == 1)],
                     correct[seen & (y == 1)], out / "fig4.png")
    print("\n".join(lines))
    print(f"wrote {out / 'table1.md'}, {out / 'table1.csv'}, {fig}")
    print(f"({len(views)} views: {t_data:.0f} s to render/load, {t_pred:.1f} s to predict)")
    return {"rows": rows, "all": (all_acc, all_f1), "views": len(views), "data_s": t_data, "predict_s": t_pred}


def _validation_line(extra: dict) -> list[str]:
    """The checkpoint's own validation precision / recall (stage 1 training), which README quotes."""
    val = (extra or {}).get("val") or {}
    if "eval/precision" not in val:
        return []
    return ["", f"Stage 1 validation at step {extra.get('step')}: precision {val['eval/precision']:.3f}, "
                f"recall {val['eval/recall']:.3f}, AF1 {val['eval/af1']:.3f}."]


def _plot_fig4(area, correct, dist, person_px, correct_pos, path: Path) -> Path:
    return save_figure(fig4_figure(area, correct, dist, person_px, correct_pos), path)


def fig4_figure(area, correct, dist, person_px, correct_pos):
    fig, (a, c, b) = pyplot().subplots(1, 3, figsize=(15, 4), layout="constrained")
    acc, n = rate_by_bin(area, correct, AREA_BINS)
    centres = (AREA_BINS[:-1] + AREA_BINS[1:]) / 2
    a2 = a.twinx()
    a2.bar(centres, n, width=16, color="0.85", zorder=0)
    a2.set_ylabel("cells in bin", color="0.5")
    a2.set_yscale("log")
    a.set_zorder(a2.get_zorder() + 1)
    a.patch.set_visible(False)
    ok = ~np.isnan(acc)
    a.plot(centres[ok], acc[ok], "o-", color="C0")
    a.set_xlabel("pixel area of the cell in the image, F_size (px)")
    a.set_ylabel("single-view cell accuracy")
    a.set_ylim(0.5, 1.0)
    a.set_title("Fig. 4: accuracy vs mapped cell size")
    a.grid(alpha=0.3)
    # Nadir camera over flat ground: F_size is ~196 px for every whole cell, so also show what does vary
    # between views: how far off-nadir the cell is (parallax, occlusion by buildings and trees).
    edges = np.arange(0.0, 50.0 + 1e-9, 5.0)
    acc3, n3 = rate_by_bin(dist, correct, edges)
    mids = (edges[:-1] + edges[1:]) / 2
    ok3 = ~np.isnan(acc3)
    c.plot(mids[ok3], acc3[ok3], "o-", color="C2")
    for x, v, k in zip(mids[ok3], acc3[ok3], n3[ok3]):
        c.text(x, v + 0.01, f"{k}", ha="center", fontsize=7, color="0.4")
    c.set_xlabel("horizontal distance camera -> cell centre (m)")
    c.set_ylabel("single-view cell accuracy")
    c.set_ylim(0.5, 1.0)
    c.set_title("accuracy vs off-nadir distance (n per bin)")
    c.grid(alpha=0.3)
    acc2, n2 = rate_by_bin(person_px, correct_pos, PERSON_PX_BINS)
    labels = ["0", "1", "2", "3-4", "5-8", "9-16", "17+"]
    b.bar(range(len(labels)), np.nan_to_num(acc2), color="C1")
    for i, (v, k) in enumerate(zip(acc2, n2)):
        b.text(i, (0 if np.isnan(v) else v) + 0.02, f"n={k}", ha="center", fontsize=8)
    b.set_xticks(range(len(labels)), labels)
    b.set_ylim(0, 1.1)
    b.set_xlabel("visible person pixels in the cell")
    b.set_ylabel("accuracy on occupied cells (recall)")
    b.set_title("recall vs visible person pixels")
    b.grid(alpha=0.3, axis="y")
    return fig


# --------------------------------------------------------------------------------------------------
# CLI hook: `uavsearch eval single-view ...` (wired in uavsearch/cli.py)


def add_eval_single_view_parser(subparsers) -> None:
    p = subparsers.add_parser("single-view", help="Table I and Fig. 4: single-view perception on the density set")
    add_dataclass_args(p, EvalArgs)
    p.set_defaults(func=cmd_eval_single_view)


def cmd_eval_single_view(args) -> int:
    evaluate_single_view(dataclass_from_args(EvalArgs, args))
    return 0
