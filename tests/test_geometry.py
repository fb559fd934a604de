"""Exact checks of frames, the camera model and the grid projection."""

import math
import warnings

import numpy as np
import pytest

from uavsearch.geometry import (
    CameraIntrinsics,
    GeodeticOrigin,
    Grid,
    camera_pose_from_vehicle,
    cell_image_polygons,
    cell_label_image,
    cell_masks,
    cell_pixel_areas,
    cells_in_view,
    enu_to_ned,
    euler_from_quaternion,
    nadir_camera_pose,
    ned_to_enu,
    polygon_area,
    project_points,
    quaternion_from_euler,
    rotation_ned_from_body,
)
from uavsearch.geometry import NEAR_PLANE_M, _clip_to_view

INTR = CameraIntrinsics(224, 224, 60.0)
GRID = Grid(10, 5.0)


def test_point_under_camera_lands_on_principal_point():
    pose = nadir_camera_pose([3.0, -7.0, 70.0])
    uv, depth = project_points([3.0, -7.0, 0.0], INTR, pose)
    assert uv == pytest.approx([INTR.cx, INTR.cy], abs=1e-9)
    assert depth == pytest.approx(70.0)


def test_north_is_image_up_and_east_is_image_right():
    pose = nadir_camera_pose([0.0, 0.0, 70.0])
    uv, _ = project_points([[0.0, 10.0, 0.0], [10.0, 0.0, 0.0]], INTR, pose)
    assert uv[0, 1] < INTR.cy and uv[0, 0] == pytest.approx(INTR.cx)
    assert uv[1, 0] > INTR.cx and uv[1, 1] == pytest.approx(INTR.cy)


def test_nadir_cell_area_matches_analytic_value():
    pose = nadir_camera_pose([0.0, 0.0, 70.0])
    areas = cell_pixel_areas(GRID, INTR, pose)
    side_px = GRID.cell_m * INTR.fx / 70.0
    # a nadir camera at 70 m with a 60 deg FOV sees the whole 50 m grid: every cell is whole
    assert areas == pytest.approx(np.full(100, side_px**2), rel=1e-9)


def test_cell_areas_at_once_are_the_areas_of_the_clipped_polygons():
    """cell_pixel_areas takes the whole cells' areas in one batch: the same numbers as polygon_area of each
    cell's clipped polygon, on a 30 x 30 grid seen whole, in part, tilted and from beyond its edge."""
    grid = Grid(30, 5.0)
    poses = [nadir_camera_pose([x, y, z]) for x, y, z in ((0, 0, 70), (-62.5, 37.5, 40), (37.5, -12.5, 70), (200, 0, 40))]
    poses.append(camera_pose_from_vehicle([10.0, -20.0, 55.0], 0.2, -0.15, 0.7, gimbal_stabilised=False))
    for pose in poses:
        expected = np.array([polygon_area(p) for p in cell_image_polygons(grid, INTR, pose)])
        np.testing.assert_allclose(cell_pixel_areas(grid, INTR, pose), expected, rtol=1e-12, atol=1e-9)


def _array_clip(poly, axis, bound, keep_greater):
    """Sutherland-Hodgman on numpy arrays, vertex by vertex: the reference the float clip must match."""
    out = []
    for k in range(len(poly)):
        a, b = poly[k], poly[(k + 1) % len(poly)]
        ina = a[axis] >= bound if keep_greater else a[axis] <= bound
        inb = b[axis] >= bound if keep_greater else b[axis] <= bound
        if ina:
            out.append(a)
        if ina != inb:
            out.append(a + (bound - a[axis]) / (b[axis] - a[axis]) * (b - a))
    return np.array(out) if out else np.zeros((0, poly.shape[1]))


def test_clipping_on_floats_gives_the_bits_of_clipping_arrays():
    """_clip_to_view clips a cell to the near plane and to the image on plain floats (for speed); clipping numpy
    arrays must give the same vertices to the last bit, or every cell area would move."""
    rng = np.random.default_rng(0)
    square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]])
    for i in range(400):
        quad = rng.uniform(-40.0, 264.0, 2) + rng.uniform(5.0, 60.0) * square + rng.normal(0, 3, (4, 2))
        depth = rng.uniform(20.0, 80.0, 4) if i % 4 else rng.uniform(-5.0, 10.0, 4)  # a quarter cross the near plane
        pc = np.column_stack([(quad[:, 0] - INTR.cx) * depth / INTR.fx, (quad[:, 1] - INTR.cy) * depth / INTR.fy,
                              depth])
        inside = pc if np.all(pc[:, 2] > NEAR_PLANE_M) else _array_clip(pc, 2, NEAR_PLANE_M, True)
        expected = np.zeros((0, 2))
        if len(inside) >= 3:
            uv = np.stack([INTR.fx * inside[:, 0] / inside[:, 2] + INTR.cx,
                           INTR.fy * inside[:, 1] / inside[:, 2] + INTR.cy], axis=-1)
            for axis, bound, keep in ((0, 0.0, True), (0, float(INTR.width_px), False), (1, 0.0, True),
                                      (1, float(INTR.height_px), False)):
                uv = _array_clip(uv, axis, bound, keep)
            expected = uv if len(uv) >= 3 else expected
        got = _clip_to_view(pc, INTR)
        assert got.shape == expected.shape and np.array_equal(got, expected)


def test_mask_pixel_counts_match_polygon_areas():
    pose = nadir_camera_pose([0.0, 0.0, 70.0])
    counts = cell_masks(GRID, INTR, pose).sum(axis=(1, 2))
    areas = cell_pixel_areas(GRID, INTR, pose)
    # pixel-centre rasterisation: counts within one perimeter's worth of pixels of the exact area
    side = math.sqrt(areas[0])
    assert np.all(np.abs(counts - areas) <= 4 * side + 1)
    assert counts.sum() == pytest.approx(areas.sum(), rel=0.02)


def test_cells_partly_out_of_view_are_clipped_not_wrapped():
    pose = nadir_camera_pose([25.0, 25.0, 70.0])  # above the NE corner of the grid
    polys = cell_image_polygons(GRID, INTR, pose)
    for p in polys:
        if len(p):
            assert p[:, 0].min() >= -1e-9 and p[:, 0].max() <= INTR.width_px + 1e-9
            assert p[:, 1].min() >= -1e-9 and p[:, 1].max() <= INTR.height_px + 1e-9
    areas = cell_pixel_areas(GRID, INTR, pose)
    full = (GRID.cell_m * INTR.fx / 70.0) ** 2
    assert areas.max() == pytest.approx(full)
    # the SW corner cell lies beyond the image: zero area, no mask pixels
    assert areas[99 - 9] == 0.0 and not cells_in_view(GRID, INTR, pose)[90]
    label = cell_label_image(GRID, INTR, pose)
    assert not np.any(label == 90)
    # partially visible cells: strictly between 0 and a whole cell
    partial = (areas > 0) & (areas < full - 1e-6)
    assert partial.any()


def test_cells_behind_camera_are_clipped_at_near_plane():
    # a camera tilted to the horizon: some cells are behind it and must not wrap into the image
    pose = camera_pose_from_vehicle([0.0, -30.0, 2.0], 0.0, math.radians(80), 0.0, gimbal_stabilised=False)
    polys = cell_image_polygons(GRID, INTR, pose)
    for p in polys:
        if len(p):
            assert np.all(np.isfinite(p))
            assert p[:, 1].min() >= -1e-9 and p[:, 1].max() <= INTR.height_px + 1e-9


def test_label_image_agrees_with_polygons_under_attitude():
    pose = camera_pose_from_vehicle([4.0, -3.0, 60.0], math.radians(5), math.radians(-8), math.radians(20), False)
    counts = np.bincount(cell_label_image(GRID, INTR, pose).ravel() + 1, minlength=101)[1:]
    areas = cell_pixel_areas(GRID, INTR, pose)
    assert np.abs(counts - areas).max() < 4 * math.sqrt(areas.max()) + 1


def test_cell_corners_tile_the_area():
    c = GRID.all_corners_enu
    assert c[0, 0] == pytest.approx([-25, 25, 0])  # NW corner of cell 0
    assert c[99, 2] == pytest.approx([25, -25, 0])  # SE corner of the last cell
    centers = GRID.centers_enu
    assert np.array_equal(GRID.cell_of_points(centers[:, 0], centers[:, 1]), np.arange(100))
    assert GRID.cell_of_points(30.0, 0.0) == -1 and GRID.cell_of_points(np.nan, 0.0) == -1


def test_enu_ned_round_trip():
    p = np.array([[1.0, 2.0, 3.0], [-4.0, 5.5, -6.0]])
    assert enu_to_ned(p)[0] == pytest.approx([2.0, 1.0, -3.0])
    assert ned_to_enu(enu_to_ned(p)) == pytest.approx(p)


def test_geodetic_round_trip_and_scale():
    home = GeodeticOrigin(47.397742, 8.545594, 488.0)
    p = np.array([[100.0, -250.0, 70.0], [0.0, 0.0, 0.0]])
    lla = home.enu_to_geodetic(p)
    assert lla[1] == pytest.approx([47.397742, 8.545594, 488.0])
    assert home.geodetic_to_enu(lla) == pytest.approx(p, abs=1e-9)
    # one degree of latitude is about 111.2 km at 47 deg N
    assert home.geodetic_to_enu([48.397742, 8.545594, 488.0])[1] == pytest.approx(111_200, rel=2e-3)


def test_quaternion_round_trip():
    rpy = (0.1, -0.2, 2.5)
    q = quaternion_from_euler(*rpy)
    assert np.linalg.norm(q) == pytest.approx(1.0)
    assert euler_from_quaternion(q) == pytest.approx(rpy)


def test_attitude_conversions_are_scipys_to_the_bit():
    """The written-out conversions give scipy's Rotation bits, so flights and their logs stay the same."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    flown = np.column_stack([rng.normal(0, 0.05, (2000, 2)), rng.uniform(-np.pi, np.pi, 2000)])
    wild = rng.uniform(-np.pi, np.pi, (2000, 3))
    for roll, pitch, yaw in np.concatenate([flown, wild]):
        rot = Rotation.from_euler("ZYX", [yaw, pitch, roll])
        assert np.array_equal(rotation_ned_from_body(roll, pitch, yaw), rot.as_matrix())
        x, y, z, w = rot.as_quat()
        assert np.array_equal(quaternion_from_euler(roll, pitch, yaw), [w, x, y, z])
    locked = [quaternion_from_euler(0.3, s * np.pi / 2, 1.0) for s in (1, -1)]
    for q in [*rng.normal(size=(4000, 4)), *(rng.normal(0, 1e-3, 4) + [1, 0, 0, 0] for _ in range(500)), *locked]:
        w, x, y, z = q
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # scipy warns of the gimbal lock
            yaw, pitch, roll = Rotation.from_quat([x, y, z, w]).as_euler("ZYX")
        assert euler_from_quaternion(q) == (roll, pitch, yaw)
    with pytest.raises(ValueError):
        euler_from_quaternion([0.0, 0.0, 0.0, 0.0])


def test_stabilised_gimbal_ignores_roll_and_pitch():
    a = camera_pose_from_vehicle([0, 0, 70], 0.2, -0.1, 0.0, gimbal_stabilised=True)
    b = nadir_camera_pose([0, 0, 70])
    assert np.allclose(a.R_enu_from_cam, b.R_enu_from_cam)
    c = camera_pose_from_vehicle([0, 0, 70], 0.0, math.radians(10), 0.0, gimbal_stabilised=False)
    # nose-up pitch turns the belly, and a body-fixed nadir camera's view, forwards (north)
    assert c.forward_enu[1] > 0
