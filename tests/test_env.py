"""The teleport environments: gymnasium conformance in every mode, determinism, lattice moves and revisits, the
paper's reward, the cached views (and the live fallback), the native vector env against N single envs."""

import os
import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

from uavsearch.errors import SceneError
from uavsearch.search.fusion import FUSIONS
from uavsearch.search.config import SearchConfig
from uavsearch.search.envs.search_env import ActiveSearchEnv
from uavsearch.search.perception import PerceptionConfig, PerceptionNet
from uavsearch.search.metrics import map_f1
from uavsearch.search.search_loop import R_RE, Agent, LiveViews, run_search, step_rewards
from uavsearch.search.views import TeleportVehicle
from uavsearch.world.scene import generate_scene

NORTH, EAST, WEST, SOUTH = 0, 1, 2, 3


@pytest.fixture(scope="module")
def env():
    e = ActiveSearchEnv(setting=1, views="live")
    yield e
    e.close()


def test_lattice_is_the_paper_one():
    cfg = SearchConfig()
    pos = cfg.lattice.positions_enu
    assert pos.shape == (25, 3)
    assert set(np.unique(pos[:, 0])) == {-20.0, -10.0, 0.0, 10.0, 20.0}
    assert np.all(pos[:, 2] == 70.0)
    assert pos[cfg.lattice.index((0, 0))] == pytest.approx([0, 0, 70])
    assert pos[cfg.lattice.index((2, 2))] == pytest.approx([20, 20, 70])  # NE corner
    assert cfg.lattice.index((-2, 2)) == 0  # NW corner first, like the cell grid


@pytest.mark.slow  # gymnasium's full check_env (about 20 s): `make test-all` runs it
def test_check_env_passes():
    e = gym.make("uavsearch.envs:uavsearch/ActiveSearch-v0", setting=1, views="live")
    check_env(e.unwrapped, skip_render_check=True)
    e.close()


def test_reset_starts_above_centre_and_step_moves_10m(env):
    obs, info = env.reset(seed=1)
    assert obs["position_enu"] == pytest.approx([0, 0, 70])
    assert obs["step"] == 0 and obs["image"].shape == (224, 224, 3)
    assert info["occupancy"].sum() == 2 and not info["revisit"]
    obs, r, term, trunc, info = env.step(EAST)
    assert obs["position_enu"] == pytest.approx([10, 0, 70]) and r == 0.0 and not term and not trunc
    obs, r, *_ = env.step(NORTH)
    assert obs["position_enu"] == pytest.approx([10, 10, 70])


def test_budget_terminates_after_T_views(env):
    env.reset(seed=2)
    terms = [env.step(EAST)[2] for _ in range(env.config.budget_T - 1)]
    assert terms == [False] * (env.config.budget_T - 2) + [True]
    with pytest.raises(gym.error.ResetNeeded):
        env.step(EAST)


def test_leaving_the_lattice_stays_and_counts_as_revisit(env):
    env.reset(seed=3)
    env.step(WEST)
    obs, r, _, _, info = env.step(WEST)
    assert obs["position_enu"] == pytest.approx([-20, 0, 70]) and not info["revisit"]
    obs, r, _, _, info = env.step(WEST)  # would leave the area
    assert obs["position_enu"] == pytest.approx([-20, 0, 70])
    assert info["revisit"] and r == env.r_revisit


def test_going_back_is_a_revisit(env):
    env.reset(seed=4)
    env.step(NORTH)
    _, r, _, _, info = env.step(SOUTH)
    assert info["revisit"] and r == R_RE == -0.5  # the R_re stage 2 trains with


def test_same_seed_same_scene_and_images():
    a, b = ActiveSearchEnv(setting=2, views="live"), ActiveSearchEnv(setting=2, views="live")
    oa, ia = a.reset(seed=7)
    ob, ib = b.reset(seed=7)
    assert ia["scene_seed"] == ib["scene_seed"]
    assert np.array_equal(oa["image"], ob["image"])
    assert np.array_equal(a.step(EAST)[0]["image"], b.step(EAST)[0]["image"])
    a.close(), b.close()


def test_cells_in_view_and_labels_agree(env):
    obs, _ = env.reset(seed=5)
    labels = np.unique(obs["cell_label"])
    seen = set(labels[labels >= 0].tolist())
    # at the centre the whole grid is in view: every cell has pixels and a positive area
    assert seen == set(range(100))
    assert np.all(obs["cells_in_view"] == 1) and np.all(obs["cell_area_px"] > 50)


def test_reset_options_choose_the_scene(env):
    _, info = env.reset(seed=0, options={"occupied_cells": 7, "scene_seed": 123})
    assert info["occupancy"].sum() == 7 and info["scene_seed"] == 123
    with pytest.raises(SceneError):
        env.reset(options={"setting": 9})


class _Scripted:
    """A policy that plays a fixed action sequence."""

    def __init__(self, actions):
        self.actions = actions

    def act(self, inp, generator=None):
        return torch.full((1,), self.actions[inp.step], dtype=torch.long), None, None


@pytest.mark.parametrize("actions", [(WEST, WEST, WEST, EAST), (NORTH, SOUTH, NORTH, EAST), (EAST, NORTH, WEST, SOUTH)])
def test_env_and_search_loop_agree_step_for_step(actions):
    """Same scene, perception, fusion and actions: the env and run_search visit the same positions, flag the
    same revisits, and the env pays each step what training's step_rewards pays that view."""
    scene = generate_scene(11, 2)
    torch.manual_seed(0)
    net = PerceptionNet(PerceptionConfig())
    env = ActiveSearchEnv(setting=1, views="live", perception=net, fusion="average")
    obs, info = env.reset(seed=0, options={"scene": scene})
    env_pos, env_idx, env_rev, env_r = [obs["position_enu"]], [info["lattice_index"]], [info["revisit"]], []
    for a in actions:
        obs, r, term, _, info = env.step(a)
        env_pos.append(obs["position_enu"])
        env_idx.append(info["lattice_index"])
        env_rev.append(info["revisit"])
        env_r.append(r)
    assert term
    env.close()
    with TeleportVehicle(scene, env.config) as vehicle, torch.no_grad():
        views = LiveViews(vehicle, net, scene.occupancy_array())
        ep = run_search(views, Agent(FUSIONS["average"](), _Scripted(actions)), generator=torch.Generator().manual_seed(0))
    assert ep.lattice_idx[0].tolist() == env_idx
    assert ep.revisit[0].tolist() == env_rev
    np.testing.assert_array_equal(np.stack([v.position_enu for v in views.views]).astype(np.float32), env_pos)
    r = step_rewards(ep.maps, ep.labels, ep.revisit)[0]  # training's reward of each view
    assert float(r[0]) == 0.0 and env_r == pytest.approx(r[1:].tolist(), abs=1e-6)
    assert info["f1"] == pytest.approx(float(map_f1(ep.maps[0, -1].numpy(), ep.labels[0].numpy())))


def test_gymnasium_finds_the_env_by_module_id_and_plain_import_skips_gymnasium():
    """A fresh interpreter: gymnasium's `module:id` form imports the registering module itself, and
    `import uavsearch` alone never loads gymnasium (the vehicle's processes don't need it)."""
    env = {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "HOME": os.environ.get("HOME", "/tmp")}
    code = ("import sys, uavsearch; assert 'gymnasium' not in sys.modules, 'uavsearch imports gymnasium'\n"
            "import gymnasium as gym\n"
            "e = gym.make('uavsearch.envs:uavsearch/ActiveSearch-v0', setting=1)\n"
            "print(type(e.unwrapped).__name__, e.action_space)")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["ActiveSearchEnv", "Discrete(4)"]
