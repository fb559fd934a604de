"""Stage-1 perception against its targets, on the TEST view caches: what the search gets to fuse.

Every lattice position of every test scene of each setting (view_cache.get_view_cache: renders and runs
perception only where the cache is missing). A cell counts where the view measured it (the cache's
`valid`); its score is p(occupied) = exp(log_probs[..., 1]); the threshold is 0.5 as in the metrics.

    measure                               target     why
    cell average precision                >= 0.75    ranks occupied cells above empty ones, whatever the threshold
    false alarms per view                 <= 1.0     empty valid cells with p > 0.5; each one costs fused precision
    recall at 4-7 visible person pixels   >= 0.80    a person a few pixels wide at 70 m must still be found
    persistent false-alarm cells / scene  <= 0.3     an empty cell that fires in more than half of the views
                                                     measuring it: fusion cannot vote it away

Also precision / recall at 0.5 and recall per visible-pixel bin (0 = hidden, 1-3, 4-7, 8-15, 16+; needs the
cache's person_px, skipped with a note for an older cache). Outputs in --out: perception_targets.md,
perception_targets.csv, perception_targets.png (recall vs visible person pixels; false alarms per view).

A scene family (`--setting wide`) is judged per altitude of its lattice, with the targets of a net that
reads 900 cells from two heights (a view sees 80-260 of them, so false alarms count per cell-view):

    at 40 m   recall of occupied cells showing >= 8 visible person pixels   >= 0.75
    at 40 m   false alarms per cell-view                                     <= 0.015
    at 70 m   recall per visible-pixel bin no worse than the reference net's (--reference, default the
              paper's models/perception.pt, trained at 70 m only) on the same views
"""

from __future__ import annotations

import csv
import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from uavsearch.cli_args import add_dataclass_args, dataclass_from_args, opt
from uavsearch.errors import UavsearchError
from uavsearch.parallel import Executor, ScaleOutArgs
from uavsearch.paths import display_path
from uavsearch.viz import pyplot, save_figure
from uavsearch.world.settings import parse_settings, setting_params

from ..data.view_cache import PARTS, get_view_cache
from ..metrics import average_precision, rate_by_bin
from ..perception import load_perception, shipped_perception

THRESHOLD = 0.5
PX_BINS: tuple[tuple[int, int | None], ...] = ((0, 0), (1, 3), (4, 7), (8, 15), (16, None))  # [lo, hi] pixels
# (key, what, ">=" or "<=", target)
TARGETS: tuple[tuple[str, str, str, float], ...] = (
    ("cell_ap", "cell average precision", ">=", 0.75),
    ("fa_per_view", "false alarms per view", "<=", 1.0),
    ("recall_4_7px", "recall at 4-7 visible person pixels", ">=", 0.80),
    ("persistent_fa_per_scene", "persistent false-alarm cells per scene", "<=", 0.3),
)


FAMILY_TARGETS: tuple[tuple[str, str, str, float], ...] = (
    ("recall_8px", "recall at >= 8 visible person pixels", ">=", 0.75),
    ("fa_per_cell_view", "false alarms per cell-view", "<=", 0.015),
)
LOW_M, HIGH_M = 40.0, 70.0  # the altitudes the family targets name


def bin_name(lo: int, hi: int | None) -> str:
    return f"{lo}+" if hi is None else (f"{lo}" if lo == hi else f"{lo}-{hi}")


def perception_stats(caches, threshold: float = THRESHOLD) -> dict:
    """The measures of the module docstring over the scenes of one or more ViewCaches (pooled)."""
    caches = list(caches)
    p = np.concatenate([c.log_probs[..., 1].exp().numpy() for c in caches])  # (S, P, N)
    valid = np.concatenate([c.valid.numpy() for c in caches]).astype(bool)
    occ = np.concatenate([c.occupancy.numpy() for c in caches]).astype(bool)  # (S, N)
    y = np.broadcast_to(occ[:, None, :], p.shape)
    fires = p > threshold
    fa_cell = fires & ~y & valid  # (S, P, N)
    fa_view = fa_cell.sum(-1).ravel()  # per view
    tp, fn = int((fires & y & valid).sum()), int((~fires & y & valid).sum())
    fp = int(fa_view.sum())
    n_valid, n_fa = valid.sum(1), fa_cell.sum(1)  # (S, N) views measuring each cell, of them firing on it
    persistent = (~occ & (n_valid > 0) & (2 * n_fa > n_valid)).sum(-1)  # (S,)
    stats = {"scenes": int(p.shape[0]), "views": int(p.shape[0] * p.shape[1]), "valid_cells": int(valid.sum()),
             "occupied_valid_cells": tp + fn, "cell_ap": average_precision(p[valid], y[valid]),
             "fa_per_view": float(fa_view.mean()), "fa_per_cell_view": fp / max(int((valid & ~y).sum()), 1),
             "precision": tp / (tp + fp) if tp + fp else float("nan"),
             "recall": tp / (tp + fn) if tp + fn else float("nan"),
             "persistent_fa_per_scene": float(persistent.mean()), "fa_hist": np.bincount(fa_view),
             "recall_by_px": None}
    if all(c.person_px is not None for c in caches):
        px = np.concatenate([c.person_px.numpy() for c in caches])
        seen = y & valid
        edges = [lo for lo, _ in PX_BINS] + [max(int(px.max()), PX_BINS[-1][0]) + 1]  # [lo, next lo): last open-ended
        rates, counts = rate_by_bin(px[seen], fires[seen], edges)
        by = {bin_name(lo, hi): (float(r), int(n)) for (lo, hi), r, n in zip(PX_BINS, rates, counts)}
        stats["recall_by_px"] = by
        stats["recall_4_7px"] = by["4-7"][0]
        big = seen & (px >= 8)
        stats["recall_8px"] = float(fires[big].mean()) if big.any() else float("nan")
    else:
        stats["recall_4_7px"] = stats["recall_8px"] = float("nan")
    return stats


def at_altitude(cache, altitude_m: float):
    """The cache's views from one altitude of its lattice (a ViewCache over those positions only)."""
    pos = np.flatnonzero(np.isclose(cache.config.lattice.positions_enu[:, 2], altitude_m))
    if not len(pos):
        raise UavsearchError(f"the lattice has no viewpoint at {altitude_m:g} m")
    t = torch.as_tensor(pos)
    return cache._replace(log_probs=cache.log_probs[:, t], cell_features=cache.cell_features[:, t],
                          global_feature=cache.global_feature[:, t], cell_area_px=cache.cell_area_px[:, t],
                          valid=cache.valid[:, t], person_px=None if cache.person_px is None else cache.person_px[:, t])


def meets(value: float, op: str, target: float) -> bool | None:
    if not np.isfinite(value):
        return None
    return value >= target if op == ">=" else value <= target


# --------------------------------------------------------------------------------------------------


@dataclass
class EvalArgs(ScaleOutArgs):
    out: str = opt("runs/perception_targets", "output folder: perception_targets.md/.csv/.png", required=True)
    setting: str = opt("all", "paper setting 1 | 2 | 3 | all (pooled in the last column), or a scene family (wide: "
                              "judged per altitude)")
    split: str | None = opt(None, "scene split (paper: 10 test scenes per setting; large: 100); default: paper for "
                                  "1-3, the family's own (large) for a family")
    part: str = opt("test", "which part of the split", choices=PARTS)
    perception: str | None = opt(None, "perception checkpoint (default models/perception.pt; a family's own "
                                       "models/perception_<family>.pt)")
    reference: str | None = opt(None, "a family's reference net at 70 m (default models/perception.pt)")
    scenes: int | None = opt(None, "only the part's first N scenes (a family; default all)")
    cache_dir: str | None = opt(None, "view caches: a folder or an fsspec URL (default cache/)")
    progress: bool = opt(True, "progress bars")


def _fmt(x: float, digits: int = 3) -> str:
    return "—" if not np.isfinite(x) else f"{x:.{digits}f}"


def write_report(stats: dict[str, dict], out: Path, meta: dict) -> tuple[Path, Path]:
    """perception_targets.md / .csv from {column name: perception_stats}."""
    out.mkdir(parents=True, exist_ok=True)
    cols = list(stats)
    pooled = stats[cols[-1]]
    rows = []
    for key, what, op, target in TARGETS:
        rows.append({"measure": what, "key": key, "target": f"{op} {target:g}",
                     **{c: stats[c][key] for c in cols}, "met": meets(pooled[key], op, target)})
    for key, what in (("precision", "precision at 0.5"), ("recall", "recall at 0.5")):
        rows.append({"measure": what, "key": key, "target": "", **{c: stats[c][key] for c in cols}, "met": None})
    if pooled["recall_by_px"] is not None:
        for name in pooled["recall_by_px"]:
            rows.append({"measure": f"recall at {name} visible person pixels (n)", "key": f"recall_{name}px",
                         "target": "", **{c: stats[c]["recall_by_px"][name][0] for c in cols},
                         "met": None, "n": pooled["recall_by_px"][name][1]})
    csv_path = out / "perception_targets.csv"
    with csv_path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["measure", "key", "target", *cols, "met", "n"])
        w.writeheader()
        w.writerows(rows)
    lines = [f"# Stage-1 perception targets: {meta['split']} split, {meta['part']} scenes, every lattice view", "",
             f"perception `{meta['perception']}` (tag {meta['tag']}); "
             + "; ".join(f"{c}: {stats[c]['scenes']} scenes, {stats[c]['views']} views, {stats[c]['valid_cells']} "
                         f"valid cells ({stats[c]['occupied_valid_cells']} occupied)" for c in cols)
             + f"; threshold {THRESHOLD}.", "",
             f"Met: judged on the {'pooled ' if len(cols) > 1 else ''}column {cols[-1]!r}.", "",
             "| measure | target | " + " | ".join(cols) + " | met |", "|---|---|" + "---|" * (len(cols) + 1)]
    for r in rows:
        met = {True: "yes", False: "**no**", None: ""}[r["met"]]
        name = r["measure"].replace(" (n)", f" (n = {r['n']} in {cols[-1]})") if "n" in r else r["measure"]
        lines.append(f"| {name} | {r['target']} | " + " | ".join(_fmt(r[c]) for c in cols) + f" | {met} |")
    if pooled["recall_by_px"] is None:
        lines += ["", "Recall by visible person pixels skipped: a view cache was written before it kept person_px "
                      "(delete its .npz under cache/search_views/ and run again to rebuild it)."]
    lines += ["", "Persistent false-alarm cell: an empty cell with p > 0.5 in more than half of the views that "
                  "measure it.", f"{meta['seconds']:.0f} s"]
    md_path = out / "perception_targets.md"
    md_path.write_text("\n".join(lines) + "\n")
    return md_path, csv_path


def _recall_panel(a, stats: dict[str, dict], extra=None) -> None:
    """Recall vs visible person pixels, one line per column (a reference net's dashed); `extra(axes, bin
    names)` draws what a report adds (its target) before the legend."""
    names = [bin_name(lo, hi) for lo, hi in PX_BINS]
    for c, st in stats.items():
        if st["recall_by_px"] is not None:
            a.plot(range(len(names)), [st["recall_by_px"][n][0] for n in names], "o--" if "reference" in c else "o-",
                   label=c)
    if extra is not None:
        extra(a, names)
    a.set_xticks(range(len(names)), names)
    a.set_ylim(0, 1.05)
    a.set_xlabel("visible person pixels in the cell")
    a.set_ylabel("recall of occupied cells (p > 0.5)")
    a.set_title("recall vs visible person pixels")
    a.grid(alpha=0.3)
    a.legend(fontsize=8)


def targets_figure(stats: dict[str, dict]):
    """Left: recall vs visible person pixels per column; right: false alarms per view (pooled column)."""
    fig, (a, b) = pyplot().subplots(1, 2, figsize=(11, 4), layout="constrained")

    def target(ax, names):
        x = names.index("4-7")
        ax.hlines(dict((t[0], t[3]) for t in TARGETS)["recall_4_7px"], x - 0.3, x + 0.3, colors="k", lw=2,
                  label="target at 4-7 px")
        if all(st["recall_by_px"] is None for st in stats.values()):
            ax.text(0.5, 0.5, "no person_px in these view caches", transform=ax.transAxes, ha="center", color="0.4")

    _recall_panel(a, stats, target)
    name, pooled = list(stats.items())[-1]
    hist = pooled["fa_hist"]
    b.bar(np.arange(len(hist)), hist / max(hist.sum(), 1), color="C3")
    b.axvline(1.0, color="k", ls="--", label=f"target <= 1 (mean {pooled['fa_per_view']:.2f})")
    b.set_xlabel("false alarms in the view (empty cells with p > 0.5)")
    b.set_ylabel("share of views")
    b.set_title(f"false alarms per view ({name})")
    b.grid(alpha=0.3, axis="y")
    b.legend(fontsize=8)
    return fig


def family_stats(cache, reference) -> dict[str, dict]:
    """Columns of a family's report: each altitude of the net, and of the reference net (same views)."""
    out = {}
    for alt in (LOW_M, HIGH_M):
        out[f"{alt:g} m"] = perception_stats([at_altitude(cache, alt)])
    for alt in (LOW_M, HIGH_M):
        out[f"{alt:g} m, reference net"] = perception_stats([at_altitude(reference, alt)])
    return out


def visibility(cache) -> dict[str, float]:
    """How hard the family is to see, from the renders alone: the median visible person pixels of an occupied
    cell in the views measuring it, per altitude, and the share of occupied cells no view shows a pixel of."""
    if cache.person_px is None:
        return {}
    alts = cache.config.lattice.positions_enu[:, 2]
    px, valid = cache.person_px.numpy(), cache.valid.numpy()
    occ = cache.occupancy.numpy()[:, None, :]
    out = {}
    for alt in (HIGH_M, LOW_M):
        m = np.isclose(alts, alt)[None, :, None] & valid & occ
        out[f"median_px_{alt:g}m"] = float(np.median(px[m])) if m.any() else float("nan")
    shown = ((px > 0) & valid).any(1)  # (S, N) some view shows a person pixel of the cell
    o = cache.occupancy.numpy()
    out["hidden_share"] = float((o & ~shown).sum() / max(o.sum(), 1))
    return out


def family_rows(stats: dict[str, dict]) -> tuple[list[dict], bool | None]:
    """Rows of the family's targets and its recall per bin (the net against the reference at 70 m); whether the
    70 m bins hold up: no bin with >= 50 occupied cells more than 0.02 below the reference."""
    low, high, ref = stats[f"{LOW_M:g} m"], stats[f"{HIGH_M:g} m"], stats[f"{HIGH_M:g} m, reference net"]
    rows = [{"measure": f"{what} at {LOW_M:g} m", "key": key, "target": f"{op} {target:g}", "value": low[key],
             "reference": stats[f"{LOW_M:g} m, reference net"][key], "met": meets(low[key], op, target)}
            for key, what, op, target in FAMILY_TARGETS]
    for key, what in (("fa_per_cell_view", "false alarms per cell-view"), ("recall_8px", "recall at >= 8 px"),
                      ("cell_ap", "cell average precision"), ("precision", "precision at 0.5"),
                      ("recall", "recall at 0.5")):
        rows.append({"measure": f"{what} at {HIGH_M:g} m", "key": key, "target": "", "value": high[key],
                     "reference": ref[key], "met": None})
    holds = None
    if high["recall_by_px"] is not None and ref["recall_by_px"] is not None:
        judged = []
        for name, (r, n) in high["recall_by_px"].items():
            r_ref = ref["recall_by_px"][name][0]
            ok = None if n < 50 or not np.isfinite(r) else bool(r >= r_ref - 0.02)
            if ok is not None:
                judged.append(ok)
            rows.append({"measure": f"recall at {name} px at {HIGH_M:g} m (n = {n})", "key": f"recall_{name}px_high",
                         "target": ">= reference - 0.02", "value": r, "reference": r_ref, "met": ok})
        holds = all(judged) if judged else None
    return rows, holds


def write_family_report(stats: dict[str, dict], out: Path, meta: dict) -> tuple[Path, Path]:
    out.mkdir(parents=True, exist_ok=True)
    rows, holds = family_rows(stats)
    csv_path = out / "perception_targets.csv"
    with csv_path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["measure", "key", "target", "value", "reference", "met"])
        w.writeheader()
        w.writerows(rows)
    low = stats[f"{LOW_M:g} m"]
    lines = [f"# Perception targets of the {meta['family']} family: {meta['split']} split, {meta['part']} scenes, "
             "every lattice view, per altitude", "",
             f"perception `{meta['perception']}` (tag {meta['tag']}); reference `{meta['reference']}` (tag "
             f"{meta['reference_tag']}); {low['scenes']} scenes; threshold {THRESHOLD}. A cell counts where the view "
             "measured it.", "",
             "| measure | target | net | reference net | met |", "|---|---|---|---|---|"]
    for r in rows:
        met = {True: "yes", False: "**no**", None: ""}[r["met"]]
        lines.append(f"| {r['measure']} | {r['target']} | {_fmt(r['value'])} | {_fmt(r['reference'])} | {met} |")
    lines += ["", f"70 m recall per visible-pixel bin holds up against the reference: "
                  f"{ {True: 'yes', False: '**no**', None: 'not measured'}[holds] } (bins with at least 50 occupied "
                  "cells; at most 0.02 lower).", "",
              "| altitude | views | cell-views | false alarms per view | recall by px: " +
              " / ".join(bin_name(lo, hi) for lo, hi in PX_BINS) + " |", "|---|---|---|---|---|"]
    for c, st in stats.items():
        by = st["recall_by_px"] or {}
        lines.append(f"| {c} | {st['views']} | {st['valid_cells']} | {st['fa_per_view']:.2f} | "
                     + " / ".join(_fmt(by.get(bin_name(lo, hi), (np.nan,))[0], 2) for lo, hi in PX_BINS) + " |")
    vis = meta.get("visibility") or {}
    if vis:
        lines += ["", f"Visibility (renders only): median visible person pixels of an occupied cell in a view measuring "
                      f"it {vis['median_px_70m']:g} at 70 m, {vis['median_px_40m']:g} at 40 m; "
                      f"{100 * vis['hidden_share']:.1f}% of occupied cells show no person pixel in any view."]
    lines += ["", f"{meta['seconds']:.0f} s"]
    md_path = out / "perception_targets.md"
    md_path.write_text("\n".join(lines) + "\n")
    return md_path, csv_path


def family_figure(stats: dict[str, dict]):
    """Left: recall vs visible person pixels per altitude and net; right: false alarms per cell-view against
    the family target."""
    fig, (a, b) = pyplot().subplots(1, 2, figsize=(11, 4), layout="constrained")
    _recall_panel(a, stats)
    cols = list(stats)
    b.bar(range(len(cols)), [stats[c]["fa_per_cell_view"] for c in cols], color=["C0", "C1", "C2", "C3"][: len(cols)])
    target = dict((t[0], t[3]) for t in FAMILY_TARGETS)["fa_per_cell_view"]
    b.axhline(target, color="k", ls="--", label=f"target at {LOW_M:g} m: <= {target:g}")
    b.set_xticks(range(len(cols)), [c.replace(", ", "\n") for c in cols], fontsize=8)
    b.set_ylabel("false alarms per cell-view")
    b.set_title("false alarms (empty measured cells with p > 0.5)")
    b.grid(alpha=0.3, axis="y")
    b.legend(fontsize=8)
    return fig


def eval_family_perception(args: EvalArgs, family: str, caches: dict | None = None) -> dict:
    """A family's report: the net per altitude against the family targets and the reference net."""
    t0 = time.perf_counter()
    split = args.split or setting_params(family).split
    paths = {"net": args.perception or str(shipped_perception(family)),
             "reference": args.reference or str(shipped_perception())}
    if caches is None:
        caches = {}
        for name, path in paths.items():
            net, _ = load_perception(path)
            caches[name] = get_view_cache(net, family, split, args.part, cache_dir=args.cache_dir,
                                          progress=args.progress, executor=Executor.from_args(args),
                                          features=False, limit=args.scenes)
    stats = family_stats(caches["net"], caches["reference"])
    meta = {"family": family, "split": split, "part": args.part, "perception": display_path(paths["net"]),
            "tag": caches["net"].perception_tag, "reference": display_path(paths["reference"]),
            "reference_tag": caches["reference"].perception_tag, "visibility": visibility(caches["net"]),
            "seconds": time.perf_counter() - t0}
    md, csv_path = write_family_report(stats, Path(args.out), meta)
    fig = save_figure(family_figure(stats), Path(args.out) / "perception_targets.png")
    print(md.read_text())
    print(f"wrote {md}, {csv_path}, {fig}")
    return {"stats": stats, "table": md, "csv": csv_path, "figure": fig}


def eval_perception(args: EvalArgs, caches: dict | None = None) -> dict:
    """The report into args.out; `caches` ({setting: ViewCache}; for a family {"net", "reference"}) skips
    perception and rendering."""
    settings = parse_settings(args.setting, families=True)
    if args.part not in PARTS:
        raise UavsearchError(f"unknown part {args.part!r}; valid: {', '.join(PARTS)}")
    torch.set_num_threads(1)
    families = [s for s in settings if setting_params(s).task.mission == "team"]  # a lattice family's report
    if families:
        if len(settings) > 1:
            raise UavsearchError("--setting: evaluate one scene family at a time, apart from the paper's settings")
        return eval_family_perception(args, families[0], caches)
    args = dataclasses.replace(args, perception=args.perception or str(shipped_perception()),
                               split=args.split or "paper")
    t0 = time.perf_counter()
    if caches is None:
        net, _ = load_perception(args.perception)
        caches = {s: get_view_cache(net, s, args.split, args.part, cache_dir=args.cache_dir, progress=args.progress,
                                    executor=Executor.from_args(args)) for s in settings}
    missing = [s for s in settings if s not in caches]
    if missing:
        raise UavsearchError(f"no view cache for setting {missing[0]}")
    stats = {f"setting {s} ({setting_params(s).k} cells)": perception_stats([caches[s]]) for s in settings}
    if len(settings) > 1:
        stats["all"] = perception_stats([caches[s] for s in settings])
    out = Path(args.out)
    meta = {"split": args.split, "part": args.part, "perception": display_path(args.perception),
            "tag": caches[settings[0]].perception_tag, "seconds": time.perf_counter() - t0}
    md, csv_path = write_report(stats, out, meta)
    fig = save_figure(targets_figure(stats), out / "perception_targets.png")
    print(md.read_text())
    print(f"wrote {md}, {csv_path}, {fig}")
    return {"stats": stats, "table": md, "csv": csv_path, "figure": fig}


def add_eval_perception_parser(subparsers) -> None:
    """`uavsearch eval perception ...` (subparsers: the `eval` command's)."""
    p = subparsers.add_parser("perception", help="stage-1 perception against its targets on the test view caches")
    add_dataclass_args(p, EvalArgs)
    p.set_defaults(func=cmd_eval_perception)


def cmd_eval_perception(args) -> int:
    eval_perception(dataclass_from_args(EvalArgs, args))
    return 0
