"""`uavsearch fly --vehicles 3` on the wide mission: three simulated vehicles (one `uavsearch sitl --vehicles 3`
process, real UDP on 127.0.0.1, lockstep) search one map with the team planner, land, and score the map; the
flight log holds every vehicle and replay draws every track."""

import json
import re
import subprocess
import sys

import numpy as np
import pytest

from uavsearch.errors import UavsearchError
from uavsearch.fly.missions import load_mission, mission_from_dict
from uavsearch.logs.flight_log import read_flight_log
from uavsearch.paths import MISSIONS_DIR
from uavsearch.replay.flight_review import write_flight_review
from uavsearch.replay.replay import replay_run_dir, trajectory_figure
from uavsearch.search.metrics import unseen_counts
from uavsearch.testing.clean_env import clean_env

WIDE = MISSIONS_DIR / "wide_team.yaml"


@pytest.fixture(scope="module")
def flown(tmp_path_factory):
    run = tmp_path_factory.mktemp("team") / "run"
    r = subprocess.run([sys.executable, "-m", "uavsearch", "fly", "--mission", str(WIDE), "--vehicles", "3",
                        "--mission-time", "20", "--out", str(run), "--gcs-port", "0"],
                       capture_output=True, text=True, timeout=300, env=clean_env())
    return r, run


def test_three_vehicles_search_one_map_and_all_land(flown):
    r, run = flown
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "vehicle 1: landed; vehicle 2: landed; vehicle 3: landed" in r.stdout
    summary = json.loads((run / "summary.json").read_text())
    assert summary["status"] == "completed" and summary["vehicles"] == 3
    assert all(n >= 1 for n in summary["views_per_vehicle"].values())
    log = read_flight_log(run)
    who = [s.vehicle for s in log.steps]
    assert set(who) == {1, 2, 3} and who[0] == 1  # vehicle 1 takes the start view
    views = [s.lattice_idx for s in log.steps]
    assert len(views) == len(set(views))  # no viewpoint twice: the team never shares one
    # the map it scored is the team's one map after its last view
    assert summary["f1"] == pytest.approx(log.steps[-1].f1, abs=1e-6)
    assert log.header["team"]["system_ids"] == [1, 2, 3]
    for s in log.steps:  # each view's image is the camera of the vehicle that took it
        assert s.image.startswith(f"vehicle{s.vehicle}/") and (run / s.image).is_file()
        assert np.linalg.norm(np.subtract(s.reported_position_enu, s.waypoint_enu)) < 1.5


def test_each_views_line_counts_what_its_scores_count(flown):
    """A view's line says how many cells are found and unseen, and what the unseen count as (the map's value
    there: below 0.5 empty, at 0.5 wrong), agreeing with the map its acc and F1 score (the log's, which the
    summary scores)."""
    r, run = flown
    assert r.returncode == 0
    log = read_flight_log(run)
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("view ") and " F1 " in ln]
    assert len(lines) == len(log.steps)
    seen = np.zeros(len(log.labels), dtype=bool)
    for line, s in zip(lines, log.steps):
        seen |= np.asarray(s.valid, dtype=bool)
        fused = np.asarray(s.fused)
        found = re.search(r"cells found (\d+) \((\d+) of (\d+) true\)(?:, (\d+) unseen \(prior ([\d.]+): count as "
                          r"(\w+)\))?  acc ([\d.]+) F1 ([\d.]+)", line)
        assert found, line
        n_found, n_true, k, unseen, prior, counted, acc, f1 = found.groups()
        assert int(n_found) == (fused > 0.5).sum() and int(n_true) == ((fused > 0.5) & log.labels).sum()
        assert int(unseen or 0) == (~seen).sum() and f"{s.acc:.2f}" == acc and f"{s.f1:.2f}" == f1
        if unseen:  # what the unseen hold (the learned aggregation's low prior, moved by their neighbours)
            n, held, how = unseen_counts(fused, seen)
            assert (int(unseen), prior, counted) == (n, f"{held:.2g}", how)
            assert how == ("empty" if held < 0.5 else "occupied") or np.all(fused[~seen] == 0.5)


def test_replay_draws_every_vehicle(flown, tmp_path):
    r, run = flown
    assert r.returncode == 0
    d = replay_run_dir(run)
    assert set(d.view_sys.tolist()) == {1, 2, 3} and {1, 2, 3} <= set(d.track_sys.tolist())
    assert np.allclose(d.maps[-1], d.logged_maps[-1], atol=1e-5)  # re-fused from the log: the same map
    fig = trajectory_figure(d)
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert [f"vehicle {i}: track and views" for i in (1, 2, 3)] == labels[:3]
    page = write_flight_review(run, tmp_path / "review.html").read_text()  # every track on the review page
    assert '"name":"vehicle 2"' in page and '"name":"vehicle 3"' in page and "a team of 3" in page


def test_team_flags_and_mission_errors_are_one_line(tmp_path):
    r = subprocess.run([sys.executable, "-m", "uavsearch", "fly", "--mission", "default", "--vehicles", "3"],
                       capture_output=True, text=True, timeout=120, env=clean_env())
    assert r.returncode != 0 and "Traceback" not in r.stderr
    assert "a team flies a scene family's mission" in r.stderr
    base = load_mission(WIDE).model_dump(mode="json")
    for change, words in (({"policy": "learned"}, "unknown team planner"), ({"fusion": "learned"}, "fusion"),
                          ({"team": {"vehicles": 0}}, "vehicles"), ({"scene": {"seed": 1, "setting": "nowhere"}},
                                                                    "unknown setting")):
        with pytest.raises(UavsearchError, match=words):
            mission_from_dict({**base, **change}, "x.yaml")
    paper = load_mission()
    with pytest.raises(UavsearchError, match="team"):
        mission_from_dict({**paper.model_dump(mode="json"), "team": {"vehicles": 2}}, "x.yaml")


def test_every_mission_names_its_vehicles_and_one_is_the_default():
    """One controller flies every mission with `mission.vehicles`: 1 by default, also with a `team` block on a paper
    setting; what a paper setting's agent cannot fly is a one-line error naming the field."""
    paper = load_mission().model_dump(mode="json")
    assert load_mission().vehicles == 1 and load_mission(MISSIONS_DIR / "wide.yaml").vehicles == 1
    one = mission_from_dict({**paper, "team": {"vehicles": 1}}, "x.yaml")
    assert one.vehicles == 1 and one.search_config() == load_mission().search_config()
    for team, words in (({"vehicles": 2}, "team.vehicles: the learned policy flies one vehicle"),
                        ({"mission_time_s": 60}, "team.mission_time_s"), ({"max_views": 8}, "team.max_views")):
        with pytest.raises(UavsearchError, match=words):
            mission_from_dict({**paper, "team": team}, "x.yaml")
