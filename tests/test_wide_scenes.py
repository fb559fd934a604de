"""The wide scene family: parameters, clustered people, exact occupancy, settings, and renders with many people."""

import numpy as np
import pytest

from uavsearch.errors import SceneError
from uavsearch.geometry import CameraIntrinsics, Grid, nadir_camera_pose, project_points
from uavsearch.world.render import Palette, RenderOptions, SceneRenderer
from uavsearch.world.scene import Placement, SceneParams, generate_scene, scene_from_json, scene_to_json
from uavsearch.world.settings import (
    SCENE_FAMILIES,
    generate_setting_scene,
    parse_settings,
    resolve_k,
    scene_seeds,
    setting_params,
)


@pytest.fixture(scope="module")
def wide():
    return generate_setting_scene("wide", scene_seeds("wide", part="test")[0])


def _assert_exact_occupancy(spec):
    grid, m = spec.grid, spec.params.cell_margin_m
    inside = [p for p in spec.people if p.cell >= 0]
    cells = grid.cell_of_points(np.array([p.x_m for p in spec.people]), np.array([p.y_m for p in spec.people]))
    assert [int(c) for c in cells] == [p.cell for p in spec.people]
    assert sorted({p.cell for p in inside}) == np.flatnonzero(spec.occupancy_array()).tolist()
    assert int(spec.occupancy_array().sum()) == spec.occupied_cells_k
    for p in inside:
        fx, fy = (p.x_m + grid.half_m) % grid.cell_m, (p.y_m + grid.half_m) % grid.cell_m
        assert m - 1e-3 <= fx <= grid.cell_m - m + 1e-3 and m - 1e-3 <= fy <= grid.cell_m - m + 1e-3
    for p in spec.people:
        if p.cell < 0:
            assert max(abs(p.x_m), abs(p.y_m)) >= grid.half_m + spec.params.outside_margin_m - 1e-3
    counts = np.bincount([p.cell for p in inside], minlength=grid.num_cells)[spec.occupancy_array() > 0]
    assert all(1 <= c <= spec.params.people_per_occupied_cell[1] for c in counts)


def test_wide_family_parameters(wide):
    fam = setting_params("wide")
    assert (fam.k, fam.grid_n, fam.cell_m, fam.placement.kind) == (10, 30, 5.0, "clustered")
    assert setting_params("wide-uniform").placement.kind == "uniform" and resolve_k("wide-uniform") == 10
    assert wide.grid == Grid(30, 5.0) and wide.grid.size_m == 150.0
    # every 70 m view over the outermost viewpoint (62.5 m) lands on city: footprint half 70 tan 30 deg
    reach = 62.5 + 70.0 * np.tan(np.radians(30.0))
    assert wide.params.city_half_m >= reach + 10 and wide.params.ground_half_m > wide.params.city_half_m
    city = [o for o in wide.objects if o.kind in ("block", "sidewalk", "road", "grass", "plaza", "parking")]
    assert max(o.x_m + o.sx_m / 2 for o in city) > reach and min(o.x_m - o.sx_m / 2 for o in city) < -reach
    assert max(o.y_m + o.sy_m / 2 for o in city) > reach and min(o.y_m - o.sy_m / 2 for o in city) < -reach
    xs = [o.x_m for o in wide.objects if o.kind == "building"]
    assert max(xs) > 75 and min(xs) < -75  # buildings beyond the search area


def test_clustered_scene_exact_and_grouped(wide):
    _assert_exact_occupancy(wide)
    g = len(wide.group_centres_m)
    assert 1 <= g <= 3 and all(max(abs(x), abs(y)) <= wide.grid.half_m for x, y in wide.group_centres_m)
    groups = {p.group for p in wide.people if p.cell >= 0}
    assert groups <= set(range(g)) and all(p.group == -1 for p in wide.people if p.cell < 0)
    # cells lie near their group's centre: closer on average than uniform cells lie to any centre
    c = wide.grid.centers_enu[:, :2]
    occ = np.flatnonzero(wide.occupancy_array())
    near = np.min(np.linalg.norm(c[occ][:, None] - np.array(wide.group_centres_m)[None], axis=-1), 1)
    assert np.median(near) < 3 * wide.placement.sigma_m


@pytest.mark.slow  # a statistic over many generated scenes (about 13 s): `make test-all` runs it
def test_clustered_cells_are_closer_together_than_uniform():
    def spread(setting):
        out = []
        for seed in scene_seeds(setting, part="val")[:4]:
            spec = generate_setting_scene(setting, seed)
            xy = spec.grid.centers_enu[np.flatnonzero(spec.occupancy_array()), :2]
            d = np.linalg.norm(xy[:, None] - xy[None], axis=-1)
            out.append(np.sort(d + np.eye(len(xy)) * 1e9, 1)[:, 0].mean())  # mean nearest-neighbour distance
        return float(np.mean(out))

    assert spread("wide") < 0.6 * spread("wide-uniform")


def test_seed_decides_everything_and_json_round_trips(wide):
    again = generate_setting_scene("wide", wide.seed)
    assert scene_to_json(again) == scene_to_json(wide)
    assert scene_from_json(scene_to_json(wide)) == wide
    other = generate_setting_scene("wide", wide.seed + 1)
    assert other.group_centres_m != wide.group_centres_m


@pytest.mark.parametrize("k", [0, 1, 60])
@pytest.mark.parametrize("kind", ["uniform", "clustered"])
def test_any_k_on_a_wide_grid(k, kind):
    spec = generate_scene(7, k, SceneParams(city_half_m=120.0), Grid(30, 5.0), Placement(kind=kind, groups=(2, 2)))
    _assert_exact_occupancy(spec)
    assert len(spec.group_centres_m) == (2 if kind == "clustered" and k else 0)


@pytest.mark.parametrize(
    "call, match",
    [(lambda: generate_scene(1, 901, SceneParams(city_half_m=120.0), Grid(30, 5.0)), "out of range"),
     (lambda: generate_scene(1, 2, grid=Grid(40, 5.0)), "does not fit"),
     (lambda: generate_scene(1, 2, placement=Placement(kind="clustered", groups=(3, 1))), "groups"),
     (lambda: setting_params("wider"), "unknown setting 'wider'; valid: 1, 2, 3, wide, wide-uniform"),
     (lambda: scene_seeds("wide", "huge"), "unknown split"),
     (lambda: parse_settings("wide"), "scene family this command does not take")],  # fmt: skip
)
def test_bad_input_is_a_one_line_scene_error(call, match):
    with pytest.raises(SceneError, match=match) as e:
        call()
    assert "\n" not in str(e.value)


def test_settings_names_and_paper_settings_unchanged():
    assert list(SCENE_FAMILIES) == [1, 2, 3, "wide", "wide-uniform"]
    assert parse_settings("all") == [1, 2, 3] and parse_settings("wide,3", families=True) == ["wide", 3]
    assert [len(scene_seeds("wide", part=p)) for p in ("train", "val", "test")] == [500, 50, 100]
    assert scene_seeds(2) == scene_seeds(2, "paper", "train") and setting_params("2") == setting_params(2)
    assert scene_to_json(generate_setting_scene(2, 1000)) == scene_to_json(generate_scene(1000, 5))


def test_palette_grows_instead_of_overflowing():
    pal = Palette()
    for i in range(5000):
        pal.colour_index((i % 256, i // 256, 7))
    assert pal.side == 128 and pal.image()[4999 // 128, 4999 % 128].tolist() == [4999 % 256, 4999 // 256, 7]


def test_many_people_render_with_exact_person_masks():
    """K = 100 on the wide grid plus background people: each person's pixels sit where it stands."""
    fam = setting_params("wide")
    spec = generate_scene(5, 100, SceneParams(city_half_m=fam.city_half_m), fam.grid, fam.placement)
    assert len(spec.people) > 200
    intr = CameraIntrinsics()
    occ = np.flatnonzero(spec.occupancy_array())
    x, y, _ = spec.grid.centers_enu[occ[len(occ) // 2]]
    seen = 0
    with SceneRenderer(spec, intr, RenderOptions(isolate=False)) as r:
        for pose in (nadir_camera_pose((x, y, 40.0)), nadir_camera_pose((-62.5, 62.5, 70.0))):
            v = r.render(pose)
            assert np.array_equal(v.person_mask, v.person_index >= 0)
            for i in np.unique(v.person_index[v.person_index >= 0]):
                p = spec.people[int(i)]
                uv, _ = project_points(np.array([[p.x_m, p.y_m, p.sz_m / 2]]), intr, pose)
                rows, cols = np.nonzero(v.person_index == i)
                assert np.hypot(cols.mean() + 0.5 - uv[0, 0], rows.mean() + 0.5 - uv[0, 1]) < 3.0
                seen += 1
    assert seen > 20
