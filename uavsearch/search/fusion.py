"""Multi-view fusion of per-cell occupancy estimates (paper Sec. IV-E and VII-D): one interface, five methods.

Every method maps a sequence of T per-view estimates of p(y_i = 1) to one fused map:

    fuse(method, p_occ, valid, *, area_px=None, scores=None, labels=None, prior=DEFAULT_PRIOR)

- p_occ:   (..., T, N) per-view probability that cell i is occupied, p(y_i^t = 1) = exp(l_i^t[1]).
- valid:   (..., T, N) bool, whether view t measured cell i: the cell is in view AND view t exists. This one
           mask handles both cells out of view and variable-length sequences (pad short sequences with
           valid = False).
- returns: (..., N) fused p(y_i = 1). A cell that no valid view measured gets `prior`.

Methods (the `FUSION_METHODS` table at the end names each with its kernel and the inputs it needs; a new
method is one kernel and one entry there):
- "bayes":   log-odds occupancy update (Elfes / Thrun): L = logit(prior) + sum_t [logit(p_t) - logit(prior)].
- "average": mean of p_t over the valid views (the paper's Average baseline).
- "size":    p_t of the valid view where the cell's pixel area is largest (needs area_px; ties -> earliest).
- "learned": Eq. 5-7, softmax over the valid views' confidence scores s_t (needs scores), then the
             weighted mean of p_t. Differentiable in torch w.r.t. scores and p_occ (stage 2 trains the
             confidence network through it).
- "oracle":  the evaluation bound (needs labels): correct iff any valid view was correct. It returns
             max_t p_t for occupied cells and min_t p_t for empty ones, which is on the correct side of 0.5
             exactly when some view was.

Works on numpy arrays or torch tensors (the result has the input's type). Probabilities are clipped to
[EPS, 1 - EPS] only inside the Bayes update, where 0 and 1 would be infinite log-odds.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np
import torch

from uavsearch.errors import UavsearchError

# A never-seen cell must land on one side of 0.5 (the metric's test is strict, so 0.5 is wrong for either
# label); the few occupied cells of every setting (2-12 of 100) make "empty" the right default.
DEFAULT_PRIOR = 0.1
EPS = 1e-6


def fuse(
    method: str,
    p_occ,
    valid,
    *,
    area_px=None,
    scores=None,
    labels=None,
    prior: float = DEFAULT_PRIOR,
):
    """Fuse T views into one occupancy map; see the module docstring for shapes and methods."""
    if method not in FUSION_METHODS:
        raise UavsearchError(f"unknown fusion method {method!r}; choose one of {', '.join(FUSION_METHODS)}")
    if not 0.0 < prior < 1.0:
        raise UavsearchError(f"fusion prior must lie in (0, 1), got {prior}")
    as_numpy = not isinstance(p_occ, torch.Tensor)
    p = torch.as_tensor(np.asarray(p_occ, dtype=np.float64) if as_numpy else p_occ)
    v = torch.as_tensor(np.asarray(valid) if as_numpy else valid, device=p.device).to(torch.bool)
    if p.shape != v.shape or p.dim() < 2:
        raise UavsearchError(f"p_occ {tuple(p.shape)} and valid {tuple(v.shape)} must both be (..., T, N)")
    given = {"area_px": area_px, "scores": scores, "labels": labels}
    inputs = {}
    for name in FUSION_METHODS[method].needs:
        x = given[name]
        if x is None:
            raise UavsearchError(f"fusion method {method!r} needs {name}")
        t = torch.as_tensor(np.asarray(x) if not isinstance(x, torch.Tensor) else x, device=p.device)
        inputs[name] = t.to(torch.bool) if name == "labels" else t.to(p.dtype)
        want = p.shape[:-2] + p.shape[-1:] if name == "labels" else p.shape
        if inputs[name].shape != want:
            shape = "p_occ's shape without T, (..., N)" if name == "labels" else f"match p_occ {tuple(p.shape)}"
            raise UavsearchError(f"{name} {tuple(inputs[name].shape)} must " + (
                f"be {shape}" if name == "labels" else shape))
    out = FUSION_METHODS[method].fn(p, v, prior, **inputs)
    return out.numpy() if as_numpy else out


def fuse_prefixes(method: str, p_occ, valid, **kwargs):
    """The fused map after each step: (..., T, N) whose [..., t, :] fuses views 0..t (the policy's M-bar^t)."""
    as_numpy = not isinstance(p_occ, torch.Tensor)
    T = np.shape(p_occ)[-2]
    per_view = ("area_px", "scores")
    outs = []
    for t in range(1, T + 1):
        kw = {k: (val[..., :t, :] if k in per_view and val is not None else val) for k, val in kwargs.items()}
        outs.append(fuse(method, p_occ[..., :t, :], valid[..., :t, :], **kw))
    return np.stack(outs, axis=-2) if as_numpy else torch.stack(outs, dim=-2)


def _no_view(v: torch.Tensor) -> torch.Tensor:
    return ~v.any(dim=-2)


def _bayes(p, v, prior):
    l0 = float(np.log(prior / (1.0 - prior)))
    lp = torch.logit(p.clamp(EPS, 1.0 - EPS))
    L = l0 + torch.where(v, lp - l0, torch.zeros_like(lp)).sum(dim=-2)
    return torch.sigmoid(L)


def _average(p, v, prior):
    n = v.sum(dim=-2)
    s = torch.where(v, p, torch.zeros_like(p)).sum(dim=-2)
    return torch.where(n > 0, s / n.clamp(min=1), torch.full_like(s, prior))


def _by_size(p, v, prior, area_px):
    a = area_px
    masked = torch.where(v, a, torch.full_like(a, -np.inf))
    # argmax returns the first maximal index on ties in torch >= 1.7 for CPU tensors; make it explicit
    # by breaking ties toward earlier views with a tiny decreasing offset.
    T = p.shape[-2]
    offset = -torch.arange(T, dtype=a.dtype, device=a.device).unsqueeze(-1) * 1e-9
    idx = (masked + offset).argmax(dim=-2, keepdim=True)
    picked = p.gather(-2, idx).squeeze(-2)
    return torch.where(_no_view(v), torch.full_like(picked, prior), picked)


def _learned(p, v, prior, scores):
    s = scores
    # Masked softmax over views (Eq. 5). Fill masked scores with a large negative finite number rather than
    # -inf so an all-masked column gives finite (then replaced) values and no NaN gradients.
    neg = torch.finfo(s.dtype).min / 4
    w = torch.softmax(torch.where(v, s, torch.full_like(s, neg)), dim=-2)
    w = torch.where(v, w, torch.zeros_like(w))
    fused = (w * p).sum(dim=-2)  # Eq. 6 on p(y=1); p(y=0) = 1 - fused since the weights sum to 1
    return torch.where(_no_view(v), torch.full_like(fused, prior), fused)


def _oracle(p, v, prior, labels):
    y = labels
    hi = torch.where(v, p, torch.full_like(p, -np.inf)).amax(dim=-2)
    lo = torch.where(v, p, torch.full_like(p, np.inf)).amin(dim=-2)
    out = torch.where(y, hi, lo)
    return torch.where(_no_view(v), torch.full_like(out, prior), out)


class FusionMethod(NamedTuple):
    """One fusion method: its kernel and the inputs it needs beyond p_occ and valid."""

    fn: Callable  # (p, valid, prior, **inputs) -> fused, all torch
    needs: tuple[str, ...]  # of "area_px" (F_size per view), "scores" (a confidence net's), "labels" (ground truth)


# THE table of fusion methods (search/agents.py builds agents from it; replay and the loop read `needs`).
FUSION_METHODS: dict[str, FusionMethod] = {
    "bayes": FusionMethod(_bayes, ()),
    "average": FusionMethod(_average, ()),
    "size": FusionMethod(_by_size, ("area_px",)),
    "learned": FusionMethod(_learned, ("scores",)),
    "oracle": FusionMethod(_oracle, ("labels",)),
}
