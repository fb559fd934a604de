"""Scene generation: determinism, exact K, exact round trips, clear errors, disjoint splits."""

import hashlib
import json

import numpy as np
import pytest

from uavsearch.errors import SceneError
from uavsearch.geometry import GeodeticOrigin, Grid
from uavsearch.world.scene import (
    GENERATOR_VERSION,
    generate_scene,
    load_scene,
    save_scene,
    scene_from_json,
    scene_to_json,
)
from uavsearch.world.settings import SCENE_FAMILIES, SETTINGS, all_seed_sets, density_scenes, resolve_k, scene_seeds

# sha256 of scene_to_json(generate_scene(seed, K)), computed before the scene parameters (grid, placement)
# existed: the paper's scenes must keep their bytes.
PAPER_SCENE_SHA256 = {
    (0, 2): "902351d84f054fdc9d6b522f2ab5b8fe90c28bb296c1e1de4a1a7bef5ba62716",
    (1000, 2): "76c1d51dd000e6527e2caf6e3d52a63ecc8b49de2112df8ba413993e5cf51d7e",
    (2205, 10): "d96792e246976162b29eb88aa4c11b99107c35f5d78b6cb3bdf939f81271f34f",
    (11, 100): "ff4b36640ba62c3d44685674ec2a568d8b91549c883aa4060e25b2c536e7d964",
    (7, 0): "d36da3d2df47c799ee4829d49f4d7a6169441d23c5749912e983303f95e3641e",
}


@pytest.fixture(scope="module")
def scene5():
    return generate_scene(3, 5)


def test_same_seed_gives_byte_identical_json(scene5):
    assert scene_to_json(generate_scene(3, 5)) == scene_to_json(scene5)
    assert scene_to_json(generate_scene(4, 5)) != scene_to_json(scene5)
    assert hashlib.sha256(scene_to_json(scene5).encode()).hexdigest() == \
        "1f1c00c9036a15f5498b19ab85a3cfd12f01071cc8d62a38661ce761a7889e52"


@pytest.mark.parametrize("seed_k", sorted(PAPER_SCENE_SHA256))
def test_paper_scenes_keep_their_bytes(seed_k):
    text = scene_to_json(generate_scene(*seed_k))
    assert hashlib.sha256(text.encode()).hexdigest() == PAPER_SCENE_SHA256[seed_k]
    assert '"placement"' not in text and '"group' not in text


@pytest.mark.parametrize("k", [0, 1, 2, 5, 10, 100])
def test_exactly_k_cells_occupied(k):
    spec = generate_scene(11, k)
    occ = spec.occupancy_array()
    assert occ.shape == (100,) and occ.dtype == np.int8 and int(occ.sum()) == k
    # the map agrees with where the people stand
    grid = spec.grid
    people = [o for o in spec.objects if o.kind == "person"]
    cells = grid.cell_of_points(np.array([p.x_m for p in people]), np.array([p.y_m for p in people]))
    assert set(int(c) for c in cells if c >= 0) == set(np.flatnonzero(occ).tolist())
    assert all(int(c) == p.cell for c, p in zip(cells, people))
    # a person inside the grid stands clear of its cell's borders; people outside keep away from the grid
    m = spec.params.cell_margin_m
    for p in people:
        if p.cell >= 0:
            fx = (p.x_m + grid.half_m) % grid.cell_m
            fy = (p.y_m + grid.half_m) % grid.cell_m
            assert m - 1e-3 <= fx <= grid.cell_m - m + 1e-3 and m - 1e-3 <= fy <= grid.cell_m - m + 1e-3
        else:
            assert max(abs(p.x_m), abs(p.y_m)) >= grid.half_m + spec.params.outside_margin_m - 1e-3


def test_people_do_not_stand_inside_buildings_or_cars(scene5):
    from uavsearch.world.scene import footprint_corners

    solids = [o for o in scene5.objects if o.kind in ("building", "car")]
    for p in scene5.people:
        for o in solids:
            c = footprint_corners(o)
            lo, hi = c.min(0), c.max(0)
            if o.yaw_rad == 0.0:
                assert not (lo[0] < p.x_m < hi[0] and lo[1] < p.y_m < hi[1]), (p, o)


@pytest.mark.parametrize("k", [-1, 101, 1000])
def test_k_out_of_range_is_a_scene_error(k):
    with pytest.raises(SceneError, match="out of range"):
        generate_scene(1, k)


def test_scene_contents(scene5):
    kinds = {o.kind for o in scene5.objects}
    assert {"road", "sidewalk", "marking", "building", "tree", "car", "clutter", "person"} <= kinds
    assert scene5.generator_version == GENERATOR_VERSION
    assert isinstance(scene5.grid, Grid) and scene5.grid.n == 10 and scene5.grid.cell_m == 5.0
    assert isinstance(scene5.home, GeodeticOrigin)
    # the rendered city reaches well beyond the search area
    xs = [o.x_m for o in scene5.objects if o.kind == "building"]
    assert max(xs) > 60 and min(xs) < -60
    # people vary in size, pose and clothing
    people = scene5.people
    assert len({p.variant for p in people}) >= 2 and len({p.color for p in people}) > 5
    assert max(p.sz_m for p in people) - min(p.sz_m for p in people) > 0.2


def test_save_load_round_trip(tmp_path, scene5):
    path = save_scene(scene5, tmp_path / "s.json")
    back = load_scene(path)
    assert back == scene5
    assert scene_to_json(back) == scene_to_json(scene5)


@pytest.mark.parametrize(
    "mutate",
    [
        lambda t: t[: len(t) // 2],  # truncated
        lambda t: "not json at all",
        lambda t: json.dumps({**json.loads(t), "occupancy": [0] * 99}),
        lambda t: json.dumps({**json.loads(t), "occupied_cells_k": 7}),
        lambda t: json.dumps({k: v for k, v in json.loads(t).items() if k != "objects"}),
        lambda t: t.replace('"kind":"person"', '"kind":"alien"', 1),
    ],
)
def test_corrupt_json_is_a_scene_error(tmp_path, scene5, mutate):
    text = mutate(scene_to_json(scene5))
    with pytest.raises(SceneError, match="corrupt scene JSON"):
        scene_from_json(text)
    (tmp_path / "bad.json").write_text(text)
    with pytest.raises(SceneError):
        load_scene(tmp_path / "bad.json")


def test_missing_file_is_a_scene_error(tmp_path):
    with pytest.raises(SceneError, match="cannot read"):
        load_scene(tmp_path / "nope.json")


def test_settings_and_splits():
    assert SETTINGS == {1: 2, 2: 5, 3: 10}
    assert [len(scene_seeds(s, "paper", p)) for s in (1, 2, 3) for p in ("train", "val", "test")] == [20, 10, 10] * 3
    assert len(scene_seeds(2, "large", "train")) == 500 and len(scene_seeds(2, "large", "test")) == 100
    sets = all_seed_sets()
    assert {f"large/setting{f}/{p}" for f in ("wide", "wide-uniform") for p in ("train", "val", "test")} <= set(sets)
    assert list(SCENE_FAMILIES) == [1, 2, 3, "wide", "wide-uniform"]
    seen: dict[int, str] = {}
    for name, seeds in sets.items():
        assert len(set(seeds)) == len(seeds)
        for s in seeds:
            assert s not in seen, f"seed {s} in {name} and {seen[s]}"
            seen[s] = name
    dens = density_scenes()
    assert sorted({k for _, k in dens}) == list(range(1, 13)) and len(dens) == 6 * 80
    assert resolve_k(3) == 10 and resolve_k(42, is_setting=False) == 42


@pytest.mark.parametrize(
    "args, match",
    [((4, "paper", "train"), "unknown setting 4; valid: 1, 2, 3, wide, wide-uniform"), ((1, "huge", "train"), "unknown split"),
     ((1, "paper", "dev"), "unknown part")],  # fmt: skip
)
def test_bad_settings_are_one_line_errors(args, match):
    with pytest.raises(SceneError, match=match) as e:
        scene_seeds(*args)
    assert "\n" not in str(e.value)


def test_the_kept_running_sum_draws_what_a_fresh_one_would_as_people_take_their_places():
    from uavsearch.world.scene import Raster, _PointSampler, _sample_point

    raster = Raster(20.0, 0.2)
    weights = np.random.default_rng(0).random((raster.n, raster.n)).astype(np.float32)
    weights[weights < 0.3] = 0.0
    kept, fresh = weights.copy(), weights.copy()
    sampler = _PointSampler(kept, raster)
    a, b = np.random.default_rng(1), np.random.default_rng(1)
    for _ in range(40):
        got, want = sampler.draw(a), _sample_point(b, fresh, raster)
        assert got == want
        for w in (kept, fresh):
            raster.disk(w, got, 1.5, 0.0)
        row = float(raster.to_px(got)[1])
        sampler.rows_changed(int(row) - 10, int(row) + 10)
    # a box of a raster holding all its positive weights draws the same point as the whole raster
    sparse = np.zeros_like(weights)
    sparse[50:60, 70:85] = weights[50:60, 70:85]
    box = np.ascontiguousarray(sparse[45:62, 66:90])
    assert _PointSampler(box, raster, (45, 66)).draw(np.random.default_rng(2)) == \
        _sample_point(np.random.default_rng(2), sparse, raster)
