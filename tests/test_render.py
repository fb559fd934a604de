"""The PyBullet camera agrees with geometry's camera model, is deterministic and sees people."""

import os

import numpy as np
import pytest
from scipy import ndimage

from uavsearch.geometry import (
    CameraIntrinsics,
    GeodeticOrigin,
    Grid,
    camera_pose_from_vehicle,
    nadir_camera_pose,
    project_points,
)
from uavsearch.world.render import RenderOptions, SceneRenderer, area_downsample
from uavsearch.world.scene import (
    GENERATOR_VERSION,
    SceneObject,
    SceneParams,
    SceneSpec,
    generate_scene,
    scene_from_json,
    scene_to_json,
)

MARKERS = [(0.0, 0.0), (7.3, -4.1), (-12.0, 9.5), (15.0, 15.0), (-6.0, -13.0)]
MARKER_TOP_M = 0.02


def _marker_scene() -> SceneSpec:
    objs = [SceneObject(kind="base", x_m=0, y_m=0, sx_m=800, sy_m=800, color=(90, 120, 60))]
    objs += [
        SceneObject(kind="roof_unit", x_m=x, y_m=y, sx_m=0.8, sy_m=0.8, sz_m=MARKER_TOP_M, color=(255, 0, 0))
        for x, y in MARKERS
    ]
    return SceneSpec(generator_version=GENERATOR_VERSION, seed=0, occupied_cells_k=0, params=SceneParams(),
                     grid=Grid(), home=GeodeticOrigin(), objects=objs, occupancy=[0] * 100)  # fmt: skip


POSES = {
    "nadir centre": nadir_camera_pose((0.0, 0.0, 40.0)),
    "off-centre, yaw 0.6": nadir_camera_pose((3.0, -2.0, 35.0), yaw_rad=0.6),
    "off-centre, yaw -2.5": nadir_camera_pose((-4.0, 5.0, 45.0), yaw_rad=-2.5),
    "hard-mounted, tilted": camera_pose_from_vehicle((1.0, 2.0, 30.0), 0.1, -0.15, 0.3, gimbal_stabilised=False),
}


@pytest.mark.parametrize("supersample", [1, 2])
def test_markers_land_on_projected_pixels(supersample):
    intr = CameraIntrinsics(224, 160, 60.0)  # non-square on purpose
    with SceneRenderer(_marker_scene(), intr, RenderOptions(supersample=supersample)) as r:
        for name, pose in POSES.items():
            img = r.render(pose).rgb.astype(int)
            redness = np.clip(img[:, :, 0] - img[:, :, 1] - 40, 0, None).astype(float)
            labels, n = ndimage.label(redness > 0)
            uv, _ = project_points(np.array([[x, y, MARKER_TOP_M] for x, y in MARKERS]), intr, pose)
            inside = (uv[:, 0] > 4) & (uv[:, 0] < intr.width_px - 4) & (uv[:, 1] > 4) & (uv[:, 1] < intr.height_px - 4)
            assert inside.sum() >= 3, name
            centres = ndimage.center_of_mass(redness, labels, range(1, n + 1))
            for u, v in uv[inside]:  # every marker fully in view is seen where project_points puts it
                d = min(np.hypot(u - (col + 0.5), v - (row + 0.5)) for row, col in centres)
                assert d < 0.5, f"{name}: marker {d:.2f} px from its projection"


@pytest.fixture(scope="module")
def city():
    return generate_scene(5, 10)


def test_same_scene_same_images_and_no_interference(city):
    intr = CameraIntrinsics()
    pose_a, pose_b = nadir_camera_pose((0, 0, 70)), nadir_camera_pose((20, -10, 70))
    r1 = SceneRenderer(city, intr)  # in a worker process (the default)
    r2 = SceneRenderer(scene_from_json(scene_to_json(city)), intr, RenderOptions(isolate=False))  # in this process
    other = SceneRenderer(_marker_scene(), intr, RenderOptions(isolate=False))  # another client in this process
    try:
        a1 = r1.render(pose_a)
        o = other.render(pose_a)
        b2 = r2.render(pose_b)
        a2 = r2.render(pose_a)
        b1 = r1.render(pose_b)
    finally:
        for r in (r1, r2, other):
            r.close()
    assert np.array_equal(a1.rgb, a2.rgb) and np.array_equal(b1.rgb, b2.rgb)
    assert np.array_equal(a1.person_mask, a2.person_mask)
    assert not np.array_equal(a1.rgb, o.rgb)
    assert a1.rgb.shape == (224, 224, 3) and a1.rgb.dtype == np.uint8


def test_person_mask_where_people_are(city):
    intr = CameraIntrinsics()
    pose = nadir_camera_pose((0, 0, 70))
    with SceneRenderer(city, intr) as r:
        out = r.render(pose)
    assert out.person_mask.any()
    assert np.array_equal(out.person_mask, out.person_fraction > 0)
    assert out.person_fraction.min() >= 0 and out.person_fraction.max() <= 1
    assert np.array_equal(out.person_index >= 0, out.person_mask)
    # every person pixel lies within a couple of pixels of the projection of the person it belongs to
    people = city.people
    rows, cols = np.nonzero(out.person_mask)
    for i in np.unique(out.person_index[out.person_mask]):
        p = people[int(i)]
        uv, _ = project_points(np.array([[p.x_m, p.y_m, 0.0], [p.x_m, p.y_m, p.sz_m]]), intr, pose)
        sel = out.person_index[rows, cols] == i
        d = np.hypot(cols[sel] + 0.5 - uv[:, 0].mean(), rows[sel] + 0.5 - uv[:, 1].mean())
        assert d.max() < 4.0
    # people in occupied cells near the image centre are seen (no tree happens to hide them all)
    seen = {int(people[i].cell) for i in np.unique(out.person_index[out.person_mask])}
    assert len(seen & set(np.flatnonzero(city.occupancy_array()).tolist())) >= 5


def test_randomisation_only_with_rng(city):
    intr = CameraIntrinsics(96, 96, 60.0)
    pose = nadir_camera_pose((0, 0, 70))
    with SceneRenderer(city, intr, RenderOptions.randomised()) as r:
        clean1, clean2 = r.render(pose), r.render(pose)
        n1 = r.render(pose, np.random.default_rng(1))
        n1b = r.render(pose, np.random.default_rng(1))
        n2 = r.render(pose, np.random.default_rng(2))
    assert np.array_equal(clean1.rgb, clean2.rgb)
    assert np.array_equal(n1.rgb, n1b.rgb)
    assert not np.array_equal(n1.rgb, clean1.rgb) and not np.array_equal(n1.rgb, n2.rgb)
    assert np.array_equal(n1.person_mask, clean1.person_mask)  # ground truth is not perturbed


def test_closed_renderer_releases_client(city):
    r = SceneRenderer(city, CameraIntrinsics(32, 32, 60.0))
    r.close()
    r.close()  # idempotent
    with pytest.raises(ValueError):
        SceneRenderer(city, CameraIntrinsics(), RenderOptions(supersample=0))


def _reference_downsample(rgb: np.ndarray, pidx: np.ndarray, s: int):
    """The area downsampling as first written (float mean over blocks): the reference for bit-identity."""
    h, w = rgb.shape[0] // s, rgb.shape[1] // s
    img = rgb.reshape(h, s, w, s, 3).astype(np.float32).mean(axis=(1, 3))
    blocks = pidx.reshape(h, s, w, s).transpose(0, 2, 1, 3).reshape(h, w, s * s)
    frac = (blocks >= 0).mean(axis=-1).astype(np.float32)
    index = np.full((h, w), -1, np.int16)  # majority person per pixel, ties to the lowest index
    best_n = np.zeros((h, w), np.int64)
    for v in np.unique(blocks[blocks >= 0]):
        n = (blocks == v).sum(-1)
        index[n > best_n], best_n = v, np.maximum(best_n, n)
    return img, frac, index


@pytest.mark.parametrize("supersample", [2, 3])
def test_downsample_bit_identical_on_rendered_frames(city, supersample):
    intr = CameraIntrinsics(96, 80, 90.0)
    partial = 0  # pixels partly covered by a person: the fraction comparison is not vacuous
    with SceneRenderer(city, intr, RenderOptions(supersample=supersample, isolate=False)) as r:
        for pose in (nadir_camera_pose((0, 0, 70)), nadir_camera_pose((-5, 5, 30), yaw_rad=0.4)):
            rgb, pidx = r._world.capture(pose)
            ref_img, ref_frac, ref_index = _reference_downsample(rgb, pidx, supersample)
            assert np.array_equal(area_downsample(rgb, supersample), ref_img)
            out = r.render(pose)
            assert np.array_equal(out.person_fraction, ref_frac)
            assert np.array_equal(out.person_index, ref_index)
            assert np.array_equal(out.rgb, np.clip(np.rint(ref_img), 0, 255).astype(np.uint8))
            partial += int(((ref_frac > 0) & (ref_frac < 1)).sum())
    assert partial > 0


# Composite vs mesh ground: they differ only where TinyRenderer breaks a depth tie between coplanar
# surfaces by draw order (tiling reorders bodies) or a texel boundary rounds the other way, a handful of
# pixels; tools/compare_render.py measured PSNR >= 58.7 dB over 100 views (96 identical). 50 dB allows
# about three pixels changed by 100 grey levels in a 224 px view, and fails on any real change of the
# ground's shading, sampling or placement (even one grey level everywhere is 48.1 dB).
MIN_PSNR_DB = 50.0


def test_composite_ground_matches_mesh_ground(city):
    intr = CameraIntrinsics()
    poses = [nadir_camera_pose((0, 0, 70)), nadir_camera_pose((10, -20, 70)), POSES["hard-mounted, tilted"]]
    with (
        SceneRenderer(city, intr, RenderOptions(ground="mesh", isolate=False)) as mesh,
        SceneRenderer(city, intr, RenderOptions(ground="composite", isolate=False)) as comp,
    ):
        for pose in poses:
            a, b = mesh.render(pose), comp.render(pose)
            mse = np.mean((a.rgb.astype(float) - b.rgb.astype(float)) ** 2)
            assert mse == 0 or 10 * np.log10(255**2 / mse) > MIN_PSNR_DB
            assert np.array_equal(a.person_index, b.person_index)
            assert np.array_equal(a.person_fraction, b.person_fraction)
            assert a.person_mask.any()


def test_unknown_ground_mode_is_a_clear_error(city):
    with pytest.raises(ValueError, match="ground must be one of"):
        SceneRenderer(city, CameraIntrinsics(32, 32, 60.0), RenderOptions(ground="flat"))


def test_a_scene_generated_in_the_render_worker_is_the_scene_generated_here():
    from uavsearch.world.render import generate_in_worker
    from uavsearch.world.scene import generate_scene, scene_to_json

    assert scene_to_json(generate_in_worker(3, 5)) == scene_to_json(generate_scene(3, 5))


# sha256 of (rgb, person_index, person_fraction) bytes of paper views, computed before people got their own
# palette and palettes could grow: a paper scene's pixels must not change.
PAPER_VIEW_SHA256 = {
    (1000, 2, (0, 0, 70), "composite"): "baa305807a8d876512881ee0a7dd5b9da18aa8b744d5607a70da2102a455fe1b",
    (3, 5, (0, 0, 70), "mesh"): "b7847c07d639e9679926dd8c59792f7159d73eace16f2ae9f9b5bb1f6b3d5112",
}


@pytest.mark.parametrize("key", sorted(PAPER_VIEW_SHA256))
def test_paper_views_keep_their_pixels(key):
    import hashlib

    seed, k, pos, ground = key
    with SceneRenderer(generate_scene(seed, k), CameraIntrinsics(), RenderOptions(isolate=False, ground=ground)) as r:
        v = r.render(nadir_camera_pose(pos))
    digest = hashlib.sha256(v.rgb.tobytes() + v.person_index.tobytes() + v.person_fraction.tobytes()).hexdigest()
    assert digest == PAPER_VIEW_SHA256[key]


@pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="Linux's scheduling classes")
def test_a_background_worker_runs_on_idle_time_until_brought_to_the_foreground():
    """Work beside a flight takes only CPU time nothing else wants; after the flight a busy machine must not
    starve it, so it goes back to the normal class."""
    from uavsearch.world import render

    render._stop_idle_workers()
    render.start_idle_worker(background=True)
    worker = render._IDLE[-1]
    try:
        assert worker.call("generate", 3, 5)  # it serves as any worker does (and has set its class by then)
        assert os.sched_getscheduler(worker.proc.pid) == os.SCHED_IDLE
        render.foreground_workers()
        assert os.sched_getscheduler(worker.proc.pid) == os.SCHED_OTHER
    finally:
        render._stop_idle_workers()
