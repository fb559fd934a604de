"""Per-cell perception (paper Eq. 2-4): the contract every perception kind keeps, its registry, and the kinds.

**The contract** (`Perception`, a typing.Protocol; what the search loop, the envs, the view caches, replay and
evaluation use): `forward_all(images, labels, geometry=None, altitude_m=None, cells=None)` maps a batch of B views
to one `ViewOutputs`:

- in: images (B, H, W, 3) uint8 RGB (or an already normalised (B, 3, H, W) float32 tensor); labels (B, H, W) the
  cell each pixel sees (-1 off the grid, `label == i` is the mask m_i, from `geometry.cell_label_image`);
  `altitude_m` the camera altitudes (one number or B), read by a kind whose `reads_altitude`; `geometry` and
  `cells` are training's (whole-view geometry for crops, the cells to classify).
- out: `log_probs` (B, N, 2) l_i = log p(y_i), `cell_features` (B, N, cell_dim) f_i (the confidence net's
  input), `global_feature` (B, global_dim) (the image embedding's input), `cell_pixels` (B, N) each cell's
  pixel count (0 = not in view), and `person_logits` where a kind has a dense person head.
- plus `num_cells`, `cell_dim`, `global_dim`, `stride` (image sides must be multiples of it),
  `reads_altitude`, `for_grid(N)` (the same weights on another grid) and `arguments()` (the constructor
  arguments its checkpoint records). Stage 1 (search/train/perception.py) also needs `TrainablePerception`:
  `dense_loss` (the kind's pixel-level loss, or None) and `shift_logit_margin` (threshold calibration).

`perceive(perception, views)` is the single-view step (captured `View`s -> outputs, the cells measured, F_size)
that live search, the envs' live fallback and replay share.

**The registry**: `@register_perception("name")` on a class with `from_arguments(dict)`; `build_perception(kind,
**arguments)` makes a fresh one; checkpoints record `kind` and `arguments()`, and `load_perception` rebuilds
them through the registry (a checkpoint without a kind, as every one written before kinds existed, is the CNN).
Kinds: "cnn" (`PerceptionNet`, the shipped nets) and "resnet" (`ResNetPerception`, residual blocks).

Both pool one backbone pass per image: the paper runs VGG-19 once per cell on the masked image O ⊙ m_i (Eq. 2):
100 forward passes per view. Here the backbone runs ONCE per image and each cell's feature is pooled from the
feature map under the cell's mask: the label image is reduced to per-cell pixel fractions at the feature map's
resolution, and the cell feature is [fraction-weighted mean ⊕ fraction-weighted max] of the feature map, plus
the cell's geometry (log pixel count and image centroid), which tells the classifier how large and where the
cell is. The literal per-cell masked pass is kept as `forward_literal` (the reference for correctness and speed:
tools/bench_perception.py).

Heads:
- classifier (Eq. 3): three FC layers, ReLU + dropout after the first two, log-softmax -> l_i = log p(y_i).
- confidence (Eq. 4): three FC layers, ReLU + dropout after the first two, one raw score s_i per cell (the
  softmax over views happens in fusion.py). Trained in stage 2 through the learned fusion.
- image embedding (Eq. 9, F_embedding): the backbone's global feature (mean ⊕ max over the whole feature
  map, `global_dim`) projected to 512 by `ImageEmbedding`, trained with the policy in stage 2.

Stage 2 freezes the perception and caches its `ViewOutputs` per (scene, lattice position): log-probs, cell
features (the confidence net's input) and the global feature.

Every tensor a net makes lives on its parameters' device; inputs are moved there (a no-op on CPU).
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import importlib
import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, ClassVar, NamedTuple, Protocol, runtime_checkable

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from uavsearch.errors import UavsearchError

from .checkpoints import shipped_perception  # noqa: F401  (where its callers have always found it)
from .perception_nets import ResidualTrunk

NUM_CELLS = 100
EMBED_DIM = 512
GEOMETRY_DIM = 3  # log pixel count, centroid u, centroid v
# Reference pixel count for the log-area feature: a 5 m cell at 70 m with the default camera is ~190 px.
AREA_REF_PX = 200.0
# Reference camera altitude of the altitude feature (log(altitude / ALTITUDE_REF_M), 0 at the paper's 70 m).
ALTITUDE_REF_M = 70.0
IMAGE_MEAN, IMAGE_STD = 0.5, 0.25


class PooledConfig:
    """What a pooled net's sizes follow from: its backbone's levels (channels, stride) from the input on, the
    deep map last, and the fields every pooled kind's config has (num_cells, use_geometry, person_head,
    altitude_feature)."""

    @property
    def levels(self) -> list[tuple[int, int]]:
        raise NotImplementedError

    @property
    def stride(self) -> int:
        return int(np.prod([s for _, s in self.levels]))

    @property
    def tap(self) -> int:
        """Index of the level the person head reads: the last one at a finer resolution than the deep map
        (the first level when every level keeps the resolution)."""
        cum = np.cumprod([s for _, s in self.levels])
        finer = [i for i, c in enumerate(cum) if c < cum[-1]]
        return finer[-1] if finer else 0

    @property
    def head_stride(self) -> int:
        return int(np.prod([s for _, s in self.levels[: self.tap + 1]]))

    @property
    def channels(self) -> int:
        """Channels every cell pools: the deep map's, plus the person head's mean and max probability."""
        return self.levels[-1][0] + (2 if self.person_head else 0)

    @property
    def cell_dim(self) -> int:
        return 2 * self.channels + (GEOMETRY_DIM + int(self.altitude_feature) if self.use_geometry else 0)

    @property
    def global_dim(self) -> int:
        return 2 * self.levels[-1][0]


@dataclass(frozen=True)
class PerceptionConfig(PooledConfig):
    """The CNN's architecture; stored in every checkpoint so it can be rebuilt without guessing."""

    # Backbone layers as (out_channels, kernel, stride); conv + BatchNorm + ReLU each. The product of the
    # strides is the feature map's stride. Default: ~0.19 GMAC per 224x224 image with the person head,
    # stride 4 (56x56 map): a 5 m cell (~14 px at 70 m) covers ~3.5 x 3.5 feature pixels; receptive field
    # 27 px (~10 m), enough to tell a person from a bench beside a wall.
    layers: tuple[tuple[int, int, int], ...] = ((16, 3, 2), (24, 3, 1), (32, 3, 2), (48, 3, 1), (48, 3, 1))
    num_cells: int = NUM_CELLS
    use_geometry: bool = True
    hidden: tuple[int, int] = (128, 64)
    dropout: float = 0.3
    conf_hidden: tuple[int, int] = (64, 32)
    # A dense person head at the finer resolution of the last layer before the final stride (stride 2 by
    # default: a 2-4 px person is one or two feature pixels there, and vanishes in a stride-4 average). It
    # reads that layer's features plus the up-sampled deep map, is trained on the renderer's per-pixel
    # person fraction, and its probability map (mean- and max-pooled to the deep map) joins the features
    # every cell pools, so the classifier sees small people the deep map blurs away.
    person_head: bool = True
    person_hidden: int = 16
    # The camera's altitude as one more geometry feature of every cell: a net trained across altitudes then
    # knows the scale it looks at (a person is ~4 px at 70 m and ~11 px at 40 m) even for a cell the image
    # edge clips, whose pixel count alone would read as a farther cell. Off for nets of one altitude.
    altitude_feature: bool = False

    @property
    def levels(self) -> list[tuple[int, int]]:
        return [(c, s) for c, _, s in self.layers]

    @staticmethod
    def from_dict(d: dict) -> "PerceptionConfig":
        d = dict(d)
        d["layers"] = tuple(tuple(x) for x in d["layers"])
        d["hidden"] = tuple(d["hidden"])
        d["conf_hidden"] = tuple(d["conf_hidden"])
        d.setdefault("person_head", False)  # checkpoints written before the head existed
        d.setdefault("altitude_feature", False)
        return PerceptionConfig(**d)


@dataclass(frozen=True)
class ResNetConfig(PooledConfig):
    """The residual kind's architecture: a stem conv (out, kernel, stride), then stages of basic blocks
    (channels, blocks, stride). Default: stride 4 like the CNN (a 5 m cell at 70 m covers ~3.5 x 3.5 feature
    pixels), three blocks, receptive field 47 px, ~0.15 GMAC per 224x224 image and about 2/3 of the CNN's time
    on CPU (no full-resolution stage); the person head reads the stem's stride-2 map."""

    stem: tuple[int, int, int] = (16, 3, 2)
    stages: tuple[tuple[int, int, int], ...] = ((24, 1, 2), (32, 2, 1))
    num_cells: int = NUM_CELLS
    use_geometry: bool = True
    hidden: tuple[int, int] = (128, 64)
    dropout: float = 0.3
    person_head: bool = True
    person_hidden: int = 16
    altitude_feature: bool = False

    @property
    def levels(self) -> list[tuple[int, int]]:
        return [(self.stem[0], self.stem[2]), *((c, s) for c, _, s in self.stages)]


class CellPooling(NamedTuple):
    """How label images map onto a feature map, as sparse (image, cell, feature pixel, fraction) entries.

    Each feature pixel overlaps one cell, or a few where cell borders cross it, so the list has about
    B * h * w entries instead of the dense B * num_cells * h * w.
    """

    image_cell: torch.Tensor  # (nnz,) long, b * num_cells + cell
    feature_pixel: torch.Tensor  # (nnz,) long, b * h * w + feature pixel index
    frac: torch.Tensor  # (nnz,) float32, fraction of the feature pixel's stride x stride block in the cell
    pixels: torch.Tensor  # (B, num_cells) pixel count of each cell in the full-resolution image
    centroid: torch.Tensor  # (B, num_cells, 2) mean pixel position (u, v) in [-1, 1]; 0 when unseen


@dataclass(frozen=True)
class ViewOutputs:
    """What a perception says about a batch of views (the contract's output); stage 2 caches all but the last
    per (scene, lattice position)."""

    log_probs: torch.Tensor  # (B, num_cells, 2) l_i = [log p(y=0), log p(y=1)]
    cell_features: torch.Tensor  # (B, num_cells, cell_dim) f_i, the confidence network's input
    global_feature: torch.Tensor  # (B, global_dim) the image embedding's input
    cell_pixels: torch.Tensor  # (B, num_cells) pixels of each cell in the image; 0 = not in view
    person_logits: torch.Tensor | None = None  # (B, 1, H/s, W/s) the person head's logits (training's target)


@runtime_checkable
class Perception(Protocol):
    """Views in, per-cell outputs out (the module docstring says what each argument and field holds). Kinds are
    torch modules, so `eval()`, `state_dict()` and `parameters()` come with them."""

    kind: ClassVar[str]

    @property
    def num_cells(self) -> int: ...

    @property
    def cell_dim(self) -> int: ...

    @property
    def global_dim(self) -> int: ...

    @property
    def stride(self) -> int: ...

    @property
    def reads_altitude(self) -> bool: ...

    def forward_all(self, images, labels, geometry: tuple[torch.Tensor, torch.Tensor] | None = None,
                    altitude_m=None, cells: torch.Tensor | None = None) -> ViewOutputs: ...

    def for_grid(self, num_cells: int) -> "Perception": ...

    def arguments(self) -> dict[str, Any]: ...


@runtime_checkable
class TrainablePerception(Perception, Protocol):
    """What stage 1 needs beyond the contract: the kind's own pixel-level loss and the threshold calibration."""

    def dense_loss(self, out: ViewOutputs, person_frac, pos_weight: float) -> torch.Tensor | None:
        """The kind's dense loss against the renderer's (B, H', W') uint8 person fraction of the (cropped) views,
        or None when it has no dense head."""

    def shift_logit_margin(self, shift: float) -> None:
        """Add `shift` to every cell's logit margin log p(1) - log p(0), in place."""


def cell_pooling(label: torch.Tensor, stride: int, num_cells: int = NUM_CELLS) -> CellPooling:
    """Reduce (B, H, W) integer labels (-1 off grid) to sparse per-cell fractions on the stride grid.

    Exact counts of (image, cell, feature pixel) keys, no per-cell loop: the labels of each stride x stride
    block are sorted within the block and counted as runs (a block holds one cell, or a few where borders
    cross it), then the runs are ordered by (image, cell, feature pixel). No dense (image, cell, pixel)
    range is made: for a 900-cell grid that would be 0.9 G counters per batch of 32, nearly all empty.
    """
    if label.dim() == 2:
        label = label.unsqueeze(0)
    B, H, W = label.shape
    if H % stride or W % stride:
        raise UavsearchError(f"image size {H}x{W} is not a multiple of the feature stride {stride}")
    h, w = H // stride, W // stride
    if label.is_floating_point() or label.numel() and (label.max() >= num_cells or label.min() < -1):
        raise UavsearchError(f"cell labels must be integers in [-1, {num_cells - 1}]")
    lab = label.to(torch.int16 if num_cells < 2**15 else torch.int32)  # the sort moves a quarter of the bytes
    ss = stride * stride
    blocks = lab.view(B, h, stride, w, stride).permute(0, 1, 3, 2, 4).reshape(B * h * w, ss)
    srt = blocks.sort(dim=1).values.reshape(-1)  # each block's labels, sorted within the block
    first = torch.ones_like(srt, dtype=torch.bool)
    first[1:] = srt[1:] != srt[:-1]
    first[::ss] = True  # a run never crosses blocks
    starts = first.nonzero().squeeze(1)
    n = torch.diff(starts, append=torch.tensor([srt.numel()], device=starts.device))
    cell, block = srt[starts].long(), starts.div(ss, rounding_mode="floor")
    on_grid = cell >= 0
    cell, block, n = cell[on_grid], block[on_grid], n[on_grid]
    b, pix = block.div(h * w, rounding_mode="floor"), block % (h * w)
    order = torch.argsort((b * num_cells + cell) * (h * w) + pix)  # (image, cell, feature pixel)
    b, cell, pix, c = b[order], cell[order], pix[order], n[order].to(torch.float32)
    pixels = torch.zeros(B * num_cells, device=c.device).index_add_(0, b * num_cells + cell, c).view(B, num_cells)
    # Centroids from the block centres weighted by counts (exact to within a block; cheap).
    u = ((pix % w).to(torch.float32) + 0.5) * (2.0 * stride / W) - 1.0
    v = (pix.div(w, rounding_mode="floor").to(torch.float32) + 0.5) * (2.0 * stride / H) - 1.0
    mom = torch.zeros(B * num_cells, 2, device=c.device).index_add_(0, b * num_cells + cell, torch.stack([c * u, c * v], -1))
    centroid = (mom / pixels.view(-1, 1).clamp(min=1.0)).view(B, num_cells, 2)
    return CellPooling(b * num_cells + cell, b * (h * w) + pix, c / float(stride * stride), pixels, centroid)


def pool_cells(fmap: torch.Tensor, pooling: CellPooling, num_cells: int = NUM_CELLS) -> torch.Tensor:
    """(B, C, h, w) feature map -> (B, num_cells, 2C): fraction-weighted mean ⊕ fraction-weighted max.

    Features are non-negative (after ReLU), so weighting by the fraction before the max damps feature
    pixels that are mostly outside the cell (a person just across the border) without a threshold.
    Cells with no pixels get zeros.
    """
    B, C, h, w = fmap.shape
    flat = fmap.permute(0, 2, 3, 1).reshape(B * h * w, C)
    src = flat.index_select(0, pooling.feature_pixel) * pooling.frac.unsqueeze(-1)  # (nnz, C)
    idx = pooling.image_cell
    mass = torch.zeros(B * num_cells, dtype=fmap.dtype, device=fmap.device).index_add_(0, idx, pooling.frac).clamp(min=1e-6)
    mean = torch.zeros(B * num_cells, C, dtype=fmap.dtype, device=fmap.device).index_add(0, idx, src) / mass.unsqueeze(-1)
    # cell_pooling lists entries sorted by (image, cell), so the max is a segment reduction: its backward
    # is ~2x faster on CPU than scatter_reduce("amax")'s. Features are >= 0, so an empty cell's 0 is right.
    lengths = torch.bincount(idx, minlength=B * num_cells)
    mx = torch.segment_reduce(src, "max", lengths=lengths, unsafe=True, initial=0.0)
    return torch.cat([mean, mx], dim=-1).view(B, num_cells, 2 * C)


def pool_cells_literal(fmap: torch.Tensor, label: torch.Tensor, stride: int, num_cells: int = NUM_CELLS) -> torch.Tensor:
    """Reference for pool_cells: one cell at a time from its full-resolution mask m_i (slow, obvious)."""
    if label.dim() == 2:
        label = label.unsqueeze(0)
    B, C, h, w = fmap.shape
    out = torch.zeros(B, num_cells, 2 * C, dtype=fmap.dtype, device=fmap.device)
    for b in range(B):
        for i in range(num_cells):
            m = (label[b] == i).to(fmap.dtype)
            frac = F.avg_pool2d(m[None, None], stride)[0, 0]  # (h, w) fraction of each block in the cell
            if frac.sum() == 0:
                continue
            out[b, i, :C] = (fmap[b] * frac).sum((1, 2)) / frac.sum()
            out[b, i, C:] = (fmap[b] * frac).amax((1, 2))
    return out


def images_to_tensor(images) -> torch.Tensor:
    """(B, H, W, 3) uint8 (numpy or torch) -> normalised (B, 3, H, W) float32."""
    x = torch.as_tensor(np.asarray(images) if not isinstance(images, torch.Tensor) else images)
    if x.dim() == 3:
        x = x.unsqueeze(0)
    if x.shape[-1] != 3:
        raise UavsearchError(f"images must be (B, H, W, 3) RGB, got {tuple(x.shape)}")
    return (x.permute(0, 3, 1, 2).to(torch.float32) / 255.0 - IMAGE_MEAN) / IMAGE_STD


class BitsDropout(nn.Dropout):
    """nn.Dropout whose keep mask compares 16 random bits per element with round(p * 2^16): the same
    Bernoulli(1 - p) mask (p to within 2^-16) from torch's global RNG, drawn 64 bits per RNG call.

    Why: on CPU torch's dropout draws one Bernoulli sample per element, which measured 11.6 ms for a
    (16000, 64) activation on one core (more than the linear layer around it, 1 ms); this draws the same
    mask in about 2.6 ms. Checkpoints are unchanged (no parameters, same place in the Sequential).
    """

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.training or self.p == 0.0:
            return x
        if self.p >= 1.0:
            return x * 0.0
        n = x.numel()
        words = torch.empty((n + 3) // 4, dtype=torch.int64, device=x.device).random_(-2**63, 2**63 - 1)
        bits = words.view(torch.int16)[:n].view(x.shape)  # uniform on [-2^15, 2^15)
        scale = (bits >= int(round(self.p * 65536)) - 32768).to(x.dtype).mul_(1.0 / (1.0 - self.p))
        return x * scale  # one product to differentiate


def _mlp(dims: list[int], dropout: float) -> nn.Sequential:
    """FC layers with ReLU + dropout after every layer but the last."""
    mods: list[nn.Module] = []
    for i in range(len(dims) - 1):
        mods.append(nn.Linear(dims[i], dims[i + 1]))
        if i < len(dims) - 2:
            mods += [nn.ReLU(inplace=True), BitsDropout(dropout)]
    return nn.Sequential(*mods)


class Backbone(nn.Module):
    """Fully convolutional feature extractor (F_perception before pooling), with the dense person head."""

    def __init__(self, cfg: PerceptionConfig):
        super().__init__()
        mods: list[nn.Module] = []
        c_in = 3
        for c_out, k, s in cfg.layers:
            mods += [nn.Conv2d(c_in, c_out, k, s, padding=k // 2, bias=False), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True)]
            c_in = c_out
        self.net = nn.Sequential(*mods)
        self.tap = 3 * cfg.tap + 2  # the ReLU closing the tapped layer
        self.ratio = cfg.stride // cfg.head_stride
        self.person = person_head(cfg)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.features(x)[0]

    def features(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """(deep map, the map every cell pools, person logits at the head's resolution or None)."""
        fine = None
        for i, m in enumerate(self.net):
            x = m(x)
            if i == self.tap:
                fine = x
        return with_person(self.person, fine, x, self.ratio)


def person_head(cfg: PooledConfig) -> nn.Sequential | None:
    """The dense person head (PerceptionConfig.person_head says why): two 1x1 convs on the tapped level's map
    and the up-sampled deep map."""
    if not cfg.person_head:
        return None
    levels = cfg.levels
    return nn.Sequential(nn.Conv2d(levels[cfg.tap][0] + levels[-1][0], cfg.person_hidden, 1),
                         nn.ReLU(inplace=True), nn.Conv2d(cfg.person_hidden, 1, 1))


def with_person(head: nn.Module | None, fine: torch.Tensor, deep: torch.Tensor, ratio: int):
    """(deep map, the map every cell pools, person logits or None): the head's probability map, mean- and
    max-pooled to the deep map's resolution, joins the deep map's channels."""
    if head is None:
        return deep, deep, None
    up = F.interpolate(deep, scale_factor=ratio, mode="nearest") if ratio > 1 else deep
    logits = head(torch.cat([fine, up], dim=1))
    prob = torch.sigmoid(logits)
    if ratio > 1:
        prob = torch.cat([F.avg_pool2d(prob, ratio), F.max_pool2d(prob, ratio)], dim=1)
    else:
        prob = torch.cat([prob, prob], dim=1)
    return deep, torch.cat([deep, prob], dim=1), logits


class ResNetBackbone(nn.Module):
    """The residual trunk (perception_nets.ResidualTrunk) with the same person head as the CNN's."""

    def __init__(self, cfg: ResNetConfig):
        super().__init__()
        self.trunk = ResidualTrunk(cfg.stem, cfg.stages)
        self.tap, self.ratio = cfg.tap, cfg.stride // cfg.head_stride
        self.person = person_head(cfg)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.features(x)[0]

    def features(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        levels = self.trunk(x)
        return with_person(self.person, levels[self.tap], levels[-1], self.ratio)


class ConfidenceNet(nn.Module):
    """Eq. 4: w_i = F_confidence(f_i), one raw score per cell (softmax over views is fusion's job)."""

    def __init__(self, in_dim: int, hidden: tuple[int, int] = (64, 32), dropout: float = 0.3):
        super().__init__()
        self.in_dim = in_dim
        self.mlp = _mlp([in_dim, *hidden, 1], dropout)

    def forward(self, cell_features: torch.Tensor) -> torch.Tensor:
        return self.mlp(cell_features).squeeze(-1)

    def forward_rows(self, cell_features: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """self(cell_features[rows]) with the first layer run once per row of cell_features: training's
        Eq. 11 reads each (scene, position) in many episodes. Dropout still draws its own mask for every
        episode's copy, so the result has the distribution of the direct form (and the same values in
        eval mode)."""
        h = self.mlp[0](cell_features)[rows]
        for layer in self.mlp[1:]:
            h = layer(h)
        return h.squeeze(-1)


class ImageEmbedding(nn.Module):
    """F_embedding's trainable head: the frozen global feature -> a 512-d embedding for the policy."""

    def __init__(self, in_dim: int, out_dim: int = EMBED_DIM):
        super().__init__()
        self.fc = nn.Linear(in_dim, out_dim)

    def forward(self, global_feature: torch.Tensor) -> torch.Tensor:
        return F.relu(self.fc(global_feature))


# --------------------------------------------------------------------------------------------------
# The registry


PERCEPTIONS: dict[str, type] = {}


def register_perception(kind: str):
    """Class decorator: register a perception kind under `kind` (its checkpoints record that name). The class
    needs `from_arguments(dict)` (build from what its `arguments()` returned) and instances keeping the
    `Perception` contract."""

    def deco(cls):
        if PERCEPTIONS.get(kind, cls) is not cls:
            raise UavsearchError(f"perception kind {kind!r} is registered twice")
        cls.kind = kind
        PERCEPTIONS[kind] = cls
        return cls

    return deco


# Kinds whose module registers them when imported, found by name as gymnasium finds an entry point: the module
# imports this one, so this one never imports it.
KIND_MODULES = {"detector": "uavsearch.search.detector"}


def perception_kind(kind: str) -> type:
    if kind not in PERCEPTIONS and kind in KIND_MODULES:
        importlib.import_module(KIND_MODULES[kind])
    if kind not in PERCEPTIONS:
        raise UavsearchError(f"unknown perception kind {kind!r} (known: {', '.join(sorted({*PERCEPTIONS, *KIND_MODULES}))})")
    return PERCEPTIONS[kind]


def build_perception(kind: str = "cnn", **arguments) -> Perception:
    """A fresh (untrained) net of a registered kind; arguments not given take the kind's defaults."""
    return perception_kind(kind).from_arguments(arguments)


def _tuples(x):
    """JSON lists back into the tuples a frozen config holds."""
    return tuple(_tuples(v) for v in x) if isinstance(x, (list, tuple)) else x


class PooledPerception(nn.Module):
    """Backbone + per-cell pooling + classifier (Eq. 2-3), the body both registered kinds share; a kind names
    its config type and backbone (a module whose `features(x)` returns (deep map, pooled map, person logits))."""

    kind: ClassVar[str] = ""
    config_type: ClassVar[type]

    def __init__(self, cfg=None):
        super().__init__()
        self.cfg = cfg or self.config_type()
        self.backbone = self.make_backbone(self.cfg)
        self.classifier = _mlp([self.cfg.cell_dim, *self.cfg.hidden, 2], self.cfg.dropout)

    @staticmethod
    def make_backbone(cfg) -> nn.Module:
        raise NotImplementedError

    # -- the contract ------------------------------------------------------------------------------
    @classmethod
    def from_arguments(cls, arguments: dict) -> "PooledPerception":
        names = {f.name for f in dataclasses.fields(cls.config_type)}
        unknown = sorted(set(arguments) - names)
        if unknown:
            raise UavsearchError(f"perception kind {cls.kind!r} has no argument(s) {', '.join(unknown)} "
                                 f"(it takes {', '.join(sorted(names))})")
        return cls(cls.config_type(**{k: _tuples(v) for k, v in arguments.items()}))

    def arguments(self) -> dict[str, Any]:
        return asdict(self.cfg)

    @property
    def num_cells(self) -> int:
        return self.cfg.num_cells

    @property
    def cell_dim(self) -> int:
        return self.cfg.cell_dim

    @property
    def global_dim(self) -> int:
        return self.cfg.global_dim

    @property
    def stride(self) -> int:
        return self.cfg.stride

    @property
    def reads_altitude(self) -> bool:
        return self.cfg.altitude_feature

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    def dense_loss(self, out: ViewOutputs, person_frac, pos_weight: float) -> torch.Tensor | None:
        """Binary cross-entropy of the person head against the person fraction averaged to its resolution."""
        if out.person_logits is None:
            return None
        s = self.cfg.head_stride
        target = torch.as_tensor(np.asarray(person_frac), dtype=torch.float32).to(out.person_logits.device) / 255.0
        if s > 1:
            target = F.avg_pool2d(target.unsqueeze(1), s)
        else:
            target = target.unsqueeze(1)
        return F.binary_cross_entropy_with_logits(
            out.person_logits, target, pos_weight=torch.tensor(pos_weight, device=target.device))

    def shift_logit_margin(self, shift: float) -> None:
        """Folded into the classifier's last biases, half on each class."""
        last = self.classifier[-1]
        with torch.no_grad():
            last.bias[1] += shift / 2.0
            last.bias[0] -= shift / 2.0

    def for_grid(self, num_cells: int) -> "PooledPerception":
        """The same net (shared weights) pooling `num_cells` cells: nothing learned depends on the grid's size
        (the classifier reads one cell at a time), so a net trained on 10 x 10 reads a 30 x 30 grid."""
        if num_cells == self.cfg.num_cells:
            return self
        other = copy.copy(self)
        other.cfg = dataclasses.replace(self.cfg, num_cells=int(num_cells))
        return other

    # -- pieces ------------------------------------------------------------------------------------
    def cell_features(self, fmap: torch.Tensor, pooling: CellPooling, altitude_m=None) -> torch.Tensor:
        f = pool_cells(fmap, pooling, self.cfg.num_cells)
        if self.cfg.use_geometry:
            f = torch.cat([f, self._geometry(pooling.pixels, pooling.centroid)], dim=-1)
            if self.cfg.altitude_feature:
                alt = self.altitudes(altitude_m, fmap.shape[0], fmap.device)
                f = torch.cat([f, torch.log(alt / ALTITUDE_REF_M)[:, None, None].expand(-1, f.shape[1], 1)], dim=-1)
        return f

    @staticmethod
    def altitudes(altitude_m, batch: int, device=None) -> torch.Tensor:
        """(B,) camera altitudes in metres from a number, a sequence or a tensor (on any device), on `device`
        (default: the tensor's, else the CPU); a net that reads the altitude refuses to guess it."""
        if altitude_m is None:
            raise UavsearchError("this perception net reads the camera altitude: pass altitude_m (the view's "
                                 "position_enu[2])")
        if isinstance(altitude_m, torch.Tensor):
            alt = altitude_m.detach().to(device=device or altitude_m.device, dtype=torch.float32).reshape(-1)
        else:
            alt = torch.as_tensor(np.asarray(altitude_m, dtype=np.float32), device=device).reshape(-1)
        if alt.numel() == 1:
            alt = alt.expand(batch)
        if alt.numel() != batch or not bool((alt > 0).all()):
            raise UavsearchError(f"altitude_m must be {batch} positive altitudes, got {alt.tolist()}")
        return alt

    @staticmethod
    def _geometry(pixels: torch.Tensor, centroid: torch.Tensor) -> torch.Tensor:
        log_area = torch.log1p(pixels) - float(np.log1p(AREA_REF_PX))
        return torch.cat([log_area.unsqueeze(-1), centroid], dim=-1)

    @staticmethod
    def global_feature(fmap: torch.Tensor) -> torch.Tensor:
        return torch.cat([fmap.mean((2, 3)), fmap.amax((2, 3))], dim=-1)

    def classify(self, cell_features: torch.Tensor) -> torch.Tensor:
        return F.log_softmax(self.classifier(cell_features), dim=-1)

    # -- forward -----------------------------------------------------------------------------------
    def forward_all(self, images, labels, geometry: tuple[torch.Tensor, torch.Tensor] | None = None,
                    altitude_m=None, cells: torch.Tensor | None = None,
                    pooling: CellPooling | None = None) -> ViewOutputs:
        """The pooled forward pass: backbone once per image, all cells at once. `pooling`: cell_pooling of
        `labels` when the caller already has it (a view cache's lattice repeats the same labels every scene).

        `geometry` ((B, N) pixels, (B, N, 2) centroids) overrides the cells' geometry features: training on
        crops passes those of the whole view, so a cell cut by the crop still reads as the cell it is.
        `altitude_m` (B,) or one number: the camera altitudes, read by a net with `altitude_feature`.
        `cells` (B, N) bool: classify only these cells (the others get log p = log 0.5): training on crops of a
        900-cell grid uses a few dozen cells of each view, and the classifier need not read the rest."""
        dev = self.device
        x = images if isinstance(images, torch.Tensor) and images.dtype == torch.float32 else images_to_tensor(images)
        lab = torch.as_tensor(np.asarray(labels) if not isinstance(labels, torch.Tensor) else labels)
        x, lab = x.to(dev), lab.to(dev)
        if lab.dim() == 2:
            lab = lab.unsqueeze(0)
        if lab.shape[0] != x.shape[0] or lab.shape[1:] != x.shape[2:]:
            raise UavsearchError(f"label images {tuple(lab.shape)} do not match images {tuple(x.shape)}")
        if hasattr(self, "test_time_flips") and not self.training and geometry is None:
            return self._flip_averaged(x, lab, altitude_m, cells)
        return self._forward(x, lab, geometry, altitude_m, cells, pooling)

    def _forward(self, x, lab, geometry, altitude_m, cells, pooling) -> ViewOutputs:
        dev = self.device
        deep, fmap, person = self.backbone.features(x)
        pooling = cell_pooling(lab, self.cfg.stride, self.cfg.num_cells) if pooling is None else pooling
        if geometry is not None:
            pooling = pooling._replace(pixels=torch.as_tensor(geometry[0]).to(dev),
                                       centroid=torch.as_tensor(geometry[1]).to(dev))
        f = self.cell_features(fmap, pooling, altitude_m)
        if cells is None:
            log_probs = self.classify(f)
        else:
            cells = torch.as_tensor(cells).to(dev)
            log_probs = torch.full((*f.shape[:2], 2), float(np.log(0.5)), dtype=f.dtype, device=dev)
            log_probs[cells] = self.classify(f[cells])
        return ViewOutputs(log_probs, f, self.global_feature(deep), pooling.pixels, person)

    def _flip_averaged(self, x, lab, altitude_m, cells) -> ViewOutputs:
        """forward_all of the view and its three mirror images (image and cell label image mirrored together, so
        each is a view of a mirrored world the net could have been shown): per cell the mean probability and the
        mean features. Four backbone passes per view. The person map is the plain view's: a strided backbone's
        maps of a mirror image, mirrored back, sit a pixel off."""
        outs = [self._forward(x.flip(dims) if dims else x, lab.flip(label_dims) if dims else lab, None, altitude_m,
                              cells, None) for dims, label_dims in FLIPS]
        p = torch.stack([o.log_probs.exp() for o in outs]).mean(0)
        return ViewOutputs(p.clamp_min(1e-12).log(), torch.stack([o.cell_features for o in outs]).mean(0),
                           torch.stack([o.global_feature for o in outs]).mean(0), outs[0].cell_pixels,
                           outs[0].person_logits)

    def forward(self, images, labels, altitude_m=None) -> torch.Tensor:
        """(B, num_cells, 2) log-probabilities; cells with no pixels get meaningless values (mask them)."""
        return self.forward_all(images, labels, altitude_m=altitude_m).log_probs

    def forward_literal(self, images, labels, batch_cells: bool = True, altitude_m=None) -> torch.Tensor:
        """Eq. 2 as written: run the backbone on O ⊙ m_i for every cell in view, pool under m_i.

        The reference for correctness (equal to `forward` for a pointwise backbone) and speed.
        `batch_cells` runs all masked copies of an image as one batch, else one pass per cell.
        """
        x = images_to_tensor(images) if not (isinstance(images, torch.Tensor) and images.dtype == torch.float32) else images
        lab = torch.as_tensor(np.asarray(labels) if not isinstance(labels, torch.Tensor) else labels)
        x, lab = x.to(self.device), lab.to(self.device)
        if lab.dim() == 2:
            lab = lab.unsqueeze(0)
        B = x.shape[0]
        N, s = self.cfg.num_cells, self.cfg.stride
        alt = self.altitudes(altitude_m, B, x.device) if self.cfg.altitude_feature else None
        out = torch.zeros(B, N, 2, device=x.device)
        for b in range(B):
            cells = [i for i in range(N) if bool((lab[b] == i).any())]
            if not cells:
                continue
            masks = torch.stack([(lab[b] == i) for i in cells]).to(x.dtype)  # (n, H, W)
            # Masked pixels are zero in the raw image (black), i.e. -mean/std after normalisation.
            zero = (0.0 - IMAGE_MEAN) / IMAGE_STD
            masked = x[b].unsqueeze(0) * masks.unsqueeze(1) + zero * (1 - masks.unsqueeze(1))
            if batch_cells:
                fmaps = self.backbone.features(masked)[1]
            else:
                fmaps = torch.cat([self.backbone.features(m.unsqueeze(0))[1] for m in masked])
            for j, i in enumerate(cells):
                one = torch.where(lab[b] == i, lab[b], torch.full_like(lab[b], -1))
                pooling = cell_pooling(one.unsqueeze(0), s, N)
                f = self.cell_features(fmaps[j : j + 1], pooling, None if alt is None else alt[b : b + 1])[0, i]
                out[b, i] = self.classify(f.unsqueeze(0))[0]
        return out


@register_perception("cnn")
class PerceptionNet(PooledPerception):
    """The plain CNN the shipped nets are (conv + BatchNorm + ReLU layers: PerceptionConfig)."""

    config_type = PerceptionConfig
    make_backbone = staticmethod(Backbone)

    def __init__(self, cfg: PerceptionConfig | None = None):
        super().__init__(cfg)


@register_perception("resnet")
class ResNetPerception(PooledPerception):
    """Residual blocks instead of plain conv layers (ResNetConfig), pooled and classified the same way."""

    config_type = ResNetConfig
    make_backbone = staticmethod(ResNetBackbone)

    def __init__(self, cfg: ResNetConfig | None = None):
        super().__init__(cfg)


# --------------------------------------------------------------------------------------------------
# The single-view step


class Perceived(NamedTuple):
    """What `perceive` returns for B captured views."""

    outputs: ViewOutputs
    valid: torch.Tensor  # (B, N) bool: the view measured the cell (c^t, and at least one pixel of it)
    cell_area_px: torch.Tensor  # (B, N) float32 F_size, the cell's clipped polygon area in the image


@torch.no_grad()
def perceive(perception: Perception, views) -> Perceived:
    """Run a perception on captured views (anything with image, cell_label, position_enu, cells_in_view,
    cell_area_px: search.views.View), against the cell labels of the pose each REPORTS. The one step live
    search, the envs' live fallback and replay share; tensors come back on the perception's device."""
    views = list(views)
    o = perception.forward_all(np.stack([v.image for v in views]), np.stack([v.cell_label for v in views]),
                               altitude_m=np.array([v.position_enu[2] for v in views], dtype=np.float32))
    dev = o.cell_pixels.device
    seen = torch.as_tensor(np.stack([np.asarray(v.cells_in_view, dtype=bool).reshape(-1) for v in views]), device=dev)
    area = torch.as_tensor(np.stack([np.asarray(v.cell_area_px, dtype=np.float32).reshape(-1) for v in views]),
                           device=dev)
    return Perceived(o, seen & (o.cell_pixels > 0), area)


# --------------------------------------------------------------------------------------------------
# Test-time flips

FLIPS_PREFIX = "flips:"  # `flips:PATH`: the checkpoint at PATH, each view seen four ways (PooledPerception)
FLIPS = (((), ()), ((3,), (2,)), ((2,), (1,)), ((2, 3), (1, 2)))  # (image dims, label image dims) of each mirror


# --------------------------------------------------------------------------------------------------
# Checkpoints


def save_perception(net: Perception, path, extra: dict | None = None) -> Path:
    """Weights + kind + constructor arguments + free-form metadata (training args, metrics) in one torch file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu().clone() for k, v in net.state_dict().items()}  # on the CPU: loads anywhere
    torch.save({"format": "uavsearch-perception/1", "kind": net.kind, "config": net.arguments(), "state_dict": state,
                "extra": json.loads(json.dumps(extra or {}, default=str))}, path)
    return path


def load_perception(path, map_location: str = "cpu") -> tuple[Perception, dict]:
    """Rebuild the net from a checkpoint through the registry (eval mode); returns (net, extra metadata). A
    checkpoint without a kind (every one written before kinds existed, the shipped ones) is the CNN. The net is
    put on `map_location` (a device: "cpu", "cuda", a torch.device). `detector:NAME` wraps a detector of your
    own instead (search/detector.py)."""
    if str(path).startswith("detector:"):
        return perception_kind("detector").from_spec(str(path)).eval().to(map_location), {}
    if str(path).startswith(FLIPS_PREFIX):
        net, extra = load_perception(str(path)[len(FLIPS_PREFIX):], map_location)
        if not isinstance(net, PooledPerception):
            raise UavsearchError(f"{FLIPS_PREFIX} takes a pooled perception checkpoint (cnn, resnet), not {path}")
        # a buffer, so perception_tag's hash (the caches' key) tells the flipped perception from the plain one
        net.register_buffer("test_time_flips", torch.tensor([len(FLIPS)], device=map_location))
        return net, {**extra, "test_time_flips": len(FLIPS)}
    path = Path(path)
    if not path.is_file():
        raise UavsearchError(f"perception checkpoint {path} not found (train one: uavsearch train perception)")
    try:
        ckpt = torch.load(path, map_location=map_location, weights_only=True)
        if ckpt.get("format") != "uavsearch-perception/1":
            raise KeyError("format")
        kind = ckpt.get("kind")
        if kind is None:
            net = PerceptionNet(PerceptionConfig.from_dict(ckpt["config"]))
        else:
            net = perception_kind(kind).from_arguments(ckpt["config"])
        net.load_state_dict(ckpt["state_dict"])
    except UavsearchError:
        raise
    except Exception as e:  # noqa: BLE001 - any corrupt file is one clear line
        raise UavsearchError(f"{path} is not a uavsearch perception checkpoint ({type(e).__name__}: {e})") from None
    net.eval().to(map_location)
    return net, ckpt.get("extra", {})


def perception_tag(net: torch.nn.Module) -> str:
    """A content hash of the weights, so caches of different perception checkpoints never mix."""
    h = hashlib.sha256()
    for k, v in sorted(net.state_dict().items()):
        h.update(k.encode())
        h.update(v.detach().cpu().contiguous().numpy().tobytes())
    return h.hexdigest()[:16]
