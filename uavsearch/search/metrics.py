"""Occupancy-map metrics of the paper (Eq. 16-19): per-map accuracy and F1, averaged over maps.

A cell is correct iff p-bar(y_i = y_i^gt) > 0.5 (Sec. VII-A), strictly. So a cell is predicted occupied iff
p > 0.5 and predicted empty iff p < 0.5; a cell at exactly 0.5 is wrong whatever its label, and is counted
as a false positive on an empty cell and a false negative on an occupied one. That keeps acc and F1
consistent: acc = (N_tp + N_tn) / N.

F1 of a map with no occupied cells and no predicted ones (2 N_tp + N_fp + N_fn = 0) is defined as 1.0:
nothing to find and nothing falsely claimed is a perfect map. (The paper's settings always have occupied
cells, so this only matters for user scenes with K = 0.)
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from uavsearch.errors import UavsearchError

RESAMPLES = 10_000  # bootstrap resamples over scenes
LEVEL = 0.95  # the intervals' coverage

F1_WHEN_EMPTY = 1.0


class MapCounts(NamedTuple):
    tp: np.ndarray
    tn: np.ndarray
    fp: np.ndarray
    fn: np.ndarray


def confusion_counts(p_occ, labels) -> MapCounts:
    """Per-map counts for (M, N) fused probabilities and (M, N) binary ground truth (or (N,) for one map)."""
    p = np.asarray(p_occ, dtype=np.float64)
    y = np.asarray(labels).astype(bool)
    if p.shape != y.shape:
        raise UavsearchError(f"predictions {p.shape} and labels {y.shape} must have the same shape")
    if np.isnan(p).any():
        raise UavsearchError("predictions contain NaN")
    pos, neg = p > 0.5, p < 0.5
    tp = (pos & y).sum(-1)
    tn = (neg & ~y).sum(-1)
    fp = (~neg & ~y).sum(-1)  # predicted occupied, or undecided (0.5), on an empty cell
    fn = (~pos & y).sum(-1)  # predicted empty, or undecided, on an occupied cell
    return MapCounts(tp, tn, fp, fn)


def map_accuracy(p_occ, labels) -> np.ndarray:
    """Eq. 16 per map."""
    c = confusion_counts(p_occ, labels)
    n = np.shape(labels)[-1]
    return (c.tp + c.tn) / n


def map_f1(p_occ, labels) -> np.ndarray:
    """Eq. 17 per map, with F1 = 1 for a map with no positives and no predictions."""
    c = confusion_counts(p_occ, labels)
    den = 2 * c.tp + c.fp + c.fn
    with np.errstate(invalid="ignore", divide="ignore"):
        f1 = np.where(den > 0, 2 * c.tp / np.maximum(den, 1), F1_WHEN_EMPTY)
    return f1.astype(np.float64)


def average_metrics(p_occ, labels) -> tuple[float, float]:
    """Eq. 18-19: (Aacc, AF1) over maps, for (M, N) inputs."""
    p = np.atleast_2d(np.asarray(p_occ, dtype=np.float64))
    y = np.atleast_2d(np.asarray(labels))
    if p.shape[0] == 0:
        raise UavsearchError("no maps to average over")
    return float(map_accuracy(p, y).mean()), float(map_f1(p, y).mean())


def unseen_counts(fused, seen) -> tuple[int, float, str] | None:
    """(cells no view has measured, the prior they hold, what the rule above counts them as), None when every cell
    was seen. Such a cell holds the fusion's prior: at 0.5 it is undecided, so wrong whatever its label (a false
    positive or a false negative in F1); below 0.5 it counts as empty, above as occupied."""
    p, unseen = np.asarray(fused, dtype=np.float64), ~np.asarray(seen, dtype=bool)
    n = int(unseen.sum())
    if n == 0:
        return None
    prior = float(np.median(p[unseen]))
    return n, prior, "wrong" if prior == 0.5 else "empty" if prior < 0.5 else "occupied"


def unseen_cells(fused, seen) -> str:
    """'599 unseen (prior 0.5: count as wrong)' for lines beside acc and F1; '' when every cell was seen."""
    c = unseen_counts(fused, seen)
    return "" if c is None else f"{c[0]} unseen (prior {c[1]:.2g}: count as {c[2]})"


def cell_correct(p_occ, labels) -> np.ndarray:
    """Per-cell correctness p-bar(y = y_gt) > 0.5, same shape as the inputs."""
    p = np.asarray(p_occ, dtype=np.float64)
    y = np.asarray(labels).astype(bool)
    return np.where(y, p > 0.5, p < 0.5)


def average_precision(scores, labels) -> float:
    """Area under the precision-recall curve as the mean precision at each positive's rank (ties broken
    by sort order), the detection literature's AP; NaN without positives. numpy only: one sort."""
    s = np.asarray(scores, dtype=np.float64).ravel()
    y = np.asarray(labels).astype(bool).ravel()
    if s.shape != y.shape:
        raise UavsearchError(f"scores {s.shape} and labels {y.shape} must have the same shape")
    if not y.any():
        return float("nan")
    order = np.argsort(-s, kind="stable")
    hits = y[order]
    precision_at = np.cumsum(hits) / np.arange(1, len(hits) + 1)
    return float(precision_at[hits].mean())


def rate_by_bin(x, ok, edges) -> tuple[np.ndarray, np.ndarray]:
    """(share of `ok` among the items whose `x` falls in each [edges[i], edges[i+1]) bin, items per bin);
    NaN for an empty bin. E.g. recall of occupied cells by visible person pixels."""
    x, ok, edges = np.asarray(x), np.asarray(ok), np.asarray(edges)
    idx = np.digitize(x, edges) - 1
    rates, counts = [], []
    for b in range(len(edges) - 1):
        m = idx == b
        counts.append(int(m.sum()))
        rates.append(float(ok[m].mean()) if m.any() else np.nan)
    return np.array(rates), np.array(counts)


def bootstrap_ci(diff, resamples: int = RESAMPLES, seed: int = 0, level: float = LEVEL) -> tuple[float, float, float]:
    """(mean, low, high): the mean of per-scene values and its percentile bootstrap interval over scenes.

    The same (seed, number of scenes) draws the same resamples, so every row of a setting is resampled
    alike (common random numbers) and a rerun gives the same interval."""
    d = np.asarray(diff, dtype=np.float64)
    if d.ndim != 1 or len(d) == 0:
        raise UavsearchError(f"bootstrap needs a non-empty vector of per-scene values, got shape {d.shape}")
    if resamples < 1 or not 0.0 < level < 1.0:
        raise UavsearchError("bootstrap needs at least one resample and a level in (0, 1)")
    idx = np.random.default_rng(seed).integers(0, len(d), (int(resamples), len(d)))
    means = d[idx].mean(1)
    lo, hi = np.quantile(means, [(1.0 - level) / 2.0, (1.0 + level) / 2.0])
    return float(d.mean()), float(lo), float(hi)
