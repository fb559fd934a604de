"""COCO box AP (pycocotools' COCOeval) of a perception on exported views: the detection field's standard metric,
so a perception of ours and a detector of your own compare on one scale.

    uavsearch dataset export --setting wide --part test --scenes 5 --format coco --out runs/wide_test_coco
    python tools/perception_box_ap.py --coco runs/wide_test_coco
    python tools/perception_box_ap.py --coco runs/wide_test_coco \
        --perception detector:examples/detector_plugin.py:detect

Our perception is per cell: it says whether a 5 m cell holds a person, not where in it. The boxes read out of it:
- **person head**: the dense person head every shipped net has (stage 1's auxiliary target, the renderer's person
  fraction) is a probability map at half the image's resolution; up-sampled, thresholded, each connected
  component is a box scored by its highest probability. This is a detector's reading of the net.
- **cell footprints**: every cell in view as the box of its pixels, scored by its p(occupied). A 5 m cell is
  about 14 px at 70 m and 24 px at 40 m, a person 2-10 px, so a footprint's IoU with a person's box stays far
  below COCO's 0.5: its AP is about 0 by construction. It is printed to say exactly that (the per-cell output
  is not a detector), not as a score to improve.
- a `detector:...` perception's own boxes and scores, as its callable gives them.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from ..errors import UavsearchError, run_command
from ..geometry import CameraIntrinsics, CameraPose, Grid, cell_label_image
from ..search.detector import DetectorPerception, as_detections
from ..search.perception import load_perception, shipped_perception

STATS = ("AP", "AP50", "AP75", "AP_small", "AP_medium", "AP_large", "AR1", "AR10", "AR100", "AR_small",
         "AR_medium", "AR_large")


def load_export(folder):
    """(pycocotools COCO, image ids, images (N, H, W, 3), label images (N, H, W), altitudes (N,)) of an export."""
    try:
        from pycocotools.coco import COCO
    except ImportError:
        raise UavsearchError("box AP needs pycocotools: pip install 'uavsearch[dataset]'") from None
    folder = Path(folder)
    if not (folder / "coco_annotations.json").is_file() or not (folder / "export.json").is_file():
        raise UavsearchError(f"{folder} is not a COCO export (uavsearch dataset export --format coco)")
    meta = json.loads((folder / "export.json").read_text())
    with contextlib.redirect_stdout(io.StringIO()):
        coco = COCO(str(folder / "coco_annotations.json"))
    grid, intr = Grid(**meta["grid"]), CameraIntrinsics(**meta["camera"])
    ids = sorted(coco.imgs)
    images, labels, alts = [], [], []
    for i in ids:
        im = coco.imgs[i]
        images.append(cv2.cvtColor(cv2.imread(str(folder / im["file_name"])), cv2.COLOR_BGR2RGB))
        cam = im["camera"]
        pose = CameraPose(np.asarray(cam["position_enu"], float), np.asarray(cam["R_enu_from_cam"], float))
        labels.append(cell_label_image(grid, intr, pose))
        alts.append(cam["altitude_m"])
    return coco, ids, np.stack(images), np.stack(labels), np.asarray(alts, np.float32), meta


def head_boxes(prob: np.ndarray, threshold: float) -> list[tuple[list[float], float]]:
    """Connected components of prob > threshold as ([x, y, w, h], highest probability inside)."""
    n, comp, stats, _ = cv2.connectedComponentsWithStats((prob > threshold).astype(np.uint8), connectivity=8)
    best = np.zeros(n)
    np.maximum.at(best, comp.ravel(), prob.ravel())
    return [([float(v) for v in stats[k, :4]], float(best[k])) for k in range(1, n)]


def footprint_boxes(label: np.ndarray, p: np.ndarray) -> list[tuple[list[float], float]]:
    out = []
    for c in np.unique(label[label >= 0]):
        rows, cols = np.nonzero(label == c)
        out.append(([float(cols.min()), float(rows.min()), float(cols.max() - cols.min() + 1),
                     float(rows.max() - rows.min() + 1)], float(p[c])))
    return out


@torch.no_grad()
def detections(net, images, labels, alts, thresholds=(0.3, 0.5), batch: int = 16) -> dict[str, list[list]]:
    """Per reading (name -> per image a list of (box, score)): the person head at each threshold and the cell
    footprints of a pooled net, or a detector's own boxes."""
    out: dict[str, list[list]] = {}
    for s in range(0, len(images), batch):
        sl = slice(s, s + batch)
        o = net.forward_all(images[sl], labels[sl], altitude_m=alts[sl])
        if isinstance(net, DetectorPerception):
            for d in net.detect(images[sl]):
                d = as_detections(d, images.shape[1:3])
                out.setdefault("detector boxes", []).append(
                    [([float(b[0]), float(b[1]), float(b[2] - b[0]), float(b[3] - b[1])], float(sc))
                     for b, sc in zip(d.boxes, d.scores)])
        elif o.person_logits is not None:
            prob = F.interpolate(torch.sigmoid(o.person_logits), size=images.shape[1:3], mode="bilinear",
                                 align_corners=False)[:, 0].cpu().numpy()
            for t in thresholds:
                out.setdefault(f"person head, components > {t:g}", []).extend(head_boxes(p, t) for p in prob)
        p = o.log_probs[..., 1].exp().cpu().numpy()
        footprints = out.setdefault("cell footprints, p(occupied)", [])
        footprints.extend(footprint_boxes(lab, q) for lab, q in zip(labels[sl], p))
    return out


def box_ap(coco, ids, dets: list[list]) -> dict[str, float]:
    """COCOeval's twelve box statistics (AP at IoU 0.5:0.95, 0.5, 0.75, by size; AR) of per-image detections."""
    from pycocotools.cocoeval import COCOeval

    res = [{"image_id": i, "category_id": 1, "bbox": box, "score": score}
           for i, per in zip(ids, dets) for box, score in per]
    if not res:
        return {k: 0.0 for k in STATS}
    with contextlib.redirect_stdout(io.StringIO()):
        ev = COCOeval(coco, coco.loadRes(res), "bbox")
        ev.evaluate()
        ev.accumulate()
        ev.summarize()
    return dict(zip(STATS, (float(v) for v in ev.stats)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--coco", required=True, help="an exported COCO folder (uavsearch dataset export --format coco)")
    ap.add_argument("--perception", default=None, help="a checkpoint or detector:NAME (default: the export "
                                                       "setting's shipped net)")
    ap.add_argument("--thresholds", default="0.3,0.5", help="person head: probability thresholds of the components")
    args = ap.parse_args(argv)
    return run_command(_run, args, prog="perception_box_ap")


def _run(args) -> int:
    coco, ids, images, labels, alts, meta = load_export(args.coco)
    path = args.perception or str(shipped_perception(meta.get("setting")))
    net, _ = load_perception(path)
    net = net.eval().for_grid(Grid(**meta["grid"]).num_cells)
    thresholds = tuple(float(t) for t in args.thresholds.split(","))
    found = detections(net, images, labels, alts, thresholds)
    n_people = len(coco.anns)
    print(f"COCO box AP (pycocotools COCOeval, person) of {path} on {len(ids)} views of {args.coco} "
          f"({n_people} people; {meta.get('setting')} {meta.get('part')}; every person is COCO-small)\n")
    print("| boxes from | AP | AP50 | AP75 | AR100 | detections per view |")
    print("|---|---|---|---|---|---|")
    for name, dets in found.items():
        s = box_ap(coco, ids, dets)
        print(f"| {name} | {s['AP']:.3f} | {s['AP50']:.3f} | {s['AP75']:.3f} | {s['AR100']:.3f} | "
              f"{np.mean([len(d) for d in dets]):.1f} |")
    return 0
