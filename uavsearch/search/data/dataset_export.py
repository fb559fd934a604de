"""Labelled datasets out: rendered views with person boxes and instance masks, in COCO or YOLO.

`uavsearch dataset export --setting wide --part train --scenes N --format coco|yolo --out DIR` renders the
lattice views of a scene family's scenes (exactly the teleport camera's pixels, the ones the view caches hold)
and labels every person the renderer's segmentation shows: each person is its own body, so the person index
image (world/render.py) gives exact instance masks, and a person hidden by a roof or a canopy has no box.
`--run RUN_DIR` exports the photos of a flown run instead, labelled by rendering its scene again at each
photo's true camera pose (the pose the camera drew it from).

The folder (written as it goes, resumable: a view whose image and record are on disk is never rendered again):

    export.json                 what was exported (setting, split, part, camera, grid, render fingerprint); a rerun
                                into a folder holding another export is refused in one line
    images/<stem>.png           the views (RGB, north up), written whole or not at all
    records/<stem>.json         per view: camera pose and altitude, occupied cells, cells in view, and every
                                visible person (index in the scene spec, cell, box, RLE mask, area)
    coco_annotations.json       (coco) as BlenderProc writes it: info, licenses, categories, images (each also
                                with its camera, scene seed, lattice index, occupied cells), annotations with
                                compressed RLE masks (pycocotools.mask), ids from 1
    labels/<stem>.txt, data.yaml, views.jsonl
                                (yolo) one `0 cx cy w h` line per box (normalised to [0, 1]), the Ultralytics
                                dataset file, and per image its camera, scene and occupied cells

Boxes are the masks' bounding boxes (pycocotools.mask.toBbox), so box, mask and area always agree.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from uavsearch.cli_args import add_dataclass_args, dataclass_from_args, opt
from uavsearch.errors import UavsearchError
from uavsearch.geometry import CameraIntrinsics, CameraPose, Grid, camera_pose_from_vehicle, nadir_camera_pose
from uavsearch.parallel import Store
from uavsearch.world import settings

from ..config import SearchConfig, setting_config
from ..views import TeleportVehicle, View, make_view
from .dataset import make_scene, render_tag

FORMAT = "uavsearch-dataset/1"
FORMATS = ("coco", "yolo")
PERSON = {"id": 1, "name": "person", "supercategory": "person"}


def _mask_api():
    try:
        from pycocotools import mask
    except ImportError:
        raise UavsearchError("dataset export needs pycocotools: pip install 'uavsearch[dataset]'") from None
    return mask


@dataclass
class ExportArgs:
    out: str = opt(None, "output folder (a rerun into it resumes)", required=True)
    setting: str = opt("wide", "scene family or paper setting whose scenes and lattice are exported (wide, "
                               "wide-uniform, 1, 2, 3)")
    part: str = opt("train", "scene part: train | val | test")
    split: str | None = opt(None, "scene split (default: the setting's own: large for the families, paper for 1-3)")
    scenes: int | None = opt(None, "the part's first N scenes (default: all of them)")
    views: int | None = opt(None, "per scene, N lattice viewpoints drawn with --seed, the start among them "
                                  "(default: every viewpoint)")
    seed: int = opt(0, "seed of the viewpoints drawn with --views")
    format: str = opt("coco", "coco (coco_annotations.json + images/) | yolo (labels/*.txt + data.yaml)",
                      choices=FORMATS)
    run: str | None = opt(None, "a flown run's folder (uavsearch fly --out): export its photos instead of lattice "
                                "views (--setting, --part, --scenes, --views are then unused)")
    progress: bool = opt(True, "progress bar")


# --------------------------------------------------------------------------------------------------
# One view's labels


def view_record(view: View, spec, grid: Grid, intrinsics: CameraIntrinsics, **extra) -> dict:
    """The labels of one rendered view (it must carry its person index image): every visible person's mask,
    box and area, the camera, and the scene's occupied cells."""
    if view.person_index is None:
        raise UavsearchError("this view carries no person segmentation (a teleport render has it)")
    mask_api = _mask_api()
    people = spec.people
    pidx = np.asarray(view.person_index)
    xy = np.array([[p.x_m, p.y_m] for p in people]) if people else np.zeros((0, 2))
    cells = grid.cell_of_points(xy[:, 0], xy[:, 1]) if len(xy) else np.zeros(0, np.int64)
    out = []
    for i in np.unique(pidx[pidx >= 0]).tolist():
        rle = mask_api.encode(np.asfortranarray(pidx == i, dtype=np.uint8))
        out.append({"person_index": int(i), "cell": int(cells[i]),
                    "position_enu": [round(float(people[i].x_m), 3), round(float(people[i].y_m), 3)],
                    "bbox": [float(v) for v in mask_api.toBbox(rle)], "area": int(mask_api.area(rle)),
                    "segmentation": {"size": [int(s) for s in rle["size"]], "counts": rle["counts"].decode("ascii")}})
    pose = view.pose
    return {
        **extra,
        "width": intrinsics.width_px, "height": intrinsics.height_px,
        "camera": {"position_enu": [round(float(v), 4) for v in pose.position_enu],
                   "R_enu_from_cam": np.round(pose.R_enu_from_cam, 6).tolist(),
                   "altitude_m": round(float(pose.position_enu[2]), 4),
                   "fx": intrinsics.fx, "fy": intrinsics.fy, "cx": intrinsics.cx, "cy": intrinsics.cy,
                   "hfov_deg": intrinsics.hfov_deg},
        "occupied_cells": [int(c) for c in np.flatnonzero(spec.occupancy_array())],
        "cells_in_view": [int(c) for c in np.flatnonzero(view.cells_in_view)],
        "people": out,
    }


# --------------------------------------------------------------------------------------------------
# The folder


class ExportFolder:
    """The export's folder: its manifest, the images and records written so far, and the final files."""

    def __init__(self, out, manifest: dict):
        self.root = Path(out)
        self.store = Store(self.root)
        old = self.store.read_json("export.json")
        if old is not None and {k: v for k, v in old.items() if k != "scenes"} != {k: v for k, v in manifest.items()
                                                                                  if k != "scenes"}:
            diff = sorted(k for k in set(old) | set(manifest) if k != "scenes" and old.get(k) != manifest.get(k))
            raise UavsearchError(f"{self.root} holds another export ({', '.join(diff)} differ); choose another "
                                 "folder or delete it")
        self.store.write_json("export.json", manifest)

    def done(self, stem: str) -> bool:
        return self.store.exists(f"images/{stem}.png") and self.record(stem) is not None

    def record(self, stem: str) -> dict | None:
        try:
            return self.store.read_json(f"records/{stem}.json")
        except UavsearchError:  # a record cut short: the view is labelled again
            return None

    def write_image(self, stem: str, rgb: np.ndarray) -> None:
        ok, png = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR))
        if not ok:
            raise UavsearchError(f"could not encode {stem}.png")
        self.store.write_bytes(f"images/{stem}.png", png.tobytes())

    def write_record(self, stem: str, record: dict) -> None:
        """After its image: a record on disk means the view is finished."""
        self.store.write_bytes(f"records/{stem}.json", json.dumps(record, separators=(",", ":")).encode())

    def finish(self, stems: list[str], fmt: str, info: dict) -> Path:
        records = []
        for stem in stems:
            r = self.record(stem)
            if r is None:
                raise UavsearchError(f"{self.root}: the record of {stem} is missing; run the export again")
            records.append(r)
        return write_coco(self.root, records, info) if fmt == "coco" else write_yolo(self.root, records, info)


def write_coco(root: Path, records: list[dict], info: dict) -> Path:
    """coco_annotations.json as BlenderProc lays it out; image and annotation ids count from 1."""
    images, annotations = [], []
    for image_id, r in enumerate(records, 1):
        images.append({"id": image_id, "file_name": r["file_name"], "width": r["width"], "height": r["height"],
                       "license": 1, **{k: r[k] for k in ("scene_seed", "lattice_index", "camera", "occupied_cells",
                                                          "cells_in_view") if k in r}})
        for p in r["people"]:
            annotations.append({"id": len(annotations) + 1, "image_id": image_id, "category_id": PERSON["id"],
                                "iscrowd": 0, "area": p["area"], "bbox": p["bbox"], "segmentation": p["segmentation"],
                                "person_index": p["person_index"], "cell": p["cell"]})
    doc = {"info": info, "licenses": [{"id": 1, "name": "generated by uavsearch", "url": ""}],
           "categories": [PERSON], "images": images, "annotations": annotations}
    Store(root).write_bytes("coco_annotations.json", json.dumps(doc, separators=(",", ":")).encode())
    return root / "coco_annotations.json"


def yolo_lines(record: dict) -> list[str]:
    """`0 cx cy w h` per person, normalised by the image size."""
    w, h = float(record["width"]), float(record["height"])
    return [f"0 {(x + bw / 2) / w:.6f} {(y + bh / 2) / h:.6f} {bw / w:.6f} {bh / h:.6f}"
            for x, y, bw, bh in (p["bbox"] for p in record["people"])]


def write_yolo(root: Path, records: list[dict], info: dict) -> Path:
    """labels/<stem>.txt beside images/<stem>.png (an image without people gets an empty file), data.yaml and
    views.jsonl (the camera, scene and occupied cells of each image)."""
    store = Store(root)
    for r in records:
        stem = Path(r["file_name"]).stem
        store.write_bytes(f"labels/{stem}.txt", "".join(line + "\n" for line in yolo_lines(r)).encode())
    store.write_bytes("views.jsonl", "".join(json.dumps({k: v for k, v in r.items() if k != "people"} | {
        "people": [{k: p[k] for k in ("person_index", "cell", "position_enu", "bbox", "area")} for p in r["people"]]},
        separators=(",", ":")) + "\n" for r in records).encode())
    part = info.get("part", "train")
    lines = [f"# {info['description']}", f"# this folder is the {part} part; point val at another part's export",
             f"path: {root.resolve().as_posix()}", "train: images", "val: images", "names:", "  0: person", ""]
    store.write_bytes("data.yaml", "\n".join(lines).encode())
    return root / "data.yaml"


# --------------------------------------------------------------------------------------------------
# Lattice views and flown runs


def lattice_positions(config: SearchConfig, scene_seed: int, views: int | None, seed: int) -> np.ndarray:
    """Lattice indices exported for one scene: all of them, or `views` drawn per scene (the start first)."""
    n = config.lattice.num_positions
    if views is None or views >= n:
        return np.arange(n)
    start = config.lattice.start_index
    rng = np.random.default_rng([int(seed), int(scene_seed)])
    others = rng.choice(np.delete(np.arange(n), start), views - 1, replace=False)
    return np.sort(np.concatenate([[start], others])).astype(np.int64)


def _setting(text: str):
    found = settings.parse_settings(text, flag="--setting", families=True)
    if len(found) != 1:
        raise UavsearchError(f"--setting: export one setting at a time, not {text!r}")
    return found[0]


def export_lattice(args: ExportArgs) -> Path:
    setting = _setting(args.setting)
    fam = settings.setting_params(setting)
    split = args.split or fam.split
    if split not in settings.splits():
        raise UavsearchError(f"unknown split {split!r}; valid: {', '.join(settings.splits())}")
    if args.part not in ("train", "val", "test"):
        raise UavsearchError(f"unknown part {args.part!r}; valid: train, val, test")
    seeds = settings.scene_seeds(setting, split, args.part)
    if args.scenes is not None and not 1 <= args.scenes <= len(seeds):
        raise UavsearchError(f"--scenes must be 1 to {len(seeds)} (the {split} split's {args.part} part), "
                             f"not {args.scenes}")
    if args.views is not None and args.views < 1:
        raise UavsearchError(f"--views must be at least 1, not {args.views}")
    seeds = seeds[: args.scenes]
    config = setting_config(setting)
    family = None if fam.generic_scenes else fam.name
    manifest = {"format": FORMAT, "source": "lattice", "setting": str(setting), "split": split, "part": args.part,
                "views": args.views, "seed": args.seed, "camera": asdict(config.intrinsics),
                "grid": asdict(config.grid), "render": config.render_key(), "renderer": render_tag(family),
                "scenes": len(seeds)}
    folder = ExportFolder(args.out, manifest)
    jobs = [(int(s), int(i)) for s in seeds for i in lattice_positions(config, s, args.views, args.seed)]
    stems = [f"s{s}_p{i:03d}" for s, i in jobs]
    todo: dict[int, list[int]] = {}
    for (s, i), stem in zip(jobs, stems):
        if not folder.done(stem):
            todo.setdefault(s, []).append(i)
    lattice = config.lattice.positions_enu
    with tqdm(total=len(jobs), initial=len(jobs) - sum(map(len, todo.values())), unit="view",
              desc=f"export {setting} {args.part}", disable=not args.progress) as bar:
        for s, idx in todo.items():
            spec = make_scene(s, fam.k, family)
            with TeleportVehicle(spec, config, cache=False) as vehicle:
                for i in idx:
                    view = vehicle.capture(lattice[i])
                    stem = f"s{s}_p{i:03d}"
                    folder.write_image(stem, view.image)
                    folder.write_record(stem, view_record(view, spec, config.grid, config.intrinsics,
                                                          file_name=f"images/{stem}.png", scene_seed=s,
                                                          lattice_index=i))
                    bar.update()
    info = {"description": f"uavsearch {setting} {split} {args.part}: {len(seeds)} scenes, lattice views",
            "version": FORMAT, "setting": str(setting), "split": split, "part": args.part}
    return folder.finish(stems, args.format, info)


def _run_captures(run: Path) -> list[tuple[str, Path, dict]]:
    """(stem, image path, capture line) of every photo of a run folder: its own captures.jsonl, or one per
    vehicle of a team (vehicle<I>/captures.jsonl)."""
    own = run / "captures.jsonl"
    logs = sorted([own] if own.is_file() else run.glob("vehicle*/captures.jsonl"))
    if not logs:
        raise UavsearchError(f"{run} holds no captures.jsonl: not a flight's run folder")
    out = []
    for log in logs:
        prefix = "" if log.parent == run else f"{log.parent.name}_"
        for n, line in enumerate(log.read_text().splitlines(), 1):
            try:
                c = json.loads(line)
            except json.JSONDecodeError:
                if n == len(log.read_text().splitlines()):
                    break  # a flight killed mid-write leaves its last line cut short
                raise UavsearchError(f"{log}:{n}: not a capture record") from None
            if not c.get("ok", True) or not c.get("true_position_enu_m"):
                continue
            image = log.parent / "images" / Path(str(c.get("path", ""))).name
            if not image.is_file():
                continue
            out.append((f"{prefix}{image.stem}", image, c))
    return out


def export_run(args: ExportArgs) -> Path:
    """The photos of a flown run, each labelled by the scene rendered again at its true camera pose."""
    from uavsearch.world.render import SceneRenderer
    from uavsearch.world.scene import load_scene

    run = Path(args.run)
    if not (run / "scene.json").is_file():
        raise UavsearchError(f"{run} is not a flight's run folder (no scene.json)")
    spec = load_scene(run / "scene.json")
    try:
        mission = json.loads((run / "mission.json").read_text())
        cam = mission.get("camera") or {}
        setting = (mission.get("scene") or {}).get("setting")
    except (OSError, json.JSONDecodeError, AttributeError):
        raise UavsearchError(f"{run}/mission.json is missing or not a mission record") from None
    intr = CameraIntrinsics(width_px=int(cam.get("width_px", 224)), height_px=int(cam.get("height_px", 224)),
                            hfov_deg=float(cam.get("hfov_deg", 60.0)))
    config = setting_config(settings.setting_key(setting)) if setting is not None else SearchConfig()
    grid = spec.grid
    captures = _run_captures(run)
    manifest = {"format": FORMAT, "source": "run", "run": run.resolve().as_posix(), "camera": asdict(intr),
                "grid": asdict(grid), "render": repr(config.render), "scenes": 1}
    folder = ExportFolder(args.out, manifest)
    todo = [c for c in captures if not folder.done(c[0])]
    renderer = None
    try:
        for stem, image, c in tqdm(todo, unit="photo", desc=f"export {run.name}", disable=not args.progress):
            if renderer is None:
                renderer = SceneRenderer(spec, intr, config.render)
            rgb = cv2.imread(str(image), cv2.IMREAD_COLOR)
            if rgb is None or rgb.shape[:2] != (intr.height_px, intr.width_px):
                raise UavsearchError(f"{image} is not a {intr.width_px}x{intr.height_px} photo of this run")
            r, p, y = c["true_rpy_rad"]
            pose: CameraPose = camera_pose_from_vehicle(np.asarray(c["true_position_enu_m"], float), r, p, y,
                                                        gimbal_stabilised=True)
            seg = renderer.render(pose)
            view = make_view(cv2.cvtColor(rgb, cv2.COLOR_BGR2RGB), pose, grid, intr, person_index=seg.person_index)
            folder.write_image(stem, view.image)
            folder.write_record(stem, view_record(view, spec, grid, intr, file_name=f"images/{stem}.png",
                                                  scene_seed=int(spec.seed), time_us=c.get("time_us")))
    finally:
        if renderer is not None:
            renderer.close()
    info = {"description": f"uavsearch flown run {run.name}: {len(captures)} photos", "version": FORMAT,
            "part": "train"}
    return folder.finish([c[0] for c in captures], args.format, info)


def export_dataset(args: ExportArgs) -> Path:
    """Write (or finish writing) the export; returns coco_annotations.json or data.yaml."""
    if args.format not in FORMATS:
        raise UavsearchError(f"--format must be one of {', '.join(FORMATS)}, not {args.format!r}")
    _mask_api()
    return export_run(args) if args.run is not None else export_lattice(args)


# --------------------------------------------------------------------------------------------------
# CLI


def add_dataset_parser(sub, help_text: str) -> None:
    """`uavsearch dataset export ...`."""
    ds = sub.add_parser("dataset", help=help_text)
    dsub = ds.add_subparsers(dest="dataset_cmd", required=True, metavar="{export}")
    p = dsub.add_parser("export", help="export lattice views (or a flown run's photos) with person boxes and "
                                       "instance masks from the renderer's segmentation")
    add_dataclass_args(p, ExportArgs)
    p.set_defaults(func=cmd_export)


def cmd_export(ns) -> int:
    out = export_dataset(dataclass_from_args(ExportArgs, ns))
    print(f"wrote {out}")
    return 0


__all__ = ["ExportArgs", "export_dataset", "view_record", "yolo_lines", "lattice_positions", "add_dataset_parser"]
