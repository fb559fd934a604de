"""A detector of your own as perception: boxes -> per-cell probabilities through the grid projection, by name."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uavsearch.errors import UavsearchError
from uavsearch.geometry import Grid, CameraIntrinsics, cell_label_image, nadir_camera_pose
from uavsearch.search.config import setting_config
from uavsearch.search.data.dataset import make_scene
from uavsearch.search.detector import DetectorPerception
from uavsearch.search.perception import load_perception, perceive, perception_tag
from uavsearch.search.views import TeleportVehicle
from uavsearch.world.settings import setting_params

FLOOR = 0.02


def centre_box(images):
    """Two detections per image: one at the image centre (score 0.9), one half-way to the right edge (0.5)."""
    h, w = images.shape[1:3]
    return [{"boxes": np.array([[w / 2 - 2, h / 2 - 2, w / 2 + 2, h / 2 + 2], [3 * w / 4 - 1, h / 2 - 1, 3 * w / 4 + 1,
                                                                             h / 2 + 1]]),
             "scores": np.array([0.9, 0.5])} for _ in images]


def test_boxes_become_cell_probabilities():
    grid, intr = Grid(10, 5.0), CameraIntrinsics()
    label = cell_label_image(grid, intr, nadir_camera_pose([0.0, 0.0, 70.0]))
    images = np.zeros((2, *label.shape, 3), np.uint8)
    net = DetectorPerception(centre_box, floor=FLOOR)
    out = net.forward_all(images, np.stack([label, label]))
    p = out.log_probs.exp()
    assert torch.allclose(p.sum(-1), torch.ones(2, 100), atol=1e-5)
    c0 = int(label[label.shape[0] // 2, label.shape[1] // 2])
    c1 = int(label[label.shape[0] // 2, 3 * label.shape[1] // 4])
    assert c0 != c1 and c0 >= 0 and c1 >= 0
    expected = np.full(100, FLOOR)
    expected[c0] = 1 - (1 - FLOOR) * 0.1
    expected[c1] = 1 - (1 - FLOOR) * 0.5
    assert np.allclose(p[0, :, 1].numpy(), expected, atol=1e-5)
    assert out.cell_features.shape == (2, 100, net.cell_dim) and out.global_feature.shape == (2, net.global_dim)
    assert torch.equal(out.cell_pixels[0], torch.as_tensor(np.bincount(label[label >= 0], minlength=100)).float())
    assert net.for_grid(900).num_cells == 900


def test_masks_stand_where_their_pixels_look():
    """With a mask, a detection stands in the cell most of its pixels see, wherever its box is."""
    grid, intr = Grid(10, 5.0), CameraIntrinsics()
    label = cell_label_image(grid, intr, nadir_camera_pose([0.0, 0.0, 70.0]))
    mask = np.zeros((1, *label.shape), bool)
    mask[0, 60:64, 60:64] = True

    def masked(images):
        return [(np.array([[150.0, 150.0, 160.0, 160.0]]), np.array([0.8]), mask) for _ in images]

    p = DetectorPerception(masked).forward_all(np.zeros((1, *label.shape, 3), np.uint8), label).log_probs.exp()
    assert label[61, 61] >= 0 and label[155, 155] not in (-1, label[61, 61])
    assert int(p[0, :, 1].argmax()) == int(label[61, 61])


def test_by_name_tag_and_bad_input():
    name = f"detector:{__file__}:centre_box"
    net, extra = load_perception(name)
    assert isinstance(net, DetectorPerception) and extra == {}
    assert perception_tag(net) == perception_tag(load_perception(name)[0])
    assert perception_tag(net) != perception_tag(load_perception(name + "?floor=0.05")[0])
    for bad, words in ((f"detector:{__file__}:nothing", "no function"),
                       ("detector:no_such_module_xyz:f", "cannot import"),
                       ("detector:justaname", "MODULE:FUNCTION"), (name + "?flor=1", "unknown option"),
                       (name + "?floor=2", "floor must be in")):
        with pytest.raises(UavsearchError, match=words):
            load_perception(bad)
    with pytest.raises(UavsearchError, match="probabilities"):
        DetectorPerception(lambda im: [([[0, 0, 1, 1]], [1.5])]).forward_all(np.zeros((1, 8, 8, 3), np.uint8),
                                                                           np.zeros((1, 8, 8), np.int16))


def test_ground_truth_boxes_land_in_occupied_cells():
    """A detector that returns the renderer's own person masks (a perfect one) marks only occupied cells, and
    every occupied cell whose person the view shows: the projection is the grid's."""
    config = setting_config(2)
    spec = make_scene(setting_params(2).scene(3).seed, setting_params(2).k)
    with TeleportVehicle(spec, config, cache=False) as vehicle:
        view = vehicle.capture([0.0, 0.0, config.altitude_m])
    ids = np.unique(view.person_index[view.person_index >= 0])

    def oracle(images):
        masks = np.stack([view.person_index == i for i in ids])
        boxes = np.array([[c.min(), r.min(), c.max() + 1, r.max() + 1] for r, c in (np.nonzero(m) for m in masks)])
        return [{"boxes": boxes, "scores": np.ones(len(ids)), "masks": masks} for _ in images]

    got = perceive(DetectorPerception(oracle), [view])
    seen = set(np.flatnonzero(got.outputs.log_probs[0, :, 1].exp().numpy() > 0.5).tolist())
    occupied = set(np.flatnonzero(spec.occupancy_array()).tolist())
    xy = np.array([[spec.people[i].x_m, spec.people[i].y_m] for i in ids])
    visible = set(config.grid.cell_of_points(xy[:, 0], xy[:, 1]).tolist()) - {-1}
    assert len(ids) > 0 and seen <= occupied and seen == visible


def test_a_detector_loaded_for_a_search_reads_its_grid():
    """A detector knows no grid until told: the agent a mission or the team controller loads reads the wide
    family's 900 cells (a flight once stopped at its first view with an index error)."""
    from uavsearch.search.agents import build_agent
    from uavsearch.search.config import setting_config

    config = setting_config("wide")
    loaded = build_agent("bayes", "random", config, perception=f"detector:{__file__}:centre_box")
    assert loaded.perception.num_cells == config.grid.num_cells == 900
