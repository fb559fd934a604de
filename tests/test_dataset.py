"""View-set generation (real renders of tiny scene sets), its cache format, and the stage-1 smoke run."""

import json

import numpy as np
import pytest
import torch

from uavsearch.errors import UavsearchError
from uavsearch.search.data.dataset import (
    ViewSetSpec,
    generate_views,
    load_views,
    perception_scenes,
    positions_for_scene,
    shard_path,
)

# The smoke training run below (seed 3, 2 training scenes x 2 views) finds these shards and renders only
# its validation scene.
SPEC = ViewSetSpec("train_v2_s3", perception_scenes("train", 2, 3), views_per_scene=2, seed=3)
(S0, K0), (S1, K1) = SPEC.scenes


@pytest.fixture(scope="module")
def tiny_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("views") / "train_v2_s3"
    generate_views(SPEC, root, workers=1, progress=False)
    return root


def test_positions_are_deterministic_distinct_and_include_the_start():
    a = positions_for_scene(SPEC, S0, K0, 25)
    assert np.array_equal(a, positions_for_scene(SPEC, S0, K0, 25))
    assert 12 in a and len(set(a.tolist())) == 2
    spec9 = ViewSetSpec("x", SPEC.scenes, views_per_scene=9, seed=5)
    b = positions_for_scene(spec9, S0, K0, 25)
    assert len(set(b.tolist())) == 9 and 12 in b


def test_perception_scenes_avoid_test_seeds_and_cover_densities():
    from uavsearch.world.settings import density_scenes, scene_seeds

    train = perception_scenes("train", 60, seed=1)
    seeds = {s for s, _ in train}
    test = {s for st in (1, 2, 3) for sp in ("paper", "large") for s in scene_seeds(st, sp, "test")}
    test |= {s for s, _ in density_scenes()}
    assert not seeds & test
    assert not seeds & {s for s, _ in perception_scenes("val", 30, seed=1)}
    assert {k for _, k in train} <= set(range(1, 13)) and len({k for _, k in train}) >= 8
    assert train == perception_scenes("train", 60, seed=1)


def test_shards_hold_the_documented_arrays(tiny_root):
    man = json.loads((tiny_root / "manifest.json").read_text())
    assert man["format"] == "uavsearch-views/2" and man["spec"]["views_per_scene"] == 2
    with np.load(shard_path(tiny_root, S0, K0)) as z:
        assert z["images"].shape == (2, 224, 224, 3) and z["images"].dtype == np.uint8
        assert z["cell_area_px"].shape == (2, 100) and z["cells_in_view"].dtype == bool
        assert int(z["occupancy"].sum()) == K0 and int(z["occupied_cells"]) == K0
        assert z["person_px"].shape == (2, 100)
        assert z["person_frac"].shape == (2, *z["images"].shape[1:3]) and z["person_frac"].dtype == np.uint8
        # the dense target agrees with the per-cell counts: a cell counts a pixel iff some person covers it
        assert (z["person_frac"] > 0).sum() >= z["person_px"].sum() > 0


def test_load_views_and_label_images(tiny_root):
    vs = load_views(tiny_root)
    assert len(vs) == 4
    assert vs.occupancy.sum(1).tolist() == [K0, K0, K1, K1]
    lab = vs.label_images(np.arange(4))
    assert lab.shape == (4, 224, 224)
    # The label image agrees with the stored pixel areas (exact pixel counts vs polygon areas).
    counts = np.bincount(lab[0][lab[0] >= 0].astype(int), minlength=100)
    assert np.abs(counts - vs.cell_area_px[0]).max() < 30
    start = load_views(tiny_root, start_only=True)
    assert len(start) == 2 and (start.lattice_index == 12).all()


def test_resume_rerenders_a_missing_shard_identically(tiny_root):
    path = shard_path(tiny_root, S1, K1)
    with np.load(path) as z:
        before = z["images"].copy()
    path.unlink()
    generate_views(SPEC, tiny_root, workers=1, progress=False)
    with np.load(path) as z:
        assert np.array_equal(z["images"], before)


def test_a_different_spec_in_the_same_directory_is_refused(tiny_root):
    other = ViewSetSpec("train_v2_s3", SPEC.scenes, views_per_scene=3, seed=3)
    with pytest.raises(UavsearchError, match="different view set"):
        generate_views(other, tiny_root, workers=1, progress=False)
    with pytest.raises(UavsearchError, match="not a view set"):
        load_views(tiny_root / "nowhere")


def test_a_set_of_an_older_format_is_rendered_again_in_place(tiny_root, tmp_path):
    import shutil

    root = tmp_path / "old"
    shutil.copytree(tiny_root, root)
    man = json.loads((root / "manifest.json").read_text())
    man["format"] = "uavsearch-views/1"  # as an older version of this code wrote it
    for entry in man["shards"].values():
        entry["tag"] = "older-renderer"
    (root / "manifest.json").write_text(json.dumps(man))
    generate_views(SPEC, root, workers=1, progress=False)
    new = json.loads((root / "manifest.json").read_text())
    assert new["format"] == "uavsearch-views/2"
    assert all(e["tag"] != "older-renderer" for e in new["shards"].values())
    with np.load(shard_path(root, S0, K0)) as z, np.load(shard_path(tiny_root, S0, K0)) as ref:
        assert np.array_equal(z["images"], ref["images"]) and "person_frac" in z.files


@pytest.mark.slow  # trains (about 25 s): `make test-all` runs it
def test_stage1_smoke_trains_resumes_and_writes_a_run(tmp_path):
    from uavsearch.search.perception import load_perception
    from uavsearch.search.train.perception import Args, train

    args = Args(exp_name="smoke", seed=3, settings="2", train_scenes=1, val_scenes=1, data_dir=str(tmp_path / "cache"),
                workers=1, steps=4, batch_size=4, eval_every=2, out=str(tmp_path / "p.pt"),
                runs_dir=str(tmp_path / "runs"), progress=False)
    rep = train(args)
    run = next((tmp_path / "runs").iterdir())
    assert {"args.json", "metrics.csv", "learning_curve.png", "perception.pt", "last.pt", "report.json"} <= {
        p.name for p in run.iterdir()}
    lines = (run / "metrics.csv").read_text().splitlines()
    assert lines[0].startswith("step,") and len(lines) == 5
    assert rep["train_views"] == 25 and rep["val_views"] == 25  # every lattice position of one scene each
    assert 0.0 <= rep["eval/aacc"] <= 1.0 and 0.0 <= rep["eval/cell_ap"] <= 1.0
    net, extra = load_perception(tmp_path / "p.pt")
    assert extra["args"]["steps"] == 4 and net.cfg.person_head
    # Same seed, same data -> same weights (determinism), and the renders are reused, not redone.
    args2 = Args(**{**args.__dict__, "out": str(tmp_path / "p2.pt"), "runs_dir": str(tmp_path / "runs2")})
    train(args2)
    net2, _ = load_perception(tmp_path / "p2.pt")
    for (k, a), (_, b) in zip(net.state_dict().items(), net2.state_dict().items()):
        assert torch.equal(a, b), k
    # A rerun continues: two more steps on the first run, its metrics file grows without repeats.
    train(Args(**{**args.__dict__, "steps": 6, "resume": str(run)}))
    steps = [int(line.split(",")[0]) for line in (run / "metrics.csv").read_text().splitlines()[1:]]
    assert steps == [1, 2, 3, 4, 5, 6]


@pytest.mark.slow  # renders two wide scenes (146 views): about a minute on two busy cores
def test_stage1_on_a_scene_family_trains_across_both_altitudes(tmp_path):
    from uavsearch.paths import MODELS_DIR
    from uavsearch.search.perception import load_perception
    from uavsearch.search.train.perception import Args, shipped_path, train

    args = Args(exp_name="wide", seed=1, settings="wide", split="paper", train_scenes=1, val_scenes=1,
                data_dir=str(tmp_path / "cache"), workers=1, steps=2, batch_size=4, eval_every=2,
                altitude_feature=True, out=str(tmp_path / "w.pt"), runs_dir=str(tmp_path / "runs"), progress=False)
    rep = train(args)
    assert rep["train_views"] == 73 and rep["val_views"] == 73  # every viewpoint of the family's lattice
    net, _ = load_perception(tmp_path / "w.pt")
    assert net.cfg.altitude_feature and net.cfg.num_cells == 900
    assert shipped_path("wide") == MODELS_DIR / "perception_wide.pt"
    assert shipped_path("1,2,3") == MODELS_DIR / "perception.pt"


def test_table1_scenes_are_balanced_per_density_pair_and_disjoint_from_training():
    from uavsearch.search.evaluate.single_view import PAPER_TABLE1, density_test_scenes

    scenes, pairs = density_test_scenes(4)
    assert len(scenes) == 24
    for (s, k), pair in zip(scenes, pairs):
        assert k in pair
    assert {p for p in pairs} == set(PAPER_TABLE1)
    assert not {s for s, _ in scenes} & {s for s, _ in perception_scenes("train", 150, seed=1)}
    with pytest.raises(UavsearchError, match="scenes per pair"):
        density_test_scenes(0)
