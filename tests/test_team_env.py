"""The team env (search/envs/team_env.py): PettingZoo's own API tests on its Parallel and AEC forms, seeding,
rewards, and stepping it with a team planner's choices is run_team with that planner (synthetic wide caches, no
rendering)."""

import csv

import numpy as np
import pytest
import torch
import yaml

pytest.importorskip("pettingzoo")
from pettingzoo.test import api_test, parallel_api_test  # noqa: E402

from uavsearch.envs import team_aec_env, team_parallel_env  # noqa: E402
from uavsearch.errors import UavsearchError  # noqa: E402
from uavsearch.paths import REPO_ROOT  # noqa: E402
from uavsearch.search.agents import make_fusion, make_planner  # noqa: E402
from uavsearch.search.envs import team_env  # noqa: E402
from uavsearch.search.metrics import map_accuracy, map_f1  # noqa: E402
from uavsearch.search.search_loop import CachedViews, classification_reward  # noqa: E402
from uavsearch.search.team import run_team  # noqa: E402
from uavsearch.testing.synthetic_views import synthetic_wide_cache  # noqa: E402

CACHE = synthetic_wide_cache(3, seed=4)


def _env(**kw):
    return team_parallel_env(cache=CACHE, progress=False, **kw)


def _random_episode(env, seed):
    """(observations, rewards, infos) of one episode of masked random actions drawn from `seed`."""
    rng = np.random.default_rng(seed)
    obs, info = env.reset(seed=seed)
    trace = [(obs, {}, info)]
    while env.agents:
        acts = {a: int(rng.choice(np.flatnonzero(obs[a]["action_mask"]))) for a in env.agents}
        obs, rew, _, _, info = env.step(acts)
        trace.append((obs, rew, info))
    return trace


def test_parallel_api_test_passes():
    parallel_api_test(_env(), num_cycles=1000)


def test_aec_api_test_passes():
    api_test(team_aec_env(cache=CACHE, progress=False), num_cycles=1000)


def test_same_seed_same_trajectory_and_rewards():
    a, b = _random_episode(_env(), 7), _random_episode(_env(), 7)
    assert len(a) == len(b) > 3
    for (oa, ra, ia), (ob, rb, ib) in zip(a, b):
        assert ra == rb and oa.keys() == ob.keys()
        for agent in oa:
            assert all(np.array_equal(oa[agent][k], ob[agent][k]) for k in oa[agent])
            assert ia[agent]["lattice_index"] == ib[agent]["lattice_index"] and ia[agent]["f1"] == ib[agent]["f1"]


def test_only_the_arriving_vehicle_chooses_and_the_others_keep_going():
    env = _env()
    obs, info = env.reset(seed=0)
    assert [info[a]["deciding"] for a in env.agents] == [True, False, False]
    for _ in range(6):
        d = env.deciding_agent
        for a in env.agents:
            mask = obs[a]["action_mask"]
            assert mask[env.KEEP_GOING] == 1 and (mask[:-1].any() == (a == d))
        ok = np.flatnonzero(obs[d]["action_mask"][:-1])
        obs, *_ = env.step({d: int(ok[0]), **{a: env.KEEP_GOING for a in env.agents if a != d}})
        for a in env.agents:  # no viewpoint another vehicle is flying to can be chosen
            flying_to = obs[a]["others_to"].sum(0) > 0
            assert not (obs[a]["action_mask"][:-1].astype(bool) & flying_to).any()


def _learned_aggregation(path) -> str:
    """The spec of a (random) neighbour fusion reading CACHE's cell features, saved at `path`."""
    from uavsearch.search.fusion import CalibratedFusion
    from uavsearch.search.neighbour_fusion import FeatureCorrectionNet, NeighbourFusion, save_neighbour

    torch.manual_seed(0)
    d = int(CACHE.cell_features.shape[-1])
    f = NeighbourFusion.around(CalibratedFusion((1.1, -0.05, -0.3, 0.02), 0.08, 0.5),
                               FeatureCorrectionNet(2 * d, kernel=3, reduce=4, hidden=8).eval(), 0.5, CACHE.config)
    return f"neighbour:{save_neighbour(f, path)}"


@pytest.mark.parametrize("planner,fusion", [("team_entropy:0.8", "bayes:0.5"), ("partition", "average"),
                                            ("rule", "average"), ("team_entropy:0.8", "learned")])
def test_stepping_with_a_planners_choices_is_run_team(planner, fusion, tmp_path):
    if fusion == "learned":  # a learned aggregation reading cell features, which the env's views serve
        fusion = _learned_aggregation(tmp_path / "learned.pt")
    env = _env(fusion=fusion)
    ep = run_team(CachedViews(CACHE, np.arange(CACHE.num_scenes), env.config), make_fusion(fusion),
                  make_planner(planner, env.config), 3, 80.0)
    final = ep.map_at(80.0).numpy()
    y = CACHE.occupancy.numpy()
    for row, seed in enumerate(CACHE.scene_seed):
        env.reset(options={"scene_seed": int(seed)})
        p = make_planner(planner, env.config)
        p.reset(1, env.V)
        while env.agents:
            v, inp = env.planner_input()
            nxt = int(p.choose(inp, v, None)[0])
            acts = {a: env.KEEP_GOING for a in env.agents}
            acts[env.deciding_agent] = nxt if nxt >= 0 else env.KEEP_GOING
            *_, info = env.step(acts)
        last = next(iter(info.values()))
        assert last["views"] == int(ep.views()[row])
        assert last["f1"] == pytest.approx(float(map_f1(final, y)[row]), abs=1e-12)
        assert last["acc"] == pytest.approx(float(map_accuracy(final, y)[row]), abs=1e-12)


@pytest.mark.parametrize("reward", ["shaped", "f1"])
@pytest.mark.parametrize("credit", ["team", "own"])
def test_per_view_rewards_add_up_to_the_final_maps(reward, credit):
    env = _env(credit=credit, reward=reward, fusion="average")
    trace = _random_episode(env, 3)
    total = sum(sum(r.values()) if credit == "own" else next(iter(r.values())) for _, r, _ in trace[1:])
    final = next(iter(trace[-1][2].values()))
    st = env._st
    f1 = float(map_f1(st.fused.numpy(), st.labels.numpy())[0])
    assert final["f1"] == pytest.approx(f1) and (reward == "shaped" or f1 > 0)
    want = float(classification_reward(st.fused, st.labels)[0]) if reward == "shaped" else f1
    assert total == pytest.approx(want, abs=1e-4)


def test_defaults_are_the_team_mission():
    m = yaml.safe_load((REPO_ROOT / "missions" / "wide_team.yaml").read_text())
    assert (m["scene"]["setting"], m["team"]["vehicles"], m["team"]["mission_time_s"], m["fusion"]) == \
        (team_env.TEAM_SETTING, team_env.TEAM_VEHICLES, team_env.TEAM_MISSION_TIME_S, team_env.TEAM_LEARNED_FUSION)
    # the env's default fusion is the hand-made table's choice for the mission's task
    rows = list(csv.DictReader((REPO_ROOT / "results/team_wide/hand_made/team.csv").open()))
    chosen = next(r for r in rows if r["team_planner"] == "True" and int(r["vehicles"]) == team_env.TEAM_VEHICLES
                  and float(r["time_s"]) == team_env.TEAM_MISSION_TIME_S)
    assert chosen["fusion"] == team_env.TEAM_FUSION


@pytest.mark.parametrize("kw,options", [({"reward": "terminal", "credit": "own"}, None), ({"vehicles": 0}, None),
                                        ({}, {"scene_seed": 999999}), ({"setting": 2}, None)])
def test_bad_input_is_one_line(kw, options):
    with pytest.raises(UavsearchError) as e:
        _env(**kw).reset(options=options)
    assert "\n" not in str(e.value)


def test_a_step_without_the_deciding_vehicles_action_is_one_line():
    env = _env()
    env.reset(seed=0)
    with pytest.raises(UavsearchError, match="vehicle_0 decides now"):
        env.step({"vehicle_1": env.KEEP_GOING})
    assert torch.equal(env._st.active, torch.ones(1, 3, dtype=torch.bool))
