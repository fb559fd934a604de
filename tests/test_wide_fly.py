"""`uavsearch fly --mission missions/wide.yaml`: the learned wide-area policy flies one simulated vehicle (its own
`uavsearch sitl` process, real UDP on 127.0.0.1, lockstep) over a `wide` scene for its 240 s of flight, at 70 m
and 40 m, fusing with the fusion saved in its checkpoint; the flight log holds every decision, and replay
re-fuses and draws it."""

import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from uavsearch.errors import UavsearchError
from uavsearch.fly.missions import load_mission, mission_from_dict
from uavsearch.logs.flight_log import read_flight_log
from uavsearch.paths import MISSIONS_DIR, MODELS_DIR
from uavsearch.replay.replay import replay_run_dir, trajectory_figure
from uavsearch.search.fusion import Fusion
from uavsearch.search.policy import load_search_model
from uavsearch.search.search_loop import Observation
from uavsearch.search.team import run_team
from uavsearch.testing.clean_env import clean_env

WIDE = MISSIONS_DIR / "wide.yaml"


@pytest.fixture(scope="module")
def flown(tmp_path_factory):
    run = tmp_path_factory.mktemp("wide") / "run"
    r = subprocess.run([sys.executable, "-m", "uavsearch", "fly", "--mission", str(WIDE), "--out", str(run),
                        "--gcs-port", "0"], capture_output=True, text=True, timeout=300, env=clean_env())
    return r, run


class LoggedMaps(Fusion):
    """The fused maps a flight logged, view by view: for a fusion that reads cell features, which a log does not
    hold, the planner is checked on the maps the flight fused."""

    name = "logged"

    def __init__(self, log):
        super().__init__()
        self.maps = [torch.as_tensor(np.asarray(s.fused), dtype=torch.float32)[None] for s in log.steps]

    def update(self, state, view):
        k = 0 if state is None else state + 1
        return k, self.maps[k]


class LoggedViews:
    """run_team's view source from a flight log: each view's logged perception outputs and capture times, in the
    order flown."""

    def __init__(self, log, config):
        self.steps, self.config, self.batch_size, self.k = log.steps, config, 1, 0
        self.labels = torch.as_tensor(np.asarray(log.labels)).bool().reshape(1, -1)
        self.asked = []

    def mission_time_s(self, vehicle):
        """The flight's clock at the capture just replayed (as the flying team's source reports it)."""
        return torch.tensor([self.steps[self.k - 1].sim_time_s - self.steps[0].sim_time_s], dtype=torch.float64)

    def observe(self, idx):
        s = self.steps[self.k]
        self.k += 1
        self.asked.append(int(idx[0]))
        p = torch.as_tensor(np.asarray(s.p_occ), dtype=torch.float32).clamp(1e-7, 1 - 1e-7)[None]
        return Observation(torch.stack([torch.log1p(-p), torch.log(p)], -1), None, torch.zeros(1, 0),
                           torch.as_tensor(np.asarray(s.cell_area_px), dtype=torch.float32)[None],
                           torch.as_tensor(np.asarray(s.valid)).bool()[None])


def test_the_learned_policy_flies_its_time_and_lands(flown):
    r, run = flown
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "vehicle 1: landed" in r.stdout and "learned wide-area policy" in r.stdout
    summary = json.loads((run / "summary.json").read_text())
    assert summary["status"] == "completed" and summary["vehicles"] == 1
    log = read_flight_log(run)
    carried = load_search_model(load_mission(WIDE).checkpoint_path).fusion  # the fusion saved in the checkpoint
    assert log.header["fusion"] == getattr(carried, "spec", carried.name) and log.header["policy"] == "map"
    views = [s.lattice_idx for s in log.steps]
    assert len(views) == len(set(views)) >= 10  # 240 s buys well over ten views, none twice
    mission = load_mission(WIDE)
    config = mission.search_config()
    # the budget is counted on the vehicle's clock: the mission time is the last capture's since the first, and
    # each decision saw the seconds really left (a leg flies within a second or two of the lattice's prediction)
    assert summary["mission_time_s"] == pytest.approx(log.steps[-1].sim_time_s - log.steps[0].sim_time_s)
    assert 200.0 < summary["mission_time_s"] <= 240.0 + 5.0
    predicted = sum(config.lattice.flight_time_s[a, b] for a, b in zip(views, views[1:]))
    assert abs(predicted - summary["mission_time_s"]) < 2.0 * len(views)
    alts = {round(float(config.lattice.positions_enu[v, 2])) for v in views}
    assert alts <= {70, 40} and 70 in alts
    for s in log.steps:  # each view taken where the policy sent the vehicle, at its altitude
        assert np.linalg.norm(np.subtract(s.reported_position_enu, s.waypoint_enu)) < 1.5
    assert summary["f1"] == pytest.approx(log.steps[-1].f1, abs=1e-6)


def test_the_flown_route_is_the_policys_choice_on_what_each_view_saw(flown):
    """The policy, given the flight's own logged perception outputs, picks exactly the viewpoints flown."""
    r, run = flown
    assert r.returncode == 0
    log = read_flight_log(run)
    mission = load_mission(WIDE)
    config = mission.search_config()
    method = mission.team_method(config)
    source = LoggedViews(log, config)
    fusion = LoggedMaps(log) if "cell_features" in method.fusion.needs else method.fusion
    ep = run_team(source, fusion, method.planner, 1, float(config.budget_s))
    assert source.asked == [s.lattice_idx for s in log.steps]
    assert np.allclose(ep.maps[0, -1].numpy(), log.steps[-1].fused, atol=1e-4)


def test_replay_refuses_with_the_checkpoints_fusion_and_draws_both_altitudes(flown):
    r, run = flown
    assert r.returncode == 0
    d = replay_run_dir(run)
    carried = load_search_model(load_mission(WIDE).checkpoint_path).fusion
    assert d.fusion == getattr(carried, "spec", carried.name)
    assert np.allclose(d.maps[-1], d.logged_maps[-1], atol=1e-5)  # re-fused from the log: the same map
    labels = [t.get_text() for t in trajectory_figure(d).legends[0].get_texts()]
    layers = {round(float(z)) for z in d.positions_enu[:, 2]}
    if len({round(z / 10) for z in layers}) > 1:
        assert any("at 40 m" in t for t in labels) and any("at 70 m" in t for t in labels)


def test_wide_policy_mission_errors_are_one_line(tmp_path):
    base = load_mission(WIDE).model_dump(mode="json")
    for change, words in (
            ({"team": {"vehicles": 3, "mission_time_s": 240}}, "flies one vehicle"),
            ({"fusion": "bayes:0.5"}, "fusion saved in its checkpoint"),
            ({"policy": "rule", "checkpoint": "models/search_wide_240s_map.pt"}, "fusion"),
            ({"policy": "rule", "fusion": "bayes:0.5", "checkpoint": "x.pt"}, "only the learned wide-area policy")):
        with pytest.raises(UavsearchError, match=words) as e:
            mission_from_dict({**base, **change}, "x.yaml")
        assert "\n" not in str(e.value)
    # a checkpoint trained for the view budget, flown under the time budget (and the reverse)
    wrong = mission_from_dict({**base, "checkpoint": str(MODELS_DIR / "search_wide_T8_map.pt")}, "x.yaml")
    with pytest.raises(UavsearchError, match="trained for T = 8 views, this search has 240 s of flight"):
        wrong.team_method()
    views = mission_from_dict({**base, "team": {"vehicles": 1, "mission_time_s": 600, "max_views": 8}}, "x.yaml")
    assert views.checkpoint_path.name == "search_wide_T8_map.pt" and "T = 8 views" in views.team_method().description
    missing = mission_from_dict({**base, "checkpoint": str(tmp_path / "none.pt")}, "x.yaml")
    with pytest.raises(UavsearchError, match="no file"):
        missing.team_method()


def test_the_flight_ends_beside_the_first_view_the_best_fixed_route_and_the_rule(flown):
    """The comparison printed and written at the end: its rows, and the rule's teleport F1 on the scene equals what
    Table III's code (evaluate/wide.run_rows over the view cache) gives for it."""
    from uavsearch.fly.scene_baselines import COMPARISON_FILE, table3_choice
    from uavsearch.search.config import wide_budgets
    from uavsearch.search.data.view_cache import get_view_cache
    from uavsearch.search.evaluate.wide import rule_agent, run_rows
    from uavsearch.search.perception import load_perception

    r, run = flown
    assert r.returncode == 0
    c = json.loads((run / COMPARISON_FILE).read_text())
    assert [row["key"] for row in c["rows"]] == ["first_view", "survey_outer", "descend_rule", "teleport_own", "flown"]
    assert [row["mode"] for row in c["rows"]] == ["teleport"] * 4 + ["flown"]
    assert "best fixed route" in r.stdout and "the rule" in r.stdout and "this flight" in r.stdout
    summary = json.loads((run / "summary.json").read_text())
    assert c["rows"][-1]["f1"] == pytest.approx(summary["f1"], abs=1e-6) and c["rows"][0]["views"] == 1
    mission = load_mission(WIDE)
    assert c["scene"] == mission.scene.seed == 131000  # the first validation scene: its cache row is row 0
    net, _ = load_perception(mission.perception_path)
    cache = get_view_cache(net, "wide", "large", "val", features=False, limit=1, progress=False)
    cfg = wide_budgets(cache.config)["240 s"]
    variant = table3_choice("wide", "240 s")["rule_variant"]
    assert variant is not None
    fusion = mission.team_method(mission.search_config()).fusion
    res = run_rows(cache, cfg, {"rule": (rule_agent(fusion, cfg, variant), 1)})["rule"]
    assert c["rows"][2]["f1"] == pytest.approx(float(res["f1"][0, 0, -1]), abs=1e-9)
    assert c["rows"][2]["views"] == int(res["views"][0])
