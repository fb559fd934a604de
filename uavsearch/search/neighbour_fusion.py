"""The neighbour fusion: the calibrated fusion's map corrected by a small conv net over each cell's views and its
neighbours' (people come in groups; a view that fools perception on one cell fools it on the next).

After every view the net reads, per cell, the calibrated fusion's log-odds and the cell's views per altitude layer
(how many, their highest, mean and lowest calibrated log-odds, their mean log pixel area: `view_planes`) over the
N x N map, and outputs a correction to those log-odds; a fitted log-odds shift sets the decision threshold. It
reads each view's viewpoint (its altitude layer), which the loop's views and the envs' buffered episodes carry
(FusionViews.viewpoints; `fuse_host` runs the same net on their numpy views).

With a FeatureCorrectionNet it also reads what perception saw, not only what it concluded: per altitude layer the
mean of the cell's views' cell features (the 104 numbers perception's classifier reads), reduced by a learned
1 x 1 convolution. A false alarm and a person can get the same score from different evidence, and the views of
one cell, at two altitudes, carry more than their scores. The running state keeps per layer the sum of the views'
features (B, 2, N, D), so a view costs the same however many came before it. Such a fusion needs each view's
cell features: the loop serves them (a cached source reads them from its feature store, a live one from
perception); the envs' buffered episodes keep per layer the running sums of them (`feature_summary`) rather than
every view's.

A checkpoint (`save_neighbour`) holds the fusion's `save_dict()`; the spec "neighbour:PATH.pt" loads it
(`neighbour_from_spec`, what agents.make_fusion calls), "neighbour:A.pt,B.pt,C.pt" averages fits of other seeds
(NeighbourEnsemble), and save_neighbour writes such an ensemble as one checkpoint too. PATH may also be a search
policy's checkpoint carrying such a fusion: "neighbour:models/search_wide_240s_map.pt" is the shipped learned
stack's aggregation (what the team table chooses among).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import nn

from uavsearch.errors import UavsearchError
from uavsearch.paths import REPO_ROOT

from .fusion import FUSIONS, CalibratedFusion, Fusion, FusionViews, calibrated_logit

FORMAT = "uavsearch-neighbour-fusion/1"
PLANES = 11  # view_planes' channels


def view_planes(fused, p, v, area, idx, coef, lowest, n: int) -> torch.Tensor:
    """(B, 11, n, n) from a map fused from views (B, T, N) taken at lattice positions idx (B, T): the fused
    log-odds, then per altitude layer (`lowest` (P,) bool: the lowest layer's viewpoints, first) the cell's views:
    count (capped at 4, / 4), highest, mean and lowest calibrated log-odds, mean log pixel area."""
    c = calibrated_logit(p, area, coef)
    planes = [torch.logit(fused.float().clamp(1e-5, 1 - 1e-5))]
    for layer in (lowest, ~lowest):
        m = v & layer[idx][..., None]
        k = m.sum(1).float()
        seen = (k > 0).float()
        planes += [k.clamp(max=4) / 4,
                   torch.where(m, c, torch.full_like(c, -20.0)).amax(1).clamp(min=-8) * seen,
                   torch.where(m, c, torch.zeros_like(c)).sum(1) / k.clamp(min=1),
                   torch.where(m, c, torch.full_like(c, 20.0)).amin(1).clamp(max=8) * seen,
                   torch.where(m, area.clamp(min=1).log(), torch.zeros_like(area)).sum(1) / k.clamp(min=1)]
    return torch.stack(planes, 1).view(len(idx), len(planes), n, n)


def layer_feature_sums(f, v, idx, lowest) -> tuple[torch.Tensor, torch.Tensor]:
    """Per altitude layer (`lowest` first) the sum of the cell features of the views that measured the cell, and
    their number: f (B, T, N, D), v (B, T, N) bool, idx (B, T) -> (B, 2, N, D) float32, (B, 2, N)."""
    sums, counts = [], []
    for layer in (lowest, ~lowest):
        m = (v & layer[idx][..., None]).float()
        sums.append(torch.einsum("btn,btnd->bnd", m, f.float()))
        counts.append(m.sum(1))
    return torch.stack(sums, 1), torch.stack(counts, 1)


def feature_mean_planes(sums, counts, n: int) -> torch.Tensor:
    """(B, 2D, n, n): the layers' mean cell features (zero where a layer has no view), the lowest layer's D
    channels first."""
    mean = sums / counts.clamp(min=1)[..., None]  # (B, 2, N, D)
    return mean.permute(0, 1, 3, 2).reshape(len(mean), -1, n, n)


def feature_planes(cache, rows, episode, lowest, n: int, step: int = -1, chunk: int = 25) -> torch.Tensor:
    """(B, 2D, n, n) float16 feature_mean_planes of a cached episode's views up to view `step` (the last by
    default), read from the cache's feature store `chunk` scenes at a time (a family's features stay on disk)."""
    t = episode.lattice_idx.shape[1]
    idx = episode.lattice_idx[:, :step % t + 1]
    taken = episode.taken if episode.taken is not None else torch.ones_like(episode.lattice_idx, dtype=torch.bool)
    out = []
    for a in range(0, len(rows), chunk):
        r = torch.as_tensor(rows[a:a + chunk])[:, None]
        i = idx[a:a + chunk]
        v = cache.valid[r, i] & taken[a:a + chunk, :i.shape[1], None]
        out.append(feature_mean_planes(*layer_feature_sums(cache.features_at(r, i), v, i, lowest), n).half())
    return torch.cat(out)


def episode_planes(cache, rows, episode, coef, lowest, n: int, step: int = -1) -> torch.Tensor:
    """view_planes of a cached episode's map after view `step` (the last by default) and its views up to it:
    `cache` a ViewCache, `rows` the episode's scenes in it, `episode` run_search's result on them."""
    r = torch.as_tensor(rows)[:, None]
    t = episode.lattice_idx.shape[1]
    idx = episode.lattice_idx[:, :step % t + 1]
    taken = episode.taken if episode.taken is not None else torch.ones_like(episode.lattice_idx, dtype=torch.bool)
    v = cache.valid[r, idx] & taken[:, :idx.shape[1], None]
    return view_planes(episode.maps[:, step], cache.log_probs[r, idx, :, 1].exp().float(), v,
                       cache.cell_area_px[r, idx].float(), idx, coef, lowest, n)


class CorrectionNet(nn.Module):
    """A correction to the calibrated log-odds (plane 0), from each cell's planes (kernel 1) or its neighbours'."""

    def __init__(self, planes: int = PLANES, kernel: int = 5, hidden: int = 24):
        super().__init__()
        self.planes, self.kernel, self.hidden = planes, kernel, hidden
        pad = kernel // 2
        self.net = nn.Sequential(nn.Conv2d(planes, hidden, kernel, padding=pad), nn.ReLU(),
                                 nn.Conv2d(hidden, hidden, kernel, padding=pad), nn.ReLU(),
                                 nn.Conv2d(hidden, hidden, 1), nn.ReLU(), nn.Conv2d(hidden, 1, 1))

    def forward(self, x):
        return self.net(x)[:, 0] + x[:, 0]


class FeatureCorrectionNet(nn.Module):
    """CorrectionNet over the score planes and the layers' mean cell features (planes PLANES on: `features` = two
    layers x D) reduced by a 1 x 1 convolution to `reduce` channels (inputs may come in float16: training keeps
    its maps that way)."""

    def __init__(self, features: int, kernel: int = 5, reduce: int = 8, hidden: int = 24):
        super().__init__()
        self.features, self.reduce_to = int(features), int(reduce)
        self.reduce = nn.Conv2d(features, reduce, 1)
        self.net = CorrectionNet(PLANES + reduce, kernel, hidden)
        self.kernel, self.hidden, self.planes = kernel, hidden, PLANES + features

    def forward(self, x):
        x = x.float()
        return self.net(torch.cat([x[:, :PLANES], torch.relu(self.reduce(x[:, PLANES:]))], 1))


def correction_net(config: dict) -> CorrectionNet | FeatureCorrectionNet:
    """The net a fusion's config describes (one with "features" reads cell features)."""
    c = config
    if c.get("features"):
        return FeatureCorrectionNet(int(c["features"]), int(c["kernel"]), int(c["reduce"]), int(c["hidden"]))
    return CorrectionNet(int(c["planes"]), int(c["kernel"]), int(c["hidden"]))


class NeighbourFusion(nn.Module, Fusion):
    """The calibrated fusion (`base`) with its map corrected by a CorrectionNet after every view, then shifted by
    `shift` log-odds, so that the policy reads the corrected map too. `lowest`: (P,) bool, the lattice's lowest
    layer (wide_policies.lowest_layer); `n`: the grid's side. With a FeatureCorrectionNet it reads the views' cell
    features too (`reads_features`; its `needs` then name them)."""

    name, needs, trainable = "neighbour", ("area_px", "viewpoints"), True

    def __init__(self, base: CalibratedFusion, net: CorrectionNet | FeatureCorrectionNet, shift: float, lowest,
                 n: int):
        nn.Module.__init__(self)
        Fusion.__init__(self, base.prior)
        self.base, self.net, self.shift, self.n = base, net, float(shift), int(n)
        self.register_buffer("lowest", torch.as_tensor(lowest, dtype=torch.bool))
        self.reads_features = isinstance(net, FeatureCorrectionNet)
        if self.reads_features:
            self.needs = type(self).needs + ("cell_features",)

    @classmethod
    def around(cls, base: CalibratedFusion, net: CorrectionNet, shift: float, config) -> "NeighbourFusion":
        """The fusion for a search config's lattice and grid."""
        from .wide_policies import lowest_layer

        return cls(base, net, shift, lowest_layer(config), config.grid.n)

    def _correct(self, fused, views: FusionViews, idx, feature_sums=None) -> torch.Tensor:
        if idx.numel() and int(idx.max()) >= len(self.lowest) or fused.shape[-1] != self.n * self.n:
            raise UavsearchError(f"the neighbour fusion was fitted for {len(self.lowest)} viewpoints and "
                                 f"{self.n} x {self.n} cells, not this search's")
        with torch.no_grad():
            planes = view_planes(fused, views.p.float(), views.valid, views.area_px.float(), idx, self.base.coef,
                                 self.lowest.to(idx.device), self.n)
            if self.reads_features:
                sums = feature_sums if feature_sums is not None else self._feature_sums(views, idx)
                planes = torch.cat([planes, feature_mean_planes(*sums, self.n)], 1)
            return torch.sigmoid(self._logits(planes))

    @property
    def cell_dim(self) -> int | None:
        """The cell features per view it reads (perception's), None for a fusion over scores."""
        return self.net.features // 2 if self.reads_features else None  # the net reads two layers' means

    def _view_features(self, views: FusionViews) -> torch.Tensor:
        """(B, T, N, D) the views' cell features; their absence, or features of another perception, is a
        one-line error."""
        f = views.cell_features
        if f is not None and views.feature_rows is not None:
            f = f[views.feature_rows]
        if f is None or f.shape[-1] == 0:
            raise UavsearchError(f"this neighbour fusion reads each view's {self.cell_dim} cell features, which "
                                 "this view source does not give (a view cache without its feature store, or "
                                 "views of scores only)")
        if f.shape[-1] != self.cell_dim:
            raise UavsearchError(f"this neighbour fusion reads {self.cell_dim} cell features per view (its "
                                 f"perception's), this view source gives {f.shape[-1]}")
        return f

    def _feature_sums(self, views: FusionViews, idx):
        if views.feature_summary is not None:
            return views.feature_summary
        return layer_feature_sums(self._view_features(views), torch.as_tensor(views.valid).bool(), idx,
                                  self.lowest.to(idx.device))

    def feature_summary(self, views: FusionViews) -> tuple | None:
        """Per altitude layer the views' feature sums and counts (layer_feature_sums): all it keeps of them."""
        if not self.reads_features:
            return None
        return self._feature_sums(views._replace(feature_summary=None), torch.as_tensor(views.viewpoints))

    def _logits(self, planes) -> torch.Tensor:
        return self.net.to(planes.device)(planes).flatten(1) + self.shift

    def fuse(self, views: FusionViews):
        if views.viewpoints is None or views.area_px is None:
            raise UavsearchError("the neighbour fusion needs each view's viewpoint and pixel areas")
        fused = self.base.fuse(views)
        return self._correct(fused, views._replace(valid=torch.as_tensor(views.valid).bool()), views.viewpoints)

    def update(self, state, view: FusionViews):
        """The calibrated fusion's state keeps the views so far; only their viewpoints are kept beside it."""
        if view.viewpoints is None:
            raise UavsearchError("the neighbour fusion needs each view's viewpoint")
        base_state, idx, sums = state if state is not None else (None, None, None)
        if self.reads_features:  # the layers' feature sums grow by this view's
            new = self._feature_sums(view, view.viewpoints)
            sums = new if sums is None else (sums[0] + new[0], sums[1] + new[1])
        base_state, fused = self.base.update(base_state, view)
        idx = view.viewpoints if idx is None else torch.cat([idx, view.viewpoints], 1)
        return (base_state, idx, sums), self._correct(fused, base_state.views, idx, sums)

    def fuse_host(self, views: FusionViews) -> np.ndarray:
        """The envs' buffered episodes fuse numpy views: the same net, on tensors (it has no numpy kernel)."""
        def t(x):
            return None if x is None else torch.as_tensor(x)

        summary = None if views.feature_summary is None else tuple(map(t, views.feature_summary))
        return self.fuse(FusionViews(t(views.p), t(views.valid), t(views.area_px), t(views.cell_features),
                                     viewpoints=t(views.viewpoints), feature_summary=summary)).double().numpy()

    def view_scores(self, state):
        return None

    def config(self) -> dict:
        features = {"features": self.net.features, "reduce": self.net.reduce_to} if self.reads_features else {}
        return {"coef": self.base.coef, "prior": self.base.prior, "gamma": self.base.gamma, "shift": self.shift,
                "kernel": self.net.kernel, "hidden": self.net.hidden, "planes": self.net.planes,
                "lowest": [bool(b) for b in self.lowest], "n": self.n, **features}

    @classmethod
    def from_config(cls, config: dict) -> "NeighbourFusion":
        c = config
        return cls(CalibratedFusion(c["coef"], c["prior"], c["gamma"]), correction_net(c), c["shift"], c["lowest"],
                   c["n"])

    @property
    def spec(self) -> str:
        return f"neighbour{'+features' if self.reads_features else ''}(calibrated:{self.base.gamma:g})"


class NeighbourEnsemble(NeighbourFusion):
    """Neighbour fusions fitted with different seeds, their shifted log-odds averaged: one fit's seed moves the
    rule's validation AF1 by up to 0.03, half of what the fusion gains. The members share the base fusion (the
    same calibration) and the lattice; each keeps its own shift."""

    name = "neighbour-ensemble"

    def __init__(self, base: CalibratedFusion, nets: list[CorrectionNet | FeatureCorrectionNet], shifts: list[float],
                 lowest, n: int):
        super().__init__(base, nets[0], shifts[0], lowest, n)
        self.others = nn.ModuleList(nets[1:])
        self.shifts = [float(x) for x in shifts]

    @classmethod
    def of(cls, members: list[NeighbourFusion]) -> "NeighbourEnsemble":
        """The ensemble of fitted fusions; members of another calibration or lattice are a one-line error."""
        first = members[0]

        def key(m):
            return m.base.coef, m.base.prior, m.base.gamma, m.n, m.reads_features, m.net.planes

        for m in members[1:]:
            if key(m) != key(first) or not torch.equal(m.lowest, first.lowest):
                raise UavsearchError("the neighbour fusions of an ensemble must share their base fusion, lattice "
                                     "and inputs (fitted for the same family, budget and perception, all with "
                                     "cell features or all without)")
        return cls(first.base, [m.net for m in members], [m.shift for m in members], first.lowest, first.n)

    def _logits(self, planes) -> torch.Tensor:
        nets = [self.net, *self.others]
        return torch.stack([net.to(planes.device)(planes).flatten(1) + s for net, s in zip(nets, self.shifts)]).mean(0)

    def config(self) -> dict:
        return {**super().config(), "shifts": self.shifts}

    @classmethod
    def from_config(cls, config: dict) -> "NeighbourEnsemble":
        c = config
        nets = [correction_net(c) for _ in c["shifts"]]
        return cls(CalibratedFusion(c["coef"], c["prior"], c["gamma"]), nets, c["shifts"], c["lowest"], c["n"])

    @property
    def spec(self) -> str:
        return f"{super().spec} x {len(self.shifts)}"


FUSIONS[NeighbourFusion.name] = NeighbourFusion  # one registry; agents.py imports this module (make_fusion)
FUSIONS[NeighbourEnsemble.name] = NeighbourEnsemble


def save_neighbour(fusion: NeighbourFusion, path, meta: dict | None = None) -> Path:
    """Write the fusion (and what made it, `meta`) to a checkpoint file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"format": FORMAT, "fusion": fusion.save_dict(), "meta": dict(meta or {})}, path)
    return path


def load_neighbour(path) -> NeighbourFusion:
    """The fusion of a checkpoint save_neighbour wrote, or the learned aggregation a search policy's checkpoint
    carries (a shipped stack's, e.g. models/search_wide_240s_map.pt); a missing or foreign file is a one-line
    error."""
    from .fusion import load_fusion

    if not Path(path).is_file() and not Path(path).is_absolute() and (REPO_ROOT / path).is_file():
        path = REPO_ROOT / path  # "neighbour:models/..." names the repository's wherever it runs from
    if not Path(path).is_file():
        raise UavsearchError(f"neighbour fusion checkpoint {path} not found")
    fusion = None
    try:
        ck = torch.load(path, map_location="cpu", weights_only=True)
        if ck.get("format") == FORMAT:
            return load_fusion(ck["fusion"])
        if "policy_state" in ck and isinstance(ck.get("fusion"), dict):  # a search policy's (policy.py's layout)
            fusion = load_fusion(ck["fusion"])
    except (OSError, KeyError, AttributeError, RuntimeError, ValueError, TypeError) as e:
        raise UavsearchError(f"{path} is not a neighbour fusion checkpoint ({type(e).__name__})") from None
    if not isinstance(fusion, NeighbourFusion):
        raise UavsearchError(f"{path} is not a neighbour fusion checkpoint, nor a search policy carrying one")
    return fusion


def neighbour_from_spec(spec: str) -> NeighbourFusion | None:
    """The fusion "neighbour:PATH.pt" names ("neighbour:A.pt,B.pt,...": the ensemble of those fits), None for
    another spec; "neighbour" alone is a one-line error."""
    name, _, paths = str(spec).partition(":")
    if name != NeighbourFusion.name:
        return None
    paths = [p for p in paths.split(",") if p]
    if not paths:
        raise UavsearchError("the neighbour fusion loads its weights: name it neighbour:PATH.pt (or PATH,PATH,...)")
    fusions = [load_neighbour(p) for p in paths]
    return fusions[0] if len(fusions) == 1 else NeighbourEnsemble.of(fusions)
