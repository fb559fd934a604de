"""Teleport teams (search/team.py): one shared map, events on simulated time, the separation of viewpoints,
the team planners, and the team table on a tiny synthetic family (no rendering)."""

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from uavsearch.errors import UavsearchError
from uavsearch.search.config import setting_config
from uavsearch.paths import display_path
from uavsearch.search.checkpoints import wide_checkpoint
from uavsearch.search.evaluate.team import (TeamEvalArgs, _fusion_specs, eval_team, learned_aggregations,
                                            make_planner)
from uavsearch.search.fusion import FUSIONS, CalibratedFusion
from uavsearch.search.neighbour_fusion import CorrectionNet, NeighbourFusion, save_neighbour
from uavsearch.search.policy import load_search_model
from uavsearch.search.search_loop import Agent, CachedViews, run_search
from uavsearch.search.team import EachVehicle, Partition, TeamEntropy, TeamRule, run_team
from uavsearch.search.wide_policies import DescendRule, EntropyPerSecond, footprints, lowest_layer
from uavsearch.testing.synthetic_views import synthetic_cache

WIDE = dataclasses.replace(setting_config("wide"), budget_T=73)


def wide_cache(num_scenes=4, seed=0, k=10):
    c = synthetic_cache(num_scenes, k=k, seed=seed, config=WIDE)
    valid = footprints(WIDE)[None].expand(num_scenes, -1, -1).clone()
    return c._replace(valid=valid, person_px=(c.occupancy[:, None, :] & valid).int() * 5)


def _team(cache, planner, vehicles, budget_s, **kw):
    return run_team(CachedViews(cache, np.arange(cache.num_scenes), WIDE), FUSIONS["average"](), planner, vehicles,
                    budget_s, **kw)


def test_one_vehicle_team_is_the_search_loop():
    """A team of one with the team rule flies the rule's episode of run_search under the same time budget."""
    cache = wide_cache(3)
    cfg = dataclasses.replace(WIDE, budget_s=120.0)
    ep = run_search(CachedViews(cache, np.arange(3), cfg), Agent(FUSIONS["average"](), DescendRule(cfg)))
    team = _team(cache, TeamRule(WIDE), 1, 120.0)
    for b in range(3):
        assert team.lattice_idx[b, team.taken[b]].tolist() == ep.lattice_idx[b, ep.taken[b]].tolist()
    assert torch.allclose(team.map_at(120.0), ep.maps[:, -1])
    # the same for entropy per second (the team's version reduces to it with one vehicle)
    ep = run_search(CachedViews(cache, np.arange(3), cfg), Agent(FUSIONS["average"](), EntropyPerSecond(cfg)))
    team = _team(cache, TeamEntropy(WIDE), 1, 120.0)
    assert team.lattice_idx[0, team.taken[0]].tolist() == ep.lattice_idx[0, ep.taken[0]].tolist()


@pytest.mark.parametrize("planner", ["rule", "rule_per_s", "partition", "entropy_per_s", "team_entropy:0.8"])
def test_a_team_never_shares_a_viewpoint_and_keeps_the_mission_time(planner):
    cache = wide_cache(4, seed=1)
    ep = _team(cache, make_planner(planner, WIDE), 3, 80.0)
    cost = WIDE.lattice.flight_time_s
    for b in range(4):
        views = ep.lattice_idx[b, ep.taken[b]].tolist()
        assert len(views) == len(set(views))  # no viewpoint twice, by any vehicle
        assert (ep.time_s[b, ep.taken[b]] <= 80.0 + 1e-4).all()
        for v in range(3):  # each vehicle's own timeline: its flights take the lattice's flight times
            mine = (ep.vehicle[b] == v) & ep.taken[b]
            idx, t = ep.lattice_idx[b, mine].tolist(), ep.time_s[b, mine].tolist()
            start = [WIDE.lattice.start_index] if v else []
            path, times = start + idx, ([0.0] if v else []) + t
            for i in range(1, len(path)):
                assert times[i] - times[i - 1] == pytest.approx(cost[path[i - 1], path[i]], abs=1e-3)
        assert ep.vehicle[b, 0] == 0 and ep.time_s[b, 0] == 0.0 and ep.taken[b, 0]  # the free start view
        assert set(ep.vehicle[b, ep.taken[b]].tolist()) == {0, 1, 2}


def test_more_vehicles_see_more_in_the_same_time():
    cache = wide_cache(4, seed=2)
    views = [float(_team(cache, TeamEntropy(WIDE), n, 60.0).views().float().mean()) for n in (1, 2, 3)]
    assert views[0] < views[1] < views[2]


def test_partition_keeps_each_vehicle_in_its_strip():
    cache = wide_cache(2, seed=3)
    ep = _team(cache, Partition(WIDE), 3, 200.0)
    east = WIDE.lattice.positions_enu[:, 0]
    for b in range(2):
        for v in range(3):
            mine = (ep.vehicle[b] == v) & ep.taken[b]
            idx = ep.lattice_idx[b, mine]
            if v == 0:
                idx = idx[1:]  # the start view above the centre
            x = east[idx.numpy()]
            assert len(x) and x.min() >= -75 + 50 * v and x.max() <= -75 + 50 * (v + 1)


def test_team_entropy_leaves_what_another_vehicle_will_see():
    """A cell inside the footprint another vehicle is flying to counts less: the decider looks elsewhere."""
    cache = wide_cache(1, seed=4)
    ep_shared = _team(cache, TeamEntropy(WIDE, shared=1.0), 2, 40.0)
    ep_blind = _team(cache, EachVehicle(EntropyPerSecond(WIDE)), 2, 40.0)
    foot = footprints(WIDE).float()

    def overlap(ep):
        first = [int(ep.lattice_idx[0, (ep.vehicle[0] == v) & ep.taken[0]][-1 if v == 0 else 0]) for v in (0, 1)]
        return float((foot[first[0]] * foot[first[1]]).sum())

    assert overlap(ep_shared) <= overlap(ep_blind)


def test_bad_planners_are_one_line_errors():
    with pytest.raises(UavsearchError, match="unknown team planner"):
        make_planner("nonsense", WIDE)
    with pytest.raises(UavsearchError, match=r"\[0, 1\]"):
        make_planner("team_entropy:2", WIDE)
    with pytest.raises(UavsearchError, match="at least one vehicle"):
        _team(wide_cache(1), TeamRule(WIDE), 0, 10.0)


def test_team_table_on_a_tiny_synthetic_family(tmp_path):
    caches = {"test": wide_cache(3, 5), "val": wide_cache(2, 6), "train": wide_cache(1, 7)}
    args = TeamEvalArgs(out=str(tmp_path), vehicles="1,3", times="30,90", bootstrap=200, progress=False,
                        fusions="average,bayes:0.3")
    res = eval_team(args, caches)
    text = (tmp_path / "team.md").read_text()
    assert "| 3 | 30 s |" in text and "Δ vs 1 vehicle at 90 s" in text
    for name in ("team.csv", "team_paired.csv", "team.png"):
        assert (tmp_path / name).is_file()
    conds = res["conditions"]
    assert set(conds) == {(1, 30.0), (1, 90.0), (3, 30.0), (3, 90.0)}
    ref = next(p for p in res["paired"] if p["vehicles"] == 1 and p["time_s"] == 90.0 and p["team_planner"])
    assert ref["diff"] == 0.0  # the reference against itself
    with pytest.raises(UavsearchError, match="positive"):
        eval_team(dataclasses.replace(args, times="0,-1"), caches)


def test_a_learned_aggregation_is_a_team_candidate(tmp_path):
    """A neighbour fusion named by its checkpoint is chosen among like the hand-made ones (here an untrained one
    on scores); the shipped stacks' aggregations are candidates only where fitted on the caches' perception."""
    torch.manual_seed(0)
    nf = NeighbourFusion(CalibratedFusion((1.0, 0.0, 0.0, 0.0), 0.1, 0.5), CorrectionNet().eval(), 0.0,
                         lowest_layer(WIDE), WIDE.grid.n)
    spec = f"neighbour:{save_neighbour(nf, tmp_path / 'nf.pt')}"
    caches = {"test": wide_cache(2, 5), "val": wide_cache(2, 6), "train": wide_cache(1, 7)}
    args = TeamEvalArgs(out=str(tmp_path / "t"), vehicles="1", times="40", bootstrap=100, progress=False,
                        fusions=f"average,{spec}")
    res = eval_team(args, caches)
    cond = res["conditions"][(1, 40.0)]
    assert {cond[k]["fusion"] for k in cond if k != "chosen"} <= {"average", spec}
    assert "neighbour:" in (tmp_path / "t" / "team.md").read_text()  # the candidates are named
    with pytest.raises(UavsearchError, match="--learned"):
        eval_team(dataclasses.replace(args, learned="12"), caches)

    assert _fusion_specs("average, neighbour:a.pt,b.pt,bayes:0.5") == ["average", "neighbour:a.pt,b.pt", "bayes:0.5"]
    assert learned_aggregations("synthetic") == []
    path = wide_checkpoint("240")
    tag = load_search_model(path).extra["perception_tag"]
    assert learned_aggregations(tag) == [f"neighbour:{display_path(path)}"]
    assert len(learned_aggregations(tag, budgets=("8", "240"))) == 2


def test_the_team_comparison_reads_each_tables_team_planners(tmp_path):
    """tools/team_learned_vs_hand_made.py pairs the committed tables' choices: one team planner per condition,
    the learned table's on the learned aggregation; a file without such rows is one line."""
    from uavsearch.paths import REPO_ROOT
    from uavsearch.research.team_learned_vs_hand_made import team_choices

    learned = team_choices(REPO_ROOT / "results/team_wide/team.csv")
    hand = team_choices(REPO_ROOT / "results/team_wide/hand_made/team.csv")
    assert set(learned) == set(hand) and len(learned) == 15
    assert all(f.startswith("neighbour:") for _, f, _ in learned.values())
    assert not any(f.startswith("neighbour:") for _, f, _ in hand.values())
    bad = tmp_path / "team.csv"
    bad.write_text("vehicles,time_s\n1,40\n")
    with pytest.raises(UavsearchError, match="no team planner rows"):
        team_choices(bad)
