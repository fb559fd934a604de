"""The viewpoint lattice: the paper's 5 x 5 layer unchanged, altitude layers and 3-D moves, flight times,
and a two-altitude search end to end in teleport mode (rendered view cache, stage-2 training, evaluation,
an agent built from the checkpoint)."""

import numpy as np
import pytest
import torch

from uavsearch.errors import UavsearchError
from uavsearch.search.agents import build_agent
from uavsearch.search.config import SearchConfig, config_from_dict, config_to_dict
from uavsearch.search.data.view_cache import CacheKey, build_view_cache, load_view_cache
from uavsearch.search.perception import PerceptionConfig, PerceptionNet
from uavsearch.search.policy import load_search_model
from uavsearch.search.scoring import evaluate_agent
from uavsearch.search.train.policy import Args, train

MOVES6 = ("MoveAhead", "MoveRight", "MoveLeft", "MoveBack", "Descend", "Climb")
TWO_ALT = SearchConfig(altitudes_m=(70.0, 40.0), actions=MOVES6, budget_T=4)


def test_paper_lattice_is_one_centred_layer_indexed_like_the_grid():
    lat = SearchConfig().lattice
    assert lat.num_positions == 25 and lat.start_index == 12
    assert lat.positions_enu[0].tolist() == [-20.0, 20.0, 70.0]  # NW corner first
    assert lat.positions_enu[lat.index((2, 2))].tolist() == [20.0, 20.0, 70.0]
    assert lat.coords(lat.index((1, -1))) == (3, 3, 0)
    assert lat.nearest([9.0, 1.0, 69.0]) == lat.index((1, 0))
    # a move off the lattice keeps the camera where it is
    assert lat.moves[0].tolist() == [0, 1, 0, 5]


def test_altitude_layers_and_3d_moves():
    lat = TWO_ALT.lattice
    assert lat.num_positions == 50 and lat.start_index == 12
    assert lat.positions_enu[37].tolist() == [0.0, 0.0, 40.0]
    down, up = MOVES6.index("Descend"), MOVES6.index("Climb")
    assert lat.moves[12, down] == 37 and lat.moves[37, up] == 12
    assert lat.moves[12, up] == 12 and lat.moves[37, down] == 37  # no layer above 70 m or below 40 m
    # distances are horizontal, pixel areas grow as the camera descends
    assert torch.equal(lat.cell_distances[12], lat.cell_distances[37])
    assert float(lat.cell_areas[37].max()) > 2.5 * float(lat.cell_areas[12].max())


def test_layers_follow_altitude_not_their_order():
    lat = SearchConfig(altitude_m=40.0, altitudes_m=(40.0, 70.0), actions=MOVES6).lattice
    assert lat.moves[12, MOVES6.index("Climb")] == 37 and lat.moves[37, MOVES6.index("Descend")] == 12


def test_flight_times_match_the_flown_legs():
    t = TWO_ALT.lattice.flight_time_s
    assert t[12, 12] == 0.0
    assert t[12, 13] == pytest.approx(6.0, abs=0.3)  # a 10 m step at 70 m
    assert t[12, 37] == pytest.approx(21.1, abs=0.3)  # a 30 m descent
    assert t[37, 12] < t[12, 37]  # climbing is faster than descending
    assert (t[12, 38] >= t[12, 37]) and (t[12, 38] >= t[12, 13])  # a diagonal leg is no faster than its parts


def test_bad_lattices_are_one_line_errors():
    with pytest.raises(UavsearchError, match="start"):
        SearchConfig(altitudes_m=(40.0, 70.0))  # altitude_m stays 70
    with pytest.raises(UavsearchError, match="repeat"):
        SearchConfig(altitudes_m=(70.0, 70.0))
    with pytest.raises(UavsearchError, match="unknown action"):
        SearchConfig(actions=("MoveUp",))


def test_config_round_trips_through_a_record():
    assert config_from_dict(config_to_dict(TWO_ALT)) == TWO_ALT
    assert config_from_dict({"altitude_m": 70.0}) == SearchConfig()  # an old record: today's defaults


@pytest.mark.slow  # renders and trains on a two-altitude lattice (about 20 s): `make test-all` runs it
def test_two_altitude_search_end_to_end_in_teleport_mode(tmp_path):
    """Render a two-altitude view cache, train stage 2 a few iterations on it, evaluate, and load the agent
    back from the checkpoint, which records its lattice (a paper-lattice search refuses it)."""
    torch.manual_seed(0)
    net = PerceptionNet(PerceptionConfig()).eval()
    key = CacheKey(2, "paper", "train", TWO_ALT)
    cache = load_view_cache(build_view_cache(net, key, scenes=[(0, 5), (1, 5)], cache_dir=str(tmp_path / "cache"),
                                             workers=1, progress=False))
    assert cache.num_positions == 50 and cache.config == TWO_ALT
    low = cache.cell_area_px[:, 25:].amax(-1).mean()
    assert low > 2.5 * cache.cell_area_px[:, :25].amax(-1).mean()  # the 40 m views see cells larger

    out = tmp_path / "search_s2_learned.pt"
    res = train(Args(iterations=3, scenes_per_batch=2, episodes_per_scene=2, eval_every=3, eval_episodes=1,
                     runs_dir=str(tmp_path / "runs"), progress=False, plot=False, out=str(out)),
                caches=(cache, cache))
    assert res.checkpoint.is_file()
    *_, extra = load_search_model(out)
    assert config_from_dict(extra["search_config"]) == TWO_ALT

    loaded = build_agent("learned", "learned", TWO_ALT, checkpoint=out)
    scores = evaluate_agent(cache, loaded.agent, episodes_per_scene=2, seed=0)
    assert scores.f1.shape == (4, TWO_ALT.budget_T) and np.isfinite(scores.f1).all()
    with pytest.raises(UavsearchError, match="another viewpoint lattice"):
        build_agent("learned", "learned", SearchConfig(), checkpoint=out)


def test_a_teleport_views_shared_grid_projection_is_the_one_make_view_computes():
    """Every scene of a lattice shares each position's projection: the same arrays as computed per view."""
    from uavsearch.geometry import cell_label_image, cell_pixel_areas, nadir_camera_pose
    from uavsearch.search.views import nadir_view_geometry

    config = CacheKey("wide", "large", "val").search_config
    for position in config.lattice.positions_enu[[0, 5, -1]]:
        label, areas = nadir_view_geometry(config.grid, config.intrinsics, tuple(position.tolist()))
        pose = nadir_camera_pose(position)
        assert np.array_equal(label, cell_label_image(config.grid, config.intrinsics, pose))
        assert np.array_equal(areas, cell_pixel_areas(config.grid, config.intrinsics, pose).astype(np.float32))
        assert not label.flags.writeable and nadir_view_geometry(config.grid, config.intrinsics, tuple(position.tolist()))[0] is label


def test_perception_outputs_with_shared_cell_poolings_equal_the_plain_ones():
    """A view cache shares each lattice batch's cell pooling across scenes: the outputs stay the same bytes."""
    from uavsearch.search.data.view_cache import perception_outputs
    from uavsearch.search.views import nadir_view_geometry

    config = SearchConfig()
    torch.manual_seed(0)
    net = PerceptionNet(PerceptionConfig()).eval()
    labels = np.stack([nadir_view_geometry(config.grid, config.intrinsics, tuple(p.tolist()))[0]
                       for p in config.lattice.positions_enu[:3]])
    images = np.random.default_rng(0).integers(0, 256, (3, *labels.shape[1:], 3), dtype=np.uint8)
    altitudes = np.full(3, config.altitude_m, np.float32)
    plain = perception_outputs(net, images, labels, altitudes, batch=2)
    poolings: dict = {}
    for _ in range(2):  # the second scene reuses the first one's poolings
        shared = perception_outputs(net, images, labels, altitudes, batch=2, poolings=poolings)
        assert len(poolings) == 2 and all(np.array_equal(plain[k], shared[k]) for k in plain)
