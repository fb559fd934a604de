"""Multi-view fusion of per-cell occupancy estimates (paper Sec. IV-E and VII-D): one interface, six methods.

Every method maps a sequence of T per-view estimates of p(y_i = 1) to one fused map:

    fuse(method, p_occ, valid, *, area_px=None, scores=None, labels=None, prior=DEFAULT_PRIOR)

- p_occ:   (..., T, N) per-view probability that cell i is occupied, p(y_i^t = 1) = exp(l_i^t[1]).
- valid:   (..., T, N) bool, whether view t measured cell i: the cell is in view AND view t exists. This one
           mask handles both cells out of view and variable-length sequences (pad short sequences with
           valid = False).
- returns: (..., N) fused p(y_i = 1). A cell that no valid view measured gets `prior`.

Each method is a `Fusion` class (the `FUSIONS` registry at the end; a new method is one class and one entry
there) whose `fuse(FusionViews)` works on a typed view batch and whose `update(state, view)` adds one view at a
time (what the search loop calls); `fuse(method, ...)` below is the functional form of the same kernels:
- "bayes":   log-odds occupancy update (Elfes / Thrun): L = logit(prior) + sum_t [logit(p_t) - logit(prior)].
- "average": mean of p_t over the valid views (the paper's Average baseline).
- "size":    p_t of the valid view where the cell's pixel area is largest (needs area_px; ties -> earliest).
- "learned": Eq. 5-7, softmax over the valid views' confidence scores s_t (needs scores), then the
             weighted mean of p_t. Differentiable in torch w.r.t. scores and p_occ (stage 2 trains the
             confidence network through it).
- "calibrated": Platt scaling of each view's p by the cell's pixel area, fitted on training views
             (`CalibratedFusion.fit`), then Bayes' rule on the calibrated views with each view's log-odds
             evidence divided by n^gamma, n the views of the cell at about the same scale: gamma 0 is plain
             Bayes, larger gamma discounts views that repeat one another (n far views count n^(1-gamma)
             times one; a closer look counts in full).
- "oracle":  the evaluation bound (needs labels): correct iff any valid view was correct. It returns
             max_t p_t for occupied cells and min_t p_t for empty ones, which is on the correct side of 0.5
             exactly when some view was.

Works on numpy arrays or torch tensors (the result has the input's type). Probabilities are clipped to
[EPS, 1 - EPS] only inside the Bayes update, where 0 and 1 would be infinite log-odds.
"""

from __future__ import annotations

from typing import Callable, ClassVar, NamedTuple

import numpy as np
import torch
from torch import nn

from uavsearch.errors import UavsearchError

from .perception import ConfidenceNet

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
    if not hasattr(fusion_class(method), "kernel"):
        raise UavsearchError(f"the {method} fusion has weights and no functional form: build it (make_fusion)")
    return _run(fusion_class(method), FusionViews(p_occ, valid, area_px=area_px, scores=scores, labels=labels), prior)


def _run(cls: type["Fusion"], views: "FusionViews", prior: float, kernel: Callable | None = None):
    """cls's kernel (or `kernel`, one with its fitted parameters bound) on the views, after checking shapes and
    that every input it needs is there."""
    p_occ, valid = views.p, views.valid
    if not 0.0 < prior < 1.0:
        raise UavsearchError(f"fusion prior must lie in (0, 1), got {prior}")
    as_numpy = not isinstance(p_occ, torch.Tensor)
    p = torch.as_tensor(np.asarray(p_occ, dtype=np.float64) if as_numpy else p_occ)
    v = torch.as_tensor(np.asarray(valid) if as_numpy else valid, device=p.device).to(torch.bool)
    if p.shape != v.shape or p.dim() < 2:
        raise UavsearchError(f"p_occ {tuple(p.shape)} and valid {tuple(v.shape)} must both be (..., T, N)")
    inputs = {}
    for name in cls.needs:
        x = getattr(views, name)
        if x is None:
            what = " (the ground truth, which this view source does not know)" if name == "labels" else ""
            raise UavsearchError(f"fusion method {cls.name!r} needs {name}{what}")
        t = torch.as_tensor(np.asarray(x) if not isinstance(x, torch.Tensor) else x, device=p.device)
        inputs[name] = t.to(torch.bool) if name == "labels" else t.to(p.dtype)
        want = p.shape[:-2] + p.shape[-1:] if name == "labels" else p.shape
        if inputs[name].shape != want:
            shape = "p_occ's shape without T, (..., N)" if name == "labels" else f"match p_occ {tuple(p.shape)}"
            raise UavsearchError(f"{name} {tuple(inputs[name].shape)} must " + (
                f"be {shape}" if name == "labels" else shape))
    out = (kernel or cls.kernel)(p, v, prior, **inputs)
    return out.numpy() if as_numpy else out


def _no_view(v: torch.Tensor) -> torch.Tensor:
    return ~v.any(dim=-2)


SERIAL_LOG = 2047  # elements: torch's vectorised log runs 2048 and more on its intra-op threads
SMALL = 65536  # elements: below, one episode's fusion; the pieces cost less than waking the threads


def _logit(p):
    """torch.logit of p clamped to [EPS, 1 - EPS], with logit's own arithmetic and the same bits (tests/test_fusion.py),
    its log taken in pieces of SERIAL_LOG elements when the whole is small: torch splits even 2,048 elements across
    its intra-op threads, and beside a busy process each call then waits for a thread the neighbour holds (a team
    env's fusion, 16 us alone, took 1.9 ms). With gradients: torch.logit."""
    z = p.clamp(EPS, 1.0 - EPS)
    if z.requires_grad:
        return torch.logit(z)
    odds = z / (1.0 - z)
    if not SERIAL_LOG < odds.numel() < SMALL:
        return torch.log(odds)
    return torch.cat([torch.log(piece) for piece in odds.reshape(-1).split(SERIAL_LOG)]).view_as(odds)


def _bayes(p, v, prior):
    l0 = float(np.log(prior / (1.0 - prior)))
    lp = _logit(p)
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


def calibrated_logit(p, area_px, coef):
    """One view's log-odds of occupancy after Platt scaling with the cell's pixel area: coef (4,) =
    (slope, slope per log px, offset, offset per log px). A net trained to find tiny people says 0.8 for
    clutter far more often than for a person, and how often depends on how many pixels the cell covers."""
    lp = _logit(p)
    la = area_px.clamp(min=1.0).log()
    c = torch.as_tensor(coef, dtype=p.dtype).to(p)  # wherever p lives
    return (c[0] + c[1] * la) * lp + c[2] + c[3] * la


UNCALIBRATED = (1.0, 0.0, 0.0, 0.0)  # p as the net says it: the calibrated kernel is then Bayes' rule


SAME_SCALE = float(np.log(2.0))  # two views whose cell areas differ by less than 2x look from about the same scale


def same_scale_views(v, area_px):
    """(..., T, N): for each view of a cell, how many valid views of it (itself included) saw it at about
    the same scale (pixel area within a factor of 2). Views from one altitude share the clutter that fools the
    net; a closer look is new evidence."""
    return _same_scale(area_px, area_px, v).sum(dim=-2).to(area_px.dtype)


def _same_scale(area_t, area_s, valid_s):
    """[..., t, s, n]: view s is valid and saw cell n at about the scale view t did."""
    la_t, la_s = area_t.clamp(min=1.0).log(), area_s.clamp(min=1.0).log()
    return ((la_t.unsqueeze(-2) - la_s.unsqueeze(-3)).abs() < SAME_SCALE) & valid_s.unsqueeze(-3)


class _CalibratedState(NamedTuple):
    views: "FusionViews"  # p, valid, area_px of the views so far (..., t, N)
    same: torch.Tensor  # (..., t, N) each view's same-scale count so far


def _calibrated(p, v, prior, area_px, coef=UNCALIBRATED, gamma=0.0, same=None):
    """`same`: same_scale_views(v, area_px) when the caller keeps it up to date (CalibratedFusion.update)."""
    l0 = float(np.log(prior / (1.0 - prior)))
    ev = torch.where(v, calibrated_logit(p, area_px, coef) - l0, torch.zeros_like(p))
    if gamma:
        n = same_scale_views(v, area_px) if same is None else same
        ev = ev / n.clamp(min=1).to(p.dtype) ** gamma
    return torch.sigmoid(l0 + ev.sum(dim=-2))


def _oracle(p, v, prior, labels):
    y = labels
    hi = torch.where(v, p, torch.full_like(p, -np.inf)).amax(dim=-2)
    lo = torch.where(v, p, torch.full_like(p, np.inf)).amin(dim=-2)
    out = torch.where(y, hi, lo)
    return torch.where(_no_view(v), torch.full_like(out, prior), out)


# The same kernels on numpy float64 arrays, for per-step work (the envs re-fuse each episode's views at every
# step): numpy runs these small ops in the calling thread, where torch hands each to its intra-op thread pool, whose
# threads wait for a core whenever another process keeps one busy. They equal the torch kernels to float32
# rounding (tests/test_fusion.py).


def _logit_np(p):
    p = np.clip(p, EPS, 1.0 - EPS)
    return np.log(p / (1.0 - p))


def _sigmoid_np(x):
    return 1.0 / (1.0 + np.exp(-x))


def _bayes_np(p, v, prior):
    l0 = float(np.log(prior / (1.0 - prior)))
    return _sigmoid_np(l0 + np.where(v, _logit_np(p) - l0, 0.0).sum(axis=-2))


def _average_np(p, v, prior):
    n = v.sum(axis=-2)
    s = np.where(v, p, 0.0).sum(axis=-2)
    return np.where(n > 0, s / np.maximum(n, 1), prior)


def _by_size_np(p, v, prior, area_px):
    offset = -np.arange(p.shape[-2], dtype=area_px.dtype)[:, None] * 1e-9
    idx = (np.where(v, area_px, -np.inf) + offset).argmax(axis=-2)[..., None, :]
    return np.where(~v.any(axis=-2), prior, np.take_along_axis(p, idx, axis=-2)[..., 0, :])


def _learned_np(p, v, prior, scores):
    s = np.where(v, scores, np.finfo(scores.dtype).min / 4)
    e = np.exp(s - s.max(axis=-2, keepdims=True))
    w = np.where(v, e / e.sum(axis=-2, keepdims=True), 0.0)
    return np.where(~v.any(axis=-2), prior, (w * p).sum(axis=-2))


def _calibrated_np(p, v, prior, area_px, coef=None, gamma=0.0):
    c0, c1, c2, c3 = coef or UNCALIBRATED
    l0 = float(np.log(prior / (1.0 - prior)))
    la = np.log(np.maximum(area_px, 1.0))
    ev = np.where(v, (c0 + c1 * la) * _logit_np(p) + c2 + c3 * la - l0, 0.0)
    if gamma:
        same = ((np.abs(la[..., :, None, :] - la[..., None, :, :]) < SAME_SCALE) & v[..., None, :, :]).sum(axis=-2)
        ev = ev / np.maximum(same, 1).astype(p.dtype) ** gamma
    return _sigmoid_np(l0 + ev.sum(axis=-2))


def _oracle_np(p, v, prior, labels):
    hi = np.where(v, p, -np.inf).max(axis=-2)
    lo = np.where(v, p, np.inf).min(axis=-2)
    return np.where(~v.any(axis=-2), prior, np.where(labels, hi, lo))


# --------------------------------------------------------------------------------------------------
# Fusion objects: one class per method, what the loop, the checkpoints and the trainers hold


class FusionViews(NamedTuple):
    """T views of B episodes: everything a fusion method may read (None where the source lacks it).

    Shapes are (B, T, N) as below, or (..., T, N) with any leading dims.
    """

    p: torch.Tensor  # (B, T, N) each view's p(y_i = 1)
    valid: torch.Tensor  # (B, T, N) bool, the view measured the cell
    area_px: torch.Tensor | None = None  # (B, T, N) the cell's pixel area in the view (F_size)
    cell_features: torch.Tensor | None = None  # (B, T, N, D) perception's per-cell features (or (U, N, D), see rows)
    scores: torch.Tensor | None = None  # (B, T, N) per-view confidence scores, when precomputed
    viewpoints: torch.Tensor | None = None  # (B, T) long lattice index of each view
    labels: torch.Tensor | None = None  # (B, N) bool ground truth (the oracle only)
    # (B, T) long: cell_features is (U, N, D) and view (b, t) is its row feature_rows[b, t] (a cache batch
    # reads each distinct (scene, position) once)
    feature_rows: torch.Tensor | None = None
    # what a fusion keeps of the views' cell features where that is a sum over views (Fusion.feature_summary):
    # the envs' buffered episodes add each view's instead of keeping every view's features; read instead of them
    feature_summary: tuple | None = None


# the view-indexed fields and the dim that indexes T in each
_TIME_DIM = {"p": -2, "valid": -2, "area_px": -2, "scores": -2, "cell_features": -3, "viewpoints": -1}


class Fusion:
    """One fusion method: `fuse(views) -> (B, N)`, or view by view with `init_state` / `update`.

    A subclass names itself (`name`), lists the FusionViews fields its kernel reads (`needs`) and gives the
    kernel; register it in FUSIONS. A method with weights is also an nn.Module, says `trainable` and
    overrides `config` / `from_config` so its checkpoint entry (`save_dict`) rebuilds it (`load_fusion`).
    """

    name: ClassVar[str]
    needs: ClassVar[tuple[str, ...]] = ()  # of "area_px", "scores", "labels" (beyond p and valid)
    trainable: ClassVar[bool] = False  # has weights that stage 2 trains (and a checkpoint holds)
    fitted: ClassVar[bool] = False  # has parameters fitted on training views (its fit() builds it; no spec names it)
    kernel: ClassVar[Callable]  # (p, valid, prior, **needs) -> fused, all torch

    def __init__(self, prior: float = DEFAULT_PRIOR):
        self.prior = prior

    def inputs(self, views: FusionViews) -> FusionViews:
        """The views with what the kernel needs filled in (a learned method scores cell features here)."""
        return views

    def fuse(self, views: FusionViews):
        """(..., T, N) views -> (..., N) fused p(y = 1)."""
        return _run(type(self), self.inputs(views), self.prior)

    host_kernel: ClassVar[Callable | None] = None  # the numpy form of `kernel` (float64 arrays), where there is one

    def _host_kernel(self) -> Callable | None:
        return type(self).host_kernel

    def fuse_host(self, views: FusionViews) -> np.ndarray:
        """`fuse` of numpy views (p float64, valid bool, the rest as `needs` says) in the calling thread: the
        per-step form (module notes above the numpy kernels). Equal to `fuse` to float32 rounding; a method
        without a numpy kernel, or views lacking what it needs, go through `fuse`."""
        kernel = self._host_kernel()
        if kernel is None or any(getattr(views, n) is None for n in self.needs):
            return np.asarray(self.fuse(views), dtype=np.float64)
        return kernel(views.p, views.valid, self.prior, **{n: getattr(views, n) for n in self.needs})

    def feature_summary(self, views: FusionViews) -> tuple | None:
        """What it keeps of the views' cell features, where that is a sum over views (tensors whose leading dim
        is B; views of one episode add up), for FusionViews.feature_summary; None: it reads no features."""
        return None

    def init_state(self, batch_size: int, num_cells: int):
        """The state before any view (None: no views yet; a method with a running state builds it here)."""
        return None

    def update(self, state, view: FusionViews):
        """Add one view (T = 1) -> (state, fused (B, N)). This default keeps the views the kernel reads and
        re-fuses them (exactly `fuse` on the history); a method with a cheaper running form overrides it."""
        view = self.inputs(view)
        view = view._replace(**{f: None for f in ("area_px", "scores", "labels", "cell_features", "viewpoints",
                                                  "feature_rows") if f not in self.needs})
        if state is not None:
            view = view._replace(**{f: torch.cat([getattr(state, f), x], dim=_TIME_DIM[f])
                                    for f, x in view._asdict().items() if f in _TIME_DIM and x is not None})
        return view, self.fuse(view)

    def view_scores(self, state) -> torch.Tensor | None:
        """(B, t+1, N) per-view confidence of the views so far (policies may read it), or None."""
        return getattr(state, "scores", None)

    def prefixes(self, views: FusionViews):
        """The fused map after each view: (..., T, N) whose [..., t, :] fuses views 0..t (the policy's M-bar^t)."""
        state, outs = None, []
        for t in range(views.p.shape[-2]):
            state, fused = self.update(state, views._replace(**{
                f: x.narrow(_TIME_DIM[f], t, 1) for f, x in views._asdict().items()
                if f in _TIME_DIM and x is not None}))
            outs.append(fused)
        return torch.stack(outs, dim=-2)

    @property
    def scorer(self) -> Callable | None:
        """cell features (..., N, D) -> per-view scores (..., N), when the method has such a one-view part
        (view sources then compute it once per (scene, position)); None otherwise."""
        return None

    def frozen(self) -> "Fusion":
        """This method for rollouts: weights shared, scoring in eval mode without grad (itself if none)."""
        return self

    def config(self) -> dict:
        return {"prior": self.prior}

    @classmethod
    def from_config(cls, config: dict) -> "Fusion":
        return cls(**config)

    @classmethod
    def new(cls, cell_dim: int) -> "Fusion":
        """A fresh (untrained) instance for perception features of `cell_dim`."""
        return cls()

    def save_dict(self) -> dict:
        """{name, config, state_dict}: what a checkpoint stores; load_fusion rebuilds the object from it."""
        sd = self.state_dict() if isinstance(self, nn.Module) else {}
        return {"name": self.name, "config": self.config(), "state_dict": dict(sd)}


class BayesFusion(Fusion):
    name, kernel = "bayes", staticmethod(_bayes)
    host_kernel = staticmethod(_bayes_np)


class AverageFusion(Fusion):
    name, kernel = "average", staticmethod(_average)
    host_kernel = staticmethod(_average_np)


class SizeFusion(Fusion):
    name, needs, kernel = "size", ("area_px",), staticmethod(_by_size)
    host_kernel = staticmethod(_by_size_np)


class CalibratedFusion(Fusion):
    """Bayes' rule over views whose p is first calibrated (Platt scaling by pixel area), with views repeated at
    about the same scale discounted by n^gamma. The prior is the training views' occupied share, so a cell no
    view measured keeps the base rate and each view adds its evidence against it."""

    name, needs, fitted, kernel = "calibrated", ("area_px",), True, staticmethod(_calibrated)

    def __init__(self, coef=UNCALIBRATED, prior: float = DEFAULT_PRIOR, gamma: float = 0.0):
        super().__init__(prior)
        self.coef, self.gamma = [float(c) for c in coef], float(gamma)
        if len(self.coef) != 4 or not np.isfinite(self.coef).all() or not 0.0 <= self.gamma <= 1.0:
            raise UavsearchError(f"calibrated fusion needs 4 finite coefficients and gamma in [0, 1], got "
                                 f"{self.coef} and {gamma}")

    def _kernel(self, same=None) -> Callable:
        return lambda p, v, prior, area_px: _calibrated(p, v, prior, area_px, self.coef, self.gamma, same)

    def fuse(self, views: FusionViews):
        return _run(type(self), self.inputs(views), self.prior, kernel=self._kernel())

    def _host_kernel(self) -> Callable:
        return lambda p, v, prior, area_px: _calibrated_np(p, v, prior, area_px, self.coef, self.gamma)

    def update(self, state, view: FusionViews):
        """One view more in O(t N): only the new view's same-scale counts are computed, the earlier views' counts
        grow by one where the new view matches their scale (the same numbers as `fuse` on the history)."""
        if view.area_px is None:
            return super().update(state, view)  # fuse() says what is missing
        view = FusionViews(view.p, torch.as_tensor(view.valid).bool(), view.area_px)
        if state is None:
            hist, same = view, same_scale_views(view.valid, view.area_px)
        else:
            hist = FusionViews(*(torch.cat([getattr(state.views, f), getattr(view, f)], dim=-2)
                                 for f in ("p", "valid", "area_px")))
            grow = _same_scale(state.views.area_px, view.area_px, view.valid).sum(dim=-2)  # (..., t, N)
            new = _same_scale(view.area_px, hist.area_px, hist.valid).sum(dim=-2)  # (..., 1, N)
            same = torch.cat([state.same + grow.to(state.same.dtype), new.to(state.same.dtype)], dim=-2)
        return _CalibratedState(hist, same), _run(type(self), hist, self.prior, kernel=self._kernel(same))

    @property
    def spec(self) -> str:
        return f"calibrated:{self.gamma:g}"

    def config(self) -> dict:
        return {"coef": self.coef, "prior": self.prior, "gamma": self.gamma}

    @classmethod
    def fit(cls, views: FusionViews, gamma: float = 0.0) -> "CalibratedFusion":
        """Platt coefficients by logistic regression (L-BFGS) on every valid cell-view of `views` (p, valid,
        area_px and labels (..., N)); the prior is their occupied share."""
        v = torch.as_tensor(views.valid).bool()
        y = torch.as_tensor(views.labels).bool().unsqueeze(-2).expand(v.shape)[v].double()
        if y.numel() == 0 or y.sum() == 0 or y.sum() == y.numel():
            raise UavsearchError("calibrating a fusion needs views of both occupied and empty cells")
        p = torch.as_tensor(views.p)[v].double()
        a = torch.as_tensor(views.area_px)[v].double()
        w = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.double, device=p.device, requires_grad=True)
        opt = torch.optim.LBFGS([w], max_iter=200, line_search_fn="strong_wolfe")

        def loss():
            opt.zero_grad()
            out = nn.functional.binary_cross_entropy_with_logits(calibrated_logit(p, a, w), y)
            out.backward()
            return out

        opt.step(loss)
        return cls(w.detach().tolist(), prior=float(y.mean()), gamma=gamma)


class OracleFusion(Fusion):
    name, needs, kernel = "oracle", ("labels",), staticmethod(_oracle)
    host_kernel = staticmethod(_oracle_np)


class _EvalScores(nn.Module):
    """A confidence net in eval mode without grad, whatever mode the net itself is in (rollouts' scores)."""

    def __init__(self, net: nn.Module):
        super().__init__()
        self.net = net

    def forward(self, x):
        was = self.net.training
        self.net.eval()
        with torch.no_grad():
            s = self.net(x)
        self.net.train(was)
        return s


class LearnedFusion(nn.Module, Fusion):
    """Eq. 4-7: a confidence net scores each view's cells, the softmax over views weights their p.

    `net` (perception.ConfidenceNet) may be None where the views come with scores (a log, a scored cache).
    """

    name, needs, trainable, kernel = "learned", ("scores",), True, staticmethod(_learned)
    host_kernel = staticmethod(_learned_np)

    def __init__(self, net: nn.Module | None = None, prior: float = DEFAULT_PRIOR):
        nn.Module.__init__(self)
        Fusion.__init__(self, prior)
        self.net = net

    def inputs(self, views: FusionViews) -> FusionViews:
        if views.scores is not None or views.cell_features is None:
            return views
        if self.net is None:
            raise UavsearchError("learned fusion needs a confidence network (or precomputed scores)")
        f, rows = views.cell_features, views.feature_rows
        s = self.net(f) if rows is None else self.net.forward_rows(f, rows)
        return views._replace(scores=s, cell_features=None, feature_rows=None)

    @property
    def scorer(self):
        return self.net

    def frozen(self) -> "LearnedFusion":
        return self if self.net is None else LearnedFusion(_EvalScores(self.net), self.prior)

    def config(self) -> dict:
        mlp = self.net.mlp
        return {"in_dim": self.net.in_dim, "hidden": [mlp[0].out_features, mlp[3].out_features],
                "dropout": float(mlp[2].p), "prior": self.prior}

    @classmethod
    def from_config(cls, config: dict) -> "LearnedFusion":
        c = dict(config)
        net = ConfidenceNet(int(c.pop("in_dim")), tuple(c.pop("hidden")), float(c.pop("dropout")))
        return cls(net, **c)

    @classmethod
    def new(cls, cell_dim: int) -> "LearnedFusion":
        return cls(ConfidenceNet(cell_dim))


# THE registry of fusion methods: name -> class (search/agents.py builds agents from it; a new method is one
# class and one entry here)
FUSIONS: dict[str, type[Fusion]] = {cls.name: cls for cls in (BayesFusion, AverageFusion, SizeFusion, LearnedFusion,
                                                               CalibratedFusion, OracleFusion)}
# the methods a name alone builds (a fitted one needs its training views)
BY_NAME: tuple[str, ...] = tuple(n for n, cls in FUSIONS.items() if not cls.fitted)


def fusion_class(name: str) -> type[Fusion]:
    if name not in FUSIONS:
        raise UavsearchError(f"unknown fusion method {name!r}; choose one of {', '.join(FUSIONS)}")
    return FUSIONS[name]


def check_buildable(name: str) -> None:
    """A one-line error for a name that cannot build a fusion by itself: unknown, or fitted on training views
    (its coefficients come from fit(), which Table III runs on the family's training scenes)."""
    fusion_class(name)
    if FUSIONS[name].fitted:
        raise UavsearchError(f"the {name} fusion is fitted on training views, not built from its name: Table III "
                             f"fits it (uavsearch eval search --wide-fusion {name}:GAMMA)")


def fusion_from_spec(spec: str, what: str = "fusion") -> Fusion:
    """A fusion without weights or labels from "name" or "name:prior" (e.g. bayes:0.02: Bayes' rule with
    that prior, which is also the p of a cell no view has measured); `what` names the option in errors."""
    name, _, prior = str(spec).partition(":")
    plain = [n for n, f in FUSIONS.items() if not f.trainable and not f.fitted and "labels" not in f.needs]
    if name not in plain:
        raise UavsearchError(f"{what} must be a fusion without weights or labels ({', '.join(plain)}), "
                             f"optionally with :prior, not {spec!r}")
    if not prior:
        return FUSIONS[name]()
    try:
        value = float(prior)
    except ValueError:
        value = float("nan")
    if not 0.0 < value < 1.0:
        raise UavsearchError(f"{what} {spec}: the prior must be a number in (0, 1)")
    return FUSIONS[name](value)


# The calibrated fusion's discount of views repeated at one scale: 0 is Bayes' rule (every view independent
# evidence); a 70 m lawnmower sees a cell ten times, and clutter that fools the net once fools it from the next
# viewpoint too.
CALIBRATED_GAMMAS = (0.0, 0.25, 0.5, 0.75, 1.0)


def calibrated_candidates(train, gammas=CALIBRATED_GAMMAS) -> list[Fusion]:
    """Calibrated fusions fitted on every view of a training view cache (its p, cell masks, pixel areas and
    labels), one per discount."""
    views = FusionViews(train.log_probs[..., 1].exp(), train.valid, train.cell_area_px, labels=train.occupancy)
    fitted = CalibratedFusion.fit(views)
    return [CalibratedFusion(fitted.coef, fitted.prior, g) for g in gammas]


def fusion_name(fusion: Fusion) -> str:
    """The spec that names a fusion object ("calibrated:0.75", "bayes:0.1"): what tables and logs print."""
    return getattr(fusion, "spec", None) or f"{fusion.name}:{fusion.prior:g}"


def calibrated_gamma(spec: str) -> float | None:
    """The discount of a "calibrated[:GAMMA]" spec (0 without one), None for any other spec, or a one-line
    error."""
    name, _, gamma = str(spec).partition(":")
    if name != "calibrated":
        return None
    try:
        g = float(gamma or 0.0)
    except ValueError:
        g = float("nan")
    if not 0.0 <= g <= 1.0:
        raise UavsearchError(f"--wide-fusion {spec}: the calibrated fusion's discount must be a number in [0, 1]")
    return g



def load_fusion(d: dict) -> Fusion:
    """The fusion object of a `save_dict()` (weights cast to float32, in eval mode)."""
    fusion = fusion_class(d["name"]).from_config(d["config"])
    if isinstance(fusion, nn.Module):
        fusion.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in d["state_dict"].items()})
        fusion.eval()
    return fusion

