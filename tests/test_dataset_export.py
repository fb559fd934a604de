"""`uavsearch dataset export`: COCO read back by pycocotools, YOLO by its line format, resumable, one-line errors."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("pycocotools")
from pycocotools.coco import COCO  # noqa: E402

from uavsearch.cli import main  # noqa: E402
from uavsearch.search.config import setting_config  # noqa: E402
from uavsearch.search.data.dataset import make_scene  # noqa: E402
from uavsearch.search.data.dataset_export import ExportArgs, export_dataset  # noqa: E402
from uavsearch.search.views import TeleportVehicle  # noqa: E402
from uavsearch.world.settings import setting_params  # noqa: E402

SCENES, VIEWS = 2, 3


def _args(out, **kw) -> ExportArgs:
    return ExportArgs(out=str(out), setting="wide", part="train", scenes=SCENES, views=VIEWS, progress=False, **kw)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    out = tmp_path_factory.mktemp("export")
    path = export_dataset(_args(out))
    return out, path


@pytest.fixture(scope="module")
def rendered(exported):
    """The person index image of every exported view, rendered again here: the oracle of the labels."""
    _, path = exported
    coco = COCO(str(path))
    config = setting_config("wide")
    out = {}
    for seed in sorted({im["scene_seed"] for im in coco.imgs.values()}):
        with TeleportVehicle(make_scene(seed, setting_params("wide").k, "wide"), config, cache=False) as vehicle:
            for im in coco.imgs.values():
                if im["scene_seed"] == seed:
                    out[im["id"]] = vehicle.capture(config.lattice.positions_enu[im["lattice_index"]]).person_index
    return coco, out


def test_coco_counts_masks_and_poses(exported, rendered):
    coco, index = rendered
    assert len(coco.imgs) == SCENES * VIEWS
    assert [c["name"] for c in coco.loadCats(coco.getCatIds())] == ["person"]
    total = 0
    for image_id, pidx in index.items():
        anns = coco.loadAnns(coco.getAnnIds(imgIds=image_id))
        visible = np.unique(pidx[pidx >= 0])
        assert len(anns) == len(visible)  # one box per person the segmentation shows
        assert sorted(a["person_index"] for a in anns) == visible.tolist()
        for a in anns:
            mask = coco.annToMask(a).astype(bool)
            assert np.array_equal(mask, pidx == a["person_index"])
            assert mask.sum() == a["area"] > 0
            x, y, w, h = a["bbox"]
            rows, cols = np.nonzero(mask)
            assert (x, y, w, h) == (cols.min(), rows.min(), cols.max() - cols.min() + 1, rows.max() - rows.min() + 1)
        im = coco.imgs[image_id]
        assert im["camera"]["altitude_m"] in (70.0, 40.0)
        assert len(im["occupied_cells"]) == setting_params("wide").k
        assert {a["cell"] for a in anns if a["cell"] >= 0} <= set(im["occupied_cells"])
        total += len(anns)
    assert total > 0


def test_yolo_lines(exported, rendered):
    out, _ = exported
    coco, _ = rendered
    path = export_dataset(_args(out, format="yolo"))  # the same records, another layout: nothing rendered again
    assert "names:" in path.read_text()
    for im in coco.imgs.values():
        label = out / "labels" / (Path(im["file_name"]).stem + ".txt")
        lines = label.read_text().splitlines()
        assert len(lines) == len(coco.getAnnIds(imgIds=im["id"]))
        for line in lines:
            cls, *box = line.split()
            assert cls == "0" and len(box) == 4
            assert all(0.0 <= float(v) <= 1.0 for v in box)
    views = [json.loads(line) for line in (out / "views.jsonl").read_text().splitlines()]
    assert len(views) == len(coco.imgs) and "camera" in views[0]


def test_rerun_resumes(exported):
    out, path = exported
    before = path.read_bytes()
    images = sorted((out / "images").glob("*.png"))
    stamps = {p.name: p.stat().st_mtime_ns for p in images}
    gone = images[1]
    gone.unlink()
    (out / "records" / (gone.stem + ".json")).write_text('{"cut short')  # a record half written
    export_dataset(_args(out))
    assert path.read_bytes() == before
    after = {p.name: p.stat().st_mtime_ns for p in (out / "images").glob("*.png")}
    assert {k for k in after if after[k] != stamps.get(k)} == {gone.name}  # only the missing view was rendered


def test_bad_input_is_one_line(tmp_path, exported, capsys):
    out, _ = exported
    for argv, words in (
        (["--setting", "nowhere"], "unknown setting"),
        (["--setting", "wide", "--scenes", "0"], "--scenes must be"),
        (["--setting", "wide", "--part", "holdout"], "unknown part"),
        (["--setting", "wide", "--scenes", "1", "--views", "5", "--out", str(out)], "holds another export"),
        (["--run", str(tmp_path)], "not a flight's run folder"),
    ):
        if "--out" not in argv:
            argv = [*argv, "--out", str(tmp_path / "x")]
        assert main(["dataset", "export", "--no-progress", *argv]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and words in err, err
