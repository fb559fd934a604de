"""A detector of your own as the search's perception: train one on an exported COCO dataset, plug it in by name.

    uavsearch dataset export --setting wide --part train --scenes 20 --format coco --out runs/wide_coco
    python examples/detector_plugin.py --coco runs/wide_coco --out runs/detector_plugin.pt --steps 400
    UAVSEARCH_DETECTOR=runs/detector_plugin.pt uavsearch eval search --setting wide \\
        --perception detector:examples/detector_plugin.py:detect --out runs/eval_detector

`detect(images)` is all the search needs (uavsearch.search.detector): (B, H, W, 3) uint8 images in, per image
{"boxes": (K, 4) x0 y0 x1 y1, "scores": (K,)} out. It loads the checkpoint UAVSEARCH_DETECTOR names (default
runs/detector_plugin.pt) on first use; `detect.cache_tag` is the checkpoint's hash, so view caches of another
training are never reused.

Two detectors, both trained from scratch (nothing is downloaded):
- `--model fasterrcnn`: torchvision's Faster R-CNN (`torchvision.models.detection.FasterRCNN`) on a small conv
  backbone, anchors of 4-16 px and the image upscaled 2x inside the model: people here are 2-10 px across;
- `--model heatmap`: pure torch, CenterNet-style: a person-centre heatmap and the box size at stride 2.
`--model auto` (default) takes Faster R-CNN when torchvision imports, else the heatmap.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

DEFAULT_CHECKPOINT = Path("runs/detector_plugin.pt")
MEAN, STD = 0.5, 0.25


def _torchvision():
    """torchvision's detection parts, or None when it does not import (absent, or built for another torch)."""
    try:
        from torchvision.models.detection import FasterRCNN
        from torchvision.models.detection.anchor_utils import AnchorGenerator
        from torchvision.ops import MultiScaleRoIAlign
    except Exception:  # noqa: BLE001 - a torchvision built for another torch fails with RuntimeError, not ImportError
        return None
    return FasterRCNN, AnchorGenerator, MultiScaleRoIAlign


def _conv(c_in: int, c_out: int, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, stride, padding=dilation, dilation=dilation, bias=False),
                         nn.BatchNorm2d(c_out), nn.ReLU(inplace=True))


def _normalise(images: np.ndarray) -> torch.Tensor:
    return (torch.as_tensor(images).permute(0, 3, 1, 2).float() / 255.0 - MEAN) / STD


class HeatmapDetector(nn.Module):
    """A person-centre heatmap and log box sizes at stride 2 (CenterNet's recipe, small)."""

    def __init__(self, width: int = 32):
        super().__init__()
        self.body = nn.Sequential(_conv(3, 16), _conv(16, width, 2), _conv(width, width), _conv(width, width, 1, 2),
                                  _conv(width, width, 1, 4), _conv(width, width))
        self.heat, self.size = nn.Conv2d(width, 1, 1), nn.Conv2d(width, 2, 1)
        nn.init.constant_(self.heat.bias, -4.0)  # most of the map is background

    def forward(self, x):
        f = self.body(x)
        return self.heat(f)[:, 0], self.size(f)

    def loss(self, images: np.ndarray, boxes: list[np.ndarray]) -> torch.Tensor:
        heat, size = self(_normalise(images))
        h, w = heat.shape[1:]
        target = torch.zeros_like(heat)
        pos, sizes = [], []
        yy, xx = torch.meshgrid(torch.arange(h).float(), torch.arange(w).float(), indexing="ij")
        for b, bx in enumerate(boxes):
            for x0, y0, x1, y1 in bx:
                cx, cy = (x0 + x1) / 4.0, (y0 + y1) / 4.0  # the centre on the stride-2 map
                ix, iy = min(int(cx), w - 1), min(int(cy), h - 1)
                sigma = max(0.5, (x1 - x0 + y1 - y0) / 12.0)
                g = torch.exp(-((xx - ix) ** 2 + (yy - iy) ** 2) / (2 * sigma**2))
                target[b] = torch.maximum(target[b], g)
                pos.append((b, iy, ix))
                sizes.append((np.log(max(x1 - x0, 1.0)), np.log(max(y1 - y0, 1.0))))
        p = torch.sigmoid(heat).clamp(1e-4, 1 - 1e-4)
        peak = target == 1.0
        focal = -(peak * (1 - p) ** 2 * torch.log(p) + (~peak) * (1 - target) ** 4 * p**2 * torch.log(1 - p)).sum()
        n = max(len(pos), 1)
        loss = focal / n
        if pos:
            b, iy, ix = (torch.tensor(v) for v in zip(*pos))
            loss = loss + 0.1 * F.l1_loss(size[b, :, iy, ix], torch.tensor(sizes, dtype=torch.float32))
        return loss

    @torch.no_grad()
    def detect(self, images: np.ndarray, min_score: float = 0.05, top: int = 100) -> list[dict]:
        heat, size = self(_normalise(images))
        p = torch.sigmoid(heat)
        peaks = (p == F.max_pool2d(p[:, None], 3, 1, 1)[:, 0]) & (p > min_score)
        out = []
        for b in range(len(images)):
            iy, ix = torch.nonzero(peaks[b], as_tuple=True)
            s = p[b, iy, ix]
            keep = torch.argsort(s, descending=True)[:top]
            iy, ix, s = iy[keep], ix[keep], s[keep]
            wh = size[b, :, iy, ix].exp().T
            cx, cy = (ix.float() + 0.5) * 2.0, (iy.float() + 0.5) * 2.0
            boxes = torch.stack([cx - wh[:, 0] / 2, cy - wh[:, 1] / 2, cx + wh[:, 0] / 2, cy + wh[:, 1] / 2], -1)
            out.append({"boxes": boxes.numpy(), "scores": s.numpy()})
        return out


class FasterRCNNDetector(nn.Module):
    """torchvision's Faster R-CNN on a small stride-2 backbone, small anchors, the image upscaled 2x inside."""

    def __init__(self, width: int = 48):
        super().__init__()
        tv = _torchvision()
        if tv is None:
            raise SystemExit("torchvision does not import here (missing, or built for another torch): "
                             "use --model heatmap, or install the torchvision that matches your torch")
        faster_rcnn, anchor_generator, roi_align = tv
        backbone = nn.Sequential(_conv(3, 16), _conv(16, width, 2), _conv(width, width), _conv(width, width, 1, 2))
        backbone.out_channels = width
        self.model = faster_rcnn(
            backbone, num_classes=2, min_size=448, max_size=448, image_mean=[MEAN] * 3, image_std=[STD] * 3,
            rpn_anchor_generator=anchor_generator(sizes=((6, 12, 24),), aspect_ratios=((0.5, 1.0, 2.0),)),
            box_roi_pool=roi_align(featmap_names=["0"], output_size=7, sampling_ratio=2),
            box_score_thresh=0.01, box_detections_per_img=100)

    @staticmethod
    def _inputs(images: np.ndarray) -> list[torch.Tensor]:
        return list(torch.as_tensor(images).permute(0, 3, 1, 2).float() / 255.0)

    def loss(self, images: np.ndarray, boxes: list[np.ndarray]) -> torch.Tensor:
        targets = [{"boxes": torch.as_tensor(b, dtype=torch.float32).reshape(-1, 4),
                    "labels": torch.ones(len(b), dtype=torch.int64)} for b in boxes]
        return sum(self.model(self._inputs(images), targets).values())

    @torch.no_grad()
    def detect(self, images: np.ndarray) -> list[dict]:
        return [{"boxes": o["boxes"].numpy(), "scores": o["scores"].numpy()}
                for o in self.model(self._inputs(images))]


MODELS = {"heatmap": HeatmapDetector, "fasterrcnn": FasterRCNNDetector}


# --------------------------------------------------------------------------------------------------
# The plug: what `--perception detector:examples/detector_plugin.py:detect` calls


def _checkpoint() -> Path:
    return Path(os.environ.get("UAVSEARCH_DETECTOR", DEFAULT_CHECKPOINT))


def load_detector(path) -> nn.Module:
    path = Path(path)
    if not path.is_file():
        raise SystemExit(f"no detector checkpoint at {path}: train one with python examples/detector_plugin.py")
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    model = MODELS[ckpt["model"]](**ckpt["arguments"])
    model.load_state_dict(ckpt["state_dict"])
    return model.eval()


_LOADED: list[nn.Module] = []


def detect(images: np.ndarray) -> list[dict]:
    """Person boxes and scores per image, from the checkpoint UAVSEARCH_DETECTOR names (loaded once)."""
    if not _LOADED:
        _LOADED.append(load_detector(_checkpoint()))
    return _LOADED[0].detect(np.asarray(images))


detect.cache_tag = (hashlib.sha256(_checkpoint().read_bytes()).hexdigest()[:16] if _checkpoint().is_file() else "")


# --------------------------------------------------------------------------------------------------
# Training on an exported COCO dataset


def load_coco(folder) -> tuple[np.ndarray, list[np.ndarray]]:
    """Images (N, H, W, 3) RGB and their person boxes (x0, y0, x1, y1) from `uavsearch dataset export` output."""
    try:
        from pycocotools.coco import COCO
    except ImportError:
        raise SystemExit("reading COCO needs pycocotools: pip install 'uavsearch[dataset]'") from None
    folder = Path(folder)
    if not (folder / "coco_annotations.json").is_file():
        raise SystemExit(f"{folder} holds no coco_annotations.json: export one with uavsearch dataset export")
    coco = COCO(str(folder / "coco_annotations.json"))
    images, boxes = [], []
    for image_id in sorted(coco.imgs):
        im = coco.imgs[image_id]
        images.append(cv2.cvtColor(cv2.imread(str(folder / im["file_name"])), cv2.COLOR_BGR2RGB))
        xywh = np.array([a["bbox"] for a in coco.loadAnns(coco.getAnnIds(imgIds=image_id))]).reshape(-1, 4)
        boxes.append(np.concatenate([xywh[:, :2], xywh[:, :2] + xywh[:, 2:]], 1))
    return np.stack(images), boxes


def _flip(images: np.ndarray, boxes: list[np.ndarray], rng: np.random.Generator):
    """A random horizontal and vertical flip per image, boxes along."""
    out_i, out_b = images.copy(), []
    h, w = images.shape[1:3]
    for k, b in enumerate(boxes):
        b = b.copy()
        if rng.random() < 0.5:
            out_i[k] = out_i[k][:, ::-1]
            b[:, [0, 2]] = w - b[:, [2, 0]]
        if rng.random() < 0.5:
            out_i[k] = out_i[k][::-1]
            b[:, [1, 3]] = h - b[:, [3, 1]]
        out_b.append(b)
    return out_i, out_b


def train(args) -> Path:
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    model_name = args.model if args.model != "auto" else ("fasterrcnn" if _torchvision() is not None else "heatmap")
    if args.model == "auto":
        print(f"detector_plugin: --model auto -> {model_name}")
    images, boxes = load_coco(args.coco)
    print(f"detector_plugin: {len(images)} images, {sum(map(len, boxes))} people from {args.coco}")
    model = MODELS[model_name]()
    opt = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, args.lr, total_steps=args.steps)
    model.train()
    t0 = time.perf_counter()
    for step in range(1, args.steps + 1):
        rows = rng.choice(len(images), min(args.batch, len(images)), replace=False)
        x, b = _flip(images[rows], [boxes[r] for r in rows], rng)
        loss = model.loss(np.ascontiguousarray(x), b)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if step % 25 == 0 or step == args.steps:
            print(f"step {step}/{args.steps}  loss {loss.item():.4f}  {time.perf_counter() - t0:.0f} s", flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"model": model_name, "arguments": {}, "state_dict": model.state_dict(),
                "trained_on": str(args.coco), "steps": args.steps, "seed": args.seed}, out)
    print(f"wrote {out}; plug it in: UAVSEARCH_DETECTOR={out} uavsearch eval search ... "
          "--perception detector:examples/detector_plugin.py:detect")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--coco", required=True, help="an exported COCO folder (uavsearch dataset export --format coco)")
    ap.add_argument("--out", default=str(DEFAULT_CHECKPOINT), help="where the checkpoint goes")
    ap.add_argument("--model", default="auto", choices=("auto", *MODELS), help="which detector (default auto)")
    ap.add_argument("--steps", type=int, default=400, help="optimiser steps")
    ap.add_argument("--batch", type=int, default=8, help="images per step")
    ap.add_argument("--lr", type=float, default=3e-3, help="peak learning rate (one-cycle)")
    ap.add_argument("--seed", type=int, default=0, help="seeds torch and the batches")
    args = ap.parse_args(argv)
    if args.steps < 1 or args.batch < 1:
        raise SystemExit("--steps and --batch must be at least 1")
    train(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
