"""WideSearch-v0 is Table III's task: its defaults are what results/search_wide/table3.md chose (budget, fusion,
rule, best fixed route), Table III's rule played through the env (LoopPolicyPlayer) flies the routes and scores
the AF1 the evaluation code (run_search on the same view cache) does, and a first reset that would render a whole
part says so and refuses. Synthetic caches but the slow test, which renders a few validation scenes."""

import re

import gymnasium as gym
import numpy as np
import pytest
import torch

import uavsearch.envs  # noqa: F401 - registers the ids
from uavsearch.errors import UavsearchError
from uavsearch.paths import REPO_ROOT
from uavsearch.search.config import setting_config
from uavsearch.search.envs.search_env import (CALIBRATION_SCENES, TABLE3, LoopPolicyPlayer, WideSearchEnv, play_scenes,
                                              cells_frame)
from uavsearch.search.evaluate.wide import LABELS
from uavsearch.search.fusion import CalibratedFusion
from uavsearch.search.policy import load_search_model
from uavsearch.search.scoring import score_episode
from uavsearch.search.search_loop import Agent, CachedViews, run_search
from uavsearch.search.wide_policies import rule_policy
from uavsearch.testing.synthetic_views import synthetic_cache

WIDE = synthetic_cache(4, k=10, seed=2, config=setting_config("wide"))


def test_table3_constants_are_the_committed_tables():
    text = (REPO_ROOT / "results/search_wide/table3.md").read_text()
    heads = {"8": "### wide, T = 8 views", "240": "### wide, 240 s"}
    for budget, task in TABLE3.items():
        part = text.split(heads[budget])[1].split("###")[0]
        assert f"Fusion **{task.fusion}**" in part
        assert f"chosen on the validation scenes: **{task.rule}**" in part
        assert re.search(re.escape(f"{task.rule} {task.rule_val_af1:.3f}") + r"[,)]", part)
        assert f"{LABELS[task.best_fixed]} (best fixed)" in part
        assert 0 < task.rule_val_af1 < 1 and task.source == "results/search_wide/table3.md"
    assert "--wide-train-scenes 20" in (REPO_ROOT / "tools/reproduce.sh").read_text() and CALIBRATION_SCENES == 20


def test_defaults_are_table3s_task_and_fusion():
    env = gym.make("uavsearch/WideSearch-v0", progress=False).unwrapped
    assert (env.config.budget_T, env.config.budget_s, env.part, env.split) == (8, None, "train", "large")
    assert isinstance(env.fusion, CalibratedFusion) and env.fusion.spec == "calibrated:0.25"
    shipped, _, extra = load_search_model(REPO_ROOT / "models/search_wide_T8_map.pt", "cpu")
    shipped = getattr(shipped, "base", shipped)  # a learned aggregation keeps Table III's calibration beneath
    assert env.fusion.coef == shipped.coef and extra["args"]["calibration_scenes"] == CALIBRATION_SCENES
    timed = WideSearchEnv(budget=240, part="val", progress=False)
    assert (timed.config.budget_T, timed.config.budget_s, timed.fusion.spec) == (73, 240.0, "calibrated:0.75")
    vec = gym.make_vec("uavsearch/WideSearch-v0", num_envs=2, vectorization_mode="vector_entry_point",
                       budget="240", progress=False).unwrapped
    assert vec.config == timed.config and vec.fusion.spec == "calibrated:0.75"
    with pytest.raises(UavsearchError, match="budget must be 8"):
        WideSearchEnv(budget=100, progress=False)


def test_a_first_reset_that_would_render_a_whole_part_says_how_much_and_refuses(tmp_path):
    env = WideSearchEnv(part="val", cache_dir=tmp_path, progress=False)
    with pytest.raises(UavsearchError) as e:
        env.reset(seed=0)
    msg = str(e.value)
    assert "render 50 scenes of wide large/val" in msg and " min " in msg and "950 MB under cache/" in msg
    assert "limit=N" in msg and "render_all=True" in msg and "\n" not in msg
    assert not any(tmp_path.iterdir())  # nothing rendered


@pytest.mark.parametrize("budget", ["8", "240"])
@pytest.mark.parametrize("fusion", [None, "bayes:0.3"])
def test_the_rule_through_the_env_is_the_evaluations_rule(budget, fusion):
    env = WideSearchEnv(cache=WIDE, budget=budget, fusion=fusion, progress=False)
    rule = rule_policy(env.config, TABLE3[budget].rule)
    f1, routes = _play(env, rule, WIDE.scene_seed)
    ep = run_search(CachedViews(WIDE, np.arange(WIDE.num_scenes), env.config), Agent(env.fusion, rule))
    assert [ep.lattice_idx[i, :len(r)].tolist() for i, r in enumerate(routes)] == routes
    np.testing.assert_array_equal(np.float32(f1), np.float32(score_episode(ep).f1[:, -1]))


def test_cells_render_is_the_fused_map_beside_the_truth():
    env = WideSearchEnv(cache=WIDE, render_mode="rgb_array", progress=False)
    assert env.render() is None  # before reset
    env.reset(seed=0)
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[1] > 2 * frame.shape[0] - 60
    labels = np.zeros(900, bool)
    labels[0] = True
    f = cells_frame(np.zeros(900), labels, np.ones(900, bool), 30)
    assert (f[18:26, -240:-232] == (230, 40, 40)).all()  # the NW cell of the truth panel is red


def _play(env, policy, seeds):
    return play_scenes(env, LoopPolicyPlayer(policy, env.config).act, seeds)


@pytest.mark.slow
def test_the_rule_through_the_env_equals_table3s_code_on_validation_scenes():
    """Three validation scenes (rendered on first use, about 10 s each): the env with its defaults against
    the evaluation's rule on the same view cache, route for route."""
    env = WideSearchEnv(part="val", limit=3, progress=False)
    rule = rule_policy(env.config, TABLE3["8"].rule)
    f1, routes = _play(env, rule, env.scenes.seeds)
    cache = env.scenes.cache
    with torch.no_grad():
        ep = run_search(CachedViews(cache, np.arange(cache.num_scenes), env.config), Agent(env.fusion, rule))
    assert [ep.lattice_idx[i].tolist() for i in range(len(routes))] == routes
    np.testing.assert_array_equal(np.float32(f1), np.float32(score_episode(ep).f1[:, -1]))


@pytest.mark.slow
def test_the_wide_ppo_example_reports_against_the_rule_and_the_best_fixed_route(tmp_path, capsys):
    import sys

    sys.path.insert(0, str(REPO_ROOT / "examples"))
    import wide_ppo

    out = wide_ppo.main(["--train-scenes", "2", "--val-scenes", "2", "--total-timesteps", "1024",
                         "--runs-dir", str(tmp_path)])
    assert set(out["af1"]) == {"PPO (this run)", "the rule", "best fixed route"}
    assert set(out["delta"]) == {"the rule", "best fixed route"}
    assert "compared on the first 2 validation scenes" in capsys.readouterr().out
