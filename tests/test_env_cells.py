"""The envs on cached views: "cells" observations, the paper's reward in both modes, the native vector env against
N single envs (seeds, autoreset), the wide family's masks and budgets, the live fallback and its notice, and the
external policy reading in run_search what the env showed it. Synthetic caches: no rendering but the fallback's."""

import warnings

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from gymnasium.wrappers import FlattenObservation

import uavsearch.envs  # noqa: F401 - registers the ids
from uavsearch.search.cells import flatten_cells
from uavsearch.search.config import setting_config
from uavsearch.search.envs.search_env import ActiveSearchEnv, WideSearchEnv
from uavsearch.search.external_policy import ExternalPolicyNet
from uavsearch.search.fusion import FUSIONS
from uavsearch.search.search_loop import R_RE, Agent, CachedViews, classification_reward, run_search
from uavsearch.search.envs.vector_env import SearchVectorEnv
from uavsearch.testing.synthetic_views import synthetic_cache

PAPER = synthetic_cache(4, k=5, seed=1)  # setting 2's K, scene seeds 0..3
WIDE = synthetic_cache(3, k=10, seed=2, config=setting_config("wide"))


def _paper(**kw):
    return dict(setting=2, obs="cells", fusion="bayes", cache=PAPER, **kw)


def _wide(**kw):
    return dict(obs="cells", fusion="bayes", cache=WIDE, budget=None, **kw)  # both budgets at once


@pytest.mark.parametrize("kw", [_paper(), _paper(reward="shaped"), _wide(), _wide(reward="shaped")],
                         ids=["cells", "cells-shaped", "wide", "wide-shaped"])
def test_check_env_passes_in_cells_mode(kw):
    env = WideSearchEnv(**kw) if kw["cache"] is WIDE else ActiveSearchEnv(**kw)
    check_env(env, skip_render_check=True)
    obs, info = env.reset(seed=3)
    assert env.observation_space.contains(obs) and 0.0 <= info["f1"] <= 1.0
    assert obs["fused"].shape == (env.config.grid.n,) * 2 and obs["position"].argmax() == env.config.lattice.start_index


def test_image_mode_from_the_caches_passes_check_env():
    """The renders of the cached lattice views (one scene of setting 2's paper split; built on first use)."""
    env = gym.make("uavsearch/ActiveSearch-v0", setting=2, limit=1, fusion="bayes", progress=False)
    check_env(env.unwrapped, skip_render_check=True)
    obs, info = env.reset(seed=0)
    assert info["cached"] and obs["image"].shape == (224, 224, 3) and obs["image"].std() > 5
    cells = ActiveSearchEnv(setting=2, limit=1, fusion="bayes", obs="cells", progress=False)
    c, ci = cells.reset(seed=0)
    assert ci["scene_seed"] == info["scene_seed"] and ci["f1"] == info["f1"]
    assert np.array_equal(c["in_view"].ravel() > 0, obs["cells_in_view"] > 0)  # every cell at the centre


def _episode(env, seed, actions):
    env.reset(seed=seed)
    rewards, infos = [], []
    for a in actions:
        _, r, term, _, info = env.step(a)
        rewards.append(r)
        infos.append(info)
        if term:
            break
    return rewards, infos


@pytest.mark.parametrize("kw", [_paper(), _wide()], ids=["paper", "wide"])
def test_shaped_rewards_sum_to_the_terminal_reward(kw):
    make = WideSearchEnv if kw["cache"] is WIDE else ActiveSearchEnv
    term_env, shaped_env = make(**kw), make(**{**kw, "reward": "shaped"})
    rng = np.random.default_rng(0)
    for seed in range(12 if kw["cache"] is PAPER else 3):
        actions = rng.integers(term_env.action_space.n, size=10).tolist()
        if kw["cache"] is PAPER and seed % 3 == 0:
            actions = [1, 2, 1, 2]  # revisits on purpose
        r_term, infos = _episode(term_env, seed, actions)
        r_shaped, _ = _episode(shaped_env, seed, actions)
        assert len(r_term) == len(r_shaped) and all(r == 0 or r == R_RE for r in r_term[:-1])
        assert sum(r_shaped) == pytest.approx(sum(r_term), abs=1e-5)
        fused = torch.as_tensor(term_env._batch.fused[0])
        labels = torch.as_tensor(infos[-1]["occupancy"]).bool()
        revisits = sum(i["revisit"] for i in infos)
        assert sum(r_term) == pytest.approx(float(classification_reward(fused, labels)) + R_RE * revisits, abs=1e-5)
    assert any(i["revisit"] for i in infos) or kw["cache"] is WIDE


@pytest.mark.parametrize("kw,n", [(_paper(reward="shaped"), 3), (_wide(), 2)], ids=["paper", "wide"])
def test_vector_env_equals_n_single_envs_step_for_step(kw, n):
    env_id = "uavsearch/WideSearch-v0" if kw["cache"] is WIDE else "uavsearch/ActiveSearch-v0"
    native = gym.make_vec(env_id, num_envs=n, vectorization_mode="vector_entry_point", **kw)
    sync = gym.make_vec(env_id, num_envs=n, vectorization_mode="sync", **kw)
    assert isinstance(native.unwrapped, SearchVectorEnv)
    assert native.metadata["autoreset_mode"] == sync.metadata["autoreset_mode"] == gym.vector.AutoresetMode.NEXT_STEP
    assert native.single_observation_space == sync.single_observation_space
    on, _ = native.reset(seed=5)
    os_, _ = sync.reset(seed=5)
    rng = np.random.default_rng(1)
    resets = 0
    for _ in range(30 if n == 3 else 16):
        for k in on:
            np.testing.assert_array_equal(on[k], os_[k], err_msg=k)
        a = rng.integers(native.single_action_space.n, size=n)
        on, rn, tn, trn, info_n = native.step(a)
        os_, rs, ts, trs, info_s = sync.step(a)
        np.testing.assert_allclose(rn, rs, atol=1e-6)
        assert np.array_equal(tn, ts) and np.array_equal(trn, trs)
        np.testing.assert_allclose(info_n["f1"], info_s["f1"])
        assert np.array_equal(info_n["scene_seed"], info_s["scene_seed"])
        resets += int(ts.sum())
    assert resets >= n  # every episode ended and autoreset at least once


def test_vector_autoreset_is_next_step():
    env = SearchVectorEnv(2, **_paper())
    obs, _ = env.reset(seed=0)
    start = obs["position"].copy()
    for t in range(4):  # T = 5 views: the 4th step ends both episodes
        obs, r, term, trunc, info = env.step([1, 0])
        assert term.tolist() == [t == 3] * 2 and not trunc.any()
    assert (obs["step"].argmax(1) == 4).all()
    last_seed = info["scene_seed"].copy()
    obs, r, term, trunc, info = env.step([3, 3])  # ignored: this step resets
    assert r.tolist() == [0.0, 0.0] and not term.any() and not trunc.any()
    np.testing.assert_array_equal(obs["position"], start)
    assert (obs["step"].argmax(1) == 0).all() and (obs["visits"].sum(1) == 1).all()
    obs, r, term, *_ = env.step([1, 1])  # the next step moves again
    assert (obs["step"].argmax(1) == 1).all() and not np.array_equal(obs["position"], start)
    assert last_seed.shape == (2,)
    obs, _ = env.reset(options={"reset_mask": np.array([True, False])})
    assert obs["step"].argmax(1).tolist() == [0, 1]


def test_wide_env_masks_and_budgets():
    env = WideSearchEnv(**_wide())
    assert env.action_space.n == 73 and env.config.budget_s == 240.0
    obs, info = env.reset(seed=0)
    start = env.config.lattice.start_index
    assert obs["action_mask"][start] == 0 and obs["action_mask"].sum() == 72 and info["action_mask"].sum() == 72
    assert obs["time_left_s"][0] == 240.0
    far = int(np.argmax(env.config.lattice.flight_time_s[start]))
    obs, r, term, _, info = env.step(far)
    assert obs["time_left_s"][0] == pytest.approx(240.0 - env.config.lattice.flight_time_s[start, far], abs=1e-3)
    assert obs["action_mask"][far] == 0 and not term
    steps = 1
    while not term:
        mask = obs["action_mask"]
        obs, r, term, _, info = env.step(int(np.flatnonzero(mask)[-1]))
        steps += 1
    assert steps <= env.config.budget_T - 1 and len(set(info["visited"])) == len(info["visited"])


def test_a_scene_outside_the_caches_is_rendered_live_with_one_notice():
    env = ActiveSearchEnv(**_paper())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _, info = env.reset(seed=0)  # a cached scene: silent
    assert info["cached"]
    with pytest.warns(UserWarning, match="not in the view caches.*rendering it live") as record:
        obs, info = env.reset(options={"scene_seed": 424242})
        obs2, r, *_ = env.step(1)
    assert len(record) == 1 and not info["cached"] and info["scene_seed"] == 424242
    assert env.observation_space.contains(obs) and env.observation_space.contains(obs2)
    assert obs["in_view"].sum() > 50 and info["occupancy"].sum() == 5
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # once per env
        _, info = env.reset(options={"scene": env.scene})  # live again (rendered already)
    assert not info["cached"]
    env.close()


@pytest.mark.parametrize("cache", [PAPER, WIDE], ids=["paper", "wide"])
def test_external_policy_sees_in_run_search_what_the_env_showed(cache):
    """The same episode in the env and in run_search (the evaluation): the external actor's input rebuilt from
    PolicyInput equals the env's flattened observation (gymnasium's FlattenObservation) at every step."""
    config = cache.config
    net = ExternalPolicyNet.for_config(config)
    seen = []

    class Recorder:
        def act(self, inp, generator=None):
            seen.append(flatten_cells(net.observation(inp))[0])
            return net.act(inp, generator, greedy=True)

    with torch.no_grad():
        ep = run_search(CachedViews(cache, [1], config), Agent(FUSIONS["bayes"](), Recorder()))
    env = FlattenObservation(WideSearchEnv(**_wide()) if cache is WIDE else ActiveSearchEnv(**_paper()))
    obs, _ = env.reset(options={"scene_seed": 1})
    assert obs.shape == (net.cfg.obs_dim,)
    for t, x in enumerate(seen):
        np.testing.assert_allclose(obs, x, atol=1e-6, err_msg=f"view {t}")
        obs, *_ = env.step(int(ep.actions[0, t]))
