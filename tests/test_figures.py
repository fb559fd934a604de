"""Every figure kind keeps its titles, legends, labels and colour bars on the canvas, at every number of
panels: matplotlib's tight bounding box of what is drawn must lie inside the figure (viz.overflow_in)."""

import numpy as np
import pytest

from uavsearch.geometry import CameraIntrinsics, Grid, camera_pose_from_vehicle
from uavsearch.replay.replay import ReplayData, frame_figure, maps_figure, metrics_figure, trajectory_figure
from uavsearch.search.evaluate.search import ROWS, fig6_figure
from uavsearch.search.evaluate.single_view import fig4_figure
from uavsearch.search.train.perception import curves_figure
from uavsearch.viz import overflow_in, pyplot, scene_figure
from uavsearch.world.scene import generate_scene

TOLERANCE_IN = 0.01


@pytest.fixture(scope="module")
def spec():
    return generate_scene(3, 5)


def _fits(fig) -> float:
    try:
        return overflow_in(fig)
    finally:
        pyplot().close(fig)


@pytest.mark.parametrize("n_settings", [1, 2, 3])
def test_fig6_fits_at_every_number_of_settings(n_settings):
    rng = np.random.default_rng(n_settings)
    results = {s: {key: {"acc": rng.random((2, 3, 5)), "f1": rng.random((2, 3, 5))} for key, *_ in ROWS}
               for s in (1, 2, 3)[:n_settings]}
    assert _fits(fig6_figure(results)) <= TOLERANCE_IN


def _replay(spec, T: int) -> ReplayData:
    rng = np.random.default_rng(T)
    pose = camera_pose_from_vehicle(np.array([0.0, 0.0, 70.0]), 0.0, 0.0, 0.0, gimbal_stabilised=True)
    return ReplayData(
        title=f"runs/fly__default__20260101-000000/telemetry.tlog in scene {spec.seed}: learned fusion over {T} views",
        grid=Grid(), labels=spec.occupancy_array().astype(bool), fusion="learned", maps=rng.random((T, 100)),
        p_occ=rng.random((T, 100)), valid=np.ones((T, 100), dtype=bool),
        positions_enu=np.c_[rng.uniform(-20, 20, (T, 2)), np.full(T, 70.0)],
        track_enu=np.c_[rng.uniform(-25, 25, (40, 2)), np.full(40, 70.0)],
        images=[rng.integers(0, 255, (224, 224, 3), dtype=np.uint8) for _ in range(T)], poses=[pose] * T, spec=spec,
        true_positions_enu=np.c_[rng.uniform(-20, 20, (T, 2)), np.full(T, 70.0)],
        logged_maps=rng.random((T, 100)))


@pytest.mark.parametrize("T", [1, 2, 5, 10])
def test_replay_figures_and_frames_fit_at_every_number_of_views(spec, T):
    d = _replay(spec, T)
    for build in (trajectory_figure, maps_figure, metrics_figure):
        assert _fits(build(d)) <= TOLERANCE_IN, build.__name__
    for t in sorted({0, T - 1}):
        assert _fits(frame_figure(d, t)) <= TOLERANCE_IN, f"frame {t}"


def test_scene_show_fits(spec):
    from uavsearch.search.config import SearchConfig
    from uavsearch.search.views import TeleportVehicle

    config = SearchConfig()
    with TeleportVehicle(spec, config) as vehicle:
        view = vehicle.capture([0.0, 0.0, config.altitude_m])
    assert _fits(scene_figure(spec, view, config.grid, CameraIntrinsics())) <= TOLERANCE_IN


def test_fig4_fits():
    rng = np.random.default_rng(4)
    n = 2000
    fig = fig4_figure(rng.choice([12.0, 196.0], n), rng.random(n) < 0.9, rng.uniform(0, 45, n),
                      rng.integers(0, 30, 300), rng.random(300) < 0.5)
    assert _fits(fig) <= TOLERANCE_IN


@pytest.mark.parametrize("evals", [0, 1, 8])
def test_perception_learning_curves_fit(evals):
    rows = [{"step": s, "losses/train_loss": 1.0 / (1 + s)} for s in range(1, 101)]
    rows += [{"step": 10 * (i + 1), "eval/aacc": 0.9, "eval/af1": 0.4, "eval/start_aacc": 0.9, "eval/start_af1": 0.4}
             for i in range(evals)]
    assert _fits(curves_figure(rows)) <= TOLERANCE_IN


def test_overflow_is_measured():
    """The measure itself: a title wider than its canvas reaches past it."""
    fig, ax = pyplot().subplots(figsize=(2, 2))
    ax.set_title("a title far too long for a two-inch canvas to hold")
    assert _fits(fig) > 0.5


def test_family_perception_figure_fits():
    from uavsearch.search.evaluate.perception import PX_BINS, bin_name, family_figure

    by = {bin_name(lo, hi): (0.5, 100) for lo, hi in PX_BINS}
    st = {"recall_by_px": by, "fa_per_cell_view": 0.02}
    stats = {c: st for c in ("40 m", "70 m", "40 m, reference net", "70 m, reference net")}
    assert _fits(family_figure(stats)) <= TOLERANCE_IN
