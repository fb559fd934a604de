"""Every figure kind keeps its titles, legends, labels and colour bars on the canvas, at every number of
panels: matplotlib's tight bounding box of what is drawn must lie inside the figure (viz.overflow_in)."""

import numpy as np
import pytest

from uavsearch.geometry import CameraIntrinsics, Grid, camera_pose_from_vehicle
from uavsearch.replay.replay import (MAPS_PANELS, ReplayData, frame_figure, maps_figure, metrics_figure,
                                     trajectory_figure)
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


@pytest.mark.parametrize("T", [1, 2, 5, 10, 40])
def test_replay_figures_and_frames_fit_at_every_number_of_views(spec, T):
    d = _replay(spec, T)
    for build in (trajectory_figure, maps_figure, metrics_figure):
        assert _fits(build(d)) <= TOLERANCE_IN, build.__name__
    for t in sorted({0, T - 1}):
        assert _fits(frame_figure(d, t)) <= TOLERANCE_IN, f"frame {t}"


@pytest.mark.parametrize("T", [1, 7, 40, 300])
def test_maps_is_a_grid_of_bounded_size_that_says_what_it_left_out(spec, T):
    """maps.png: rows of at most MAPS_COLUMNS panels, at most MAPS_PANELS of them (views spread evenly, the
    first and the last kept, the title saying how many are shown), so it reads at any number of views."""
    d = _replay(spec, T)
    fig = maps_figure(d)
    try:
        panels = [ax for ax in fig.axes if ax.get_title()]
        w, h = fig.get_size_inches()
        assert len(panels) == min(T, MAPS_PANELS - 1) + 1 and w <= 17 and h <= 13
        titles = [ax.get_title() for ax in panels]
        assert titles[0].startswith("fused after view 1\n") and titles[-2].startswith(f"fused after view {T}\n")
        assert (f"{MAPS_PANELS - 1} of {T} views shown" in fig._suptitle.get_text()) == (T >= MAPS_PANELS)
        assert any(ax.get_label() == "<colorbar>" for ax in fig.axes)
    finally:
        pyplot().close(fig)


def test_maps_and_metrics_say_what_unseen_cells_count_as(spec):
    """A cell no view has measured holds the prior (0.5: undecided, wrong in acc and F1): the maps draw it grey
    with a key saying so, the metrics plot adds the share of cells seen, and its title the final scores."""
    d = _replay(spec, 3)
    d.valid = np.zeros_like(d.valid)
    d.valid[0, :40], d.valid[1, 30:70], d.valid[2, :] = True, True, True
    d.maps = np.where(d.seen, d.maps, 0.5)
    fig = maps_figure(d)
    keys = [t.get_text() for t in fig.legends[0].get_texts()]
    pyplot().close(fig)
    assert keys == ["occupied (ground truth)", "unseen (prior 0.5: counts as wrong)"]
    fig = metrics_figure(d)
    lines = {ln.get_label(): ln.get_ydata() for ln in fig.axes[0].get_lines()}
    title = fig.axes[0].get_title()
    pyplot().close(fig)
    assert list(lines["share of cells seen"]) == [0.4, 0.7, 1.0]
    assert f"final Aacc {d.acc[-1]:.3f}, F1 {d.f1[-1]:.3f}" in title and "count as wrong" in title
    assert d.acc[0] <= 0.4  # the unseen 60 cells are wrong: acc cannot exceed the share seen


def test_replay_frame_keys_every_mark(spec):
    """The video frame's view names its red and yellow outlines, its map has a colour bar and a key."""
    d = _replay(spec, 2)
    fig = frame_figure(d, 1)
    try:
        view, fused = fig.axes[0], fig.axes[1]
        assert [t.get_text() for t in view.get_legend().get_texts()] == ["grid cell", "occupied (ground truth)"]
        assert "occupied (ground truth)" in [t.get_text() for t in fused.get_legend().get_texts()]
        assert any(ax.get_label() == "<colorbar>" for ax in fig.axes)
        assert "person" in [t.get_text() for t in fig.legends[0].get_texts()]
    finally:
        pyplot().close(fig)


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
