"""A detector of your own as perception: any callable from images to person boxes, read against the grid.

The search reads per-cell probabilities (the `Perception` contract, perception.py); a detector says where people
are in the image. `DetectorPerception` joins the two through the grid projection every perception uses: the cell
label image (`geometry.cell_label_image`: which ground cell each pixel sees, from the camera model and the pose
the view is reported at). Each detection stands where its mask's pixels (or, without a mask, its box centre)
look at the ground, and a cell's probability is the noisy-or of the detections standing in it over a floor,
the chance of a person the detector missed:

    p_i = 1 - (1 - floor) * prod_{k in cell i} (1 - score_k)

**The detector** is a callable `detect(images) -> detections`: images (B, H, W, 3) uint8 RGB, and one entry per
image, either a dict with `boxes` (K, 4) x0, y0, x1, y1 in pixels and `scores` (K,) (numpy or torch; torchvision's
detection models return exactly this, with `masks` (K, 1, H, W) or (K, H, W) where they segment), or a tuple
(boxes, scores[, masks]). Only the person class is the detector's to pick (keep its person detections).

**By name**: wherever a perception checkpoint is taken (`uavsearch eval search --perception`, a mission's
`perception:`, the envs' `perception=`), `detector:MODULE:FUNCTION` or `detector:path/to/file.py:FUNCTION` loads
the function and wraps it (`?floor=0.02` after it sets the floor), e.g.

    uavsearch eval search --setting wide --perception detector:examples/detector_plugin.py:detect --out runs/det

View caches key perception outputs by `perception_tag`: this wrapper's is a hash of the name and floor, plus the
detector's weights when it is a torch module, plus its `cache_tag` attribute when it has one (set it to the
checkpoint's hash, so a retrained detector under the same name never reuses the old outputs).
"""

from __future__ import annotations

import copy
import hashlib
import importlib
import importlib.util
import sys
from pathlib import Path
from typing import Any, Callable, ClassVar, NamedTuple
from urllib.parse import parse_qsl

import numpy as np
import torch
from torch import nn

from uavsearch.errors import UavsearchError

from .perception import NUM_CELLS, ViewOutputs, register_perception

PREFIX = "detector:"
FLOOR = 0.02  # p of a cell no detection stands in: the chance that the detector missed a person there
CELL_DIM = 3  # noisy-or probability, highest score, number of detections standing in the cell
GLOBAL_DIM = 2  # detections in the image, their mean score


class Detections(NamedTuple):
    """One image's person detections."""

    boxes: np.ndarray  # (K, 4) float x0, y0, x1, y1 pixels
    scores: np.ndarray  # (K,) float in [0, 1]
    masks: np.ndarray | None = None  # (K, H, W) bool


def _numpy(x) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def as_detections(d, shape: tuple[int, int]) -> Detections:
    """One image's detections in any of the accepted forms (module docstring), checked."""
    if isinstance(d, Detections):
        boxes, scores, masks = d
    elif isinstance(d, dict):
        if "boxes" not in d or "scores" not in d:
            raise UavsearchError(f"a detector's output per image needs 'boxes' and 'scores', got keys {sorted(d)}")
        boxes, scores, masks = d["boxes"], d["scores"], d.get("masks")
    elif isinstance(d, (tuple, list)) and len(d) in (2, 3):
        boxes, scores, masks = (*d, None)[:3]
    else:
        raise UavsearchError(f"a detector must return per image a dict (boxes, scores[, masks]) or a tuple, "
                             f"not {type(d).__name__}")
    boxes = _numpy(boxes).astype(np.float64).reshape(-1, 4)
    scores = _numpy(scores).astype(np.float64).reshape(-1)
    if len(scores) != len(boxes):
        raise UavsearchError(f"a detector gave {len(boxes)} boxes but {len(scores)} scores")
    if not np.all(np.isfinite(scores)) or (len(scores) and (scores.min() < 0 or scores.max() > 1)):
        raise UavsearchError("a detector's scores must be probabilities in [0, 1]")
    if masks is not None:
        masks = _numpy(masks)
        masks = masks.reshape(len(boxes), *masks.shape[-2:]) > 0.5
        if masks.shape[1:] != tuple(shape):
            raise UavsearchError(f"a detector's masks are {masks.shape[1:]}, the images {tuple(shape)}")
    return Detections(boxes, scores, masks)


def detection_cells(det: Detections, label: np.ndarray) -> np.ndarray:
    """(K,) the cell each detection stands in (-1 off the grid): the cell most of its mask's pixels see, or the
    cell its box centre sees."""
    h, w = label.shape
    out = np.full(len(det.scores), -1, np.int64)
    for k, box in enumerate(det.boxes):
        if det.masks is not None and det.masks[k].any():
            cells = label[det.masks[k]]
            cells = cells[cells >= 0]
            out[k] = np.bincount(cells).argmax() if len(cells) else -1
        else:
            u = int(np.clip(np.floor((box[0] + box[2]) / 2.0), 0, w - 1))
            v = int(np.clip(np.floor((box[1] + box[3]) / 2.0), 0, h - 1))
            out[k] = label[v, u]
    return out


def cell_outputs(det: Detections, label: np.ndarray, num_cells: int, floor: float) -> tuple[np.ndarray, ...]:
    """(p (N,), cell features (N, CELL_DIM), global feature (GLOBAL_DIM,), cell pixels (N,)) of one view."""
    cells = detection_cells(det, label)
    on = cells >= 0
    miss = np.ones(num_cells)
    np.multiply.at(miss, cells[on], 1.0 - det.scores[on])
    p = 1.0 - (1.0 - floor) * miss
    best = np.zeros(num_cells)
    np.maximum.at(best, cells[on], det.scores[on])
    count = np.bincount(cells[on], minlength=num_cells)[:num_cells].astype(np.float64)
    pixels = np.bincount(label[label >= 0].ravel().astype(np.int64), minlength=num_cells)[:num_cells]
    glob = np.array([len(det.scores), det.scores.mean() if len(det.scores) else 0.0])
    return p, np.stack([p, best, count], -1), glob, pixels


def load_detector(name: str) -> Callable:
    """MODULE:FUNCTION (importable) or path/to/file.py:FUNCTION (a file, loaded as a module of its own)."""
    where, sep, attr = name.rpartition(":")
    if not sep or not where or not attr:
        raise UavsearchError(f"a detector is named {PREFIX}MODULE:FUNCTION or {PREFIX}path/to/file.py:FUNCTION, "
                             f"not {PREFIX}{name}")
    try:
        if where.endswith(".py"):
            path = Path(where).expanduser()
            if not path.is_file():
                raise UavsearchError(f"detector file {where} not found")
            mod_name = f"uavsearch_detector_{hashlib.sha256(str(path.resolve()).encode()).hexdigest()[:12]}"
            module = sys.modules.get(mod_name)
            if module is None:
                spec = importlib.util.spec_from_file_location(mod_name, path)
                module = importlib.util.module_from_spec(spec)
                sys.modules[mod_name] = module
                try:
                    spec.loader.exec_module(module)
                except BaseException:
                    del sys.modules[mod_name]
                    raise
        else:
            module = importlib.import_module(where)
    except UavsearchError:
        raise
    except ImportError as e:
        raise UavsearchError(f"detector {name}: cannot import {where} ({e})") from None
    except SystemExit as e:  # a plugin that refuses to load (say, a missing package) has said why
        raise UavsearchError(f"detector {name}: {e}") from None
    fn = getattr(module, attr, None)
    if not callable(fn):
        raise UavsearchError(f"detector {name}: {where} has no function {attr!r}")
    return fn


def parse_spec(spec: str) -> tuple[str, dict[str, Any]]:
    """`detector:NAME[?floor=F]` -> (NAME, arguments)."""
    if not spec.startswith(PREFIX):
        raise UavsearchError(f"a detector perception is named {PREFIX}..., not {spec!r}")
    name, _, query = spec[len(PREFIX):].partition("?")
    args: dict[str, Any] = {}
    for k, v in parse_qsl(query, keep_blank_values=True):
        if k != "floor":
            raise UavsearchError(f"{spec}: unknown option {k!r} (known: floor)")
        try:
            args[k] = float(v)
        except ValueError:
            raise UavsearchError(f"{spec}: floor must be a number, not {v!r}") from None
    return name, args


@register_perception("detector")
class DetectorPerception(nn.Module):
    """A person detector behind the perception contract (module docstring): `DetectorPerception(detect)` with
    any callable, or `DetectorPerception("examples/detector_plugin.py:detect")` by name."""

    kind: ClassVar[str] = "detector"

    def __init__(self, detector: str | Callable, floor: float = FLOOR, num_cells: int = NUM_CELLS):
        super().__init__()
        if not 0.0 < float(floor) < 1.0:
            raise UavsearchError(f"a detector perception's floor must be in (0, 1), not {floor}")
        self.name = detector if isinstance(detector, str) else None
        self.detect = load_detector(detector) if isinstance(detector, str) else detector
        if not callable(self.detect):
            raise UavsearchError(f"a detector must be callable, not {type(self.detect).__name__}")
        self.floor, self._num_cells = float(floor), int(num_cells)
        # perception_tag hashes the state dict: the detector's identity goes in as a buffer
        self.register_buffer("identity", torch.tensor(list(self._identity()), dtype=torch.uint8), persistent=True)

    def _identity(self) -> bytes:
        h = hashlib.sha256(f"{self.name or getattr(self.detect, '__qualname__', repr(self.detect))}|{self.floor!r}"
                           .encode())
        h.update(str(getattr(self.detect, "cache_tag", "")).encode())
        state = getattr(self.detect, "state_dict", None)
        if callable(state):
            for k, v in sorted(state().items()):
                h.update(k.encode())
                h.update(_numpy(v).tobytes())
        return h.digest()

    # -- the contract ------------------------------------------------------------------------------
    @classmethod
    def from_arguments(cls, arguments: dict) -> "DetectorPerception":
        arguments = dict(arguments)
        if not isinstance(arguments.get("detector"), str):
            raise UavsearchError("a detector perception is rebuilt from its name (MODULE:FUNCTION or "
                                 "path/to/file.py:FUNCTION): give detector=NAME")
        unknown = sorted(set(arguments) - {"detector", "floor", "num_cells"})
        if unknown:
            raise UavsearchError(f"perception kind 'detector' has no argument(s) {', '.join(unknown)}")
        return cls(**arguments)

    @classmethod
    def from_spec(cls, spec: str) -> "DetectorPerception":
        name, args = parse_spec(spec)
        return cls(name, **args)

    def arguments(self) -> dict[str, Any]:
        return {"detector": self.name, "floor": self.floor, "num_cells": self._num_cells}

    @property
    def num_cells(self) -> int:
        return self._num_cells

    @property
    def cell_dim(self) -> int:
        return CELL_DIM

    @property
    def global_dim(self) -> int:
        return GLOBAL_DIM

    @property
    def stride(self) -> int:
        return 1

    @property
    def reads_altitude(self) -> bool:
        return False

    @property
    def device(self) -> torch.device:
        return self.identity.device

    def for_grid(self, num_cells: int) -> "DetectorPerception":
        if num_cells == self._num_cells:
            return self
        other = copy.copy(self)
        other._num_cells = int(num_cells)
        return other

    @torch.no_grad()
    def forward_all(self, images, labels, geometry=None, altitude_m=None, cells=None) -> ViewOutputs:
        """The detector once per batch; every cell of every view from its detections (module docstring)."""
        imgs = _numpy(images)
        if imgs.ndim == 3:
            imgs = imgs[None]
        if imgs.ndim != 4 or imgs.shape[-1] != 3 or imgs.dtype != np.uint8:
            raise UavsearchError(f"a detector perception reads (B, H, W, 3) uint8 images, got {imgs.shape} "
                                 f"{imgs.dtype}")
        lab = _numpy(labels)
        lab = lab[None] if lab.ndim == 2 else lab
        if lab.shape != imgs.shape[:3]:
            raise UavsearchError(f"label images {lab.shape} do not match images {imgs.shape}")
        dets = list(self.detect(imgs))
        if len(dets) != len(imgs):
            raise UavsearchError(f"the detector returned {len(dets)} results for {len(imgs)} images")
        outs = [cell_outputs(as_detections(d, imgs.shape[1:3]), lab[b], self._num_cells, self.floor)
                for b, d in enumerate(dets)]
        dev = self.device
        p = torch.as_tensor(np.stack([o[0] for o in outs]), dtype=torch.float32, device=dev)
        log_probs = torch.stack([torch.log1p(-p.clamp(max=1 - 1e-6)), torch.log(p.clamp(min=1e-6))], -1)
        return ViewOutputs(log_probs,
                           torch.as_tensor(np.stack([o[1] for o in outs]), dtype=torch.float32, device=dev),
                           torch.as_tensor(np.stack([o[2] for o in outs]), dtype=torch.float32, device=dev),
                           torch.as_tensor(np.stack([o[3] for o in outs]), dtype=torch.float32, device=dev))

    def forward(self, images, labels, altitude_m=None) -> torch.Tensor:
        return self.forward_all(images, labels).log_probs


__all__ = ["DetectorPerception", "Detections", "PREFIX", "as_detections", "cell_outputs", "detection_cells",
           "load_detector", "parse_spec"]
