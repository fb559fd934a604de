"""QGroundControl `.plan` files: validation with one-line errors, round trips, and a plan flown on the vehicle.

`tests/data/survey.plan` is laid out as QGC 4.x saves a survey: a takeoff, a speed change, a survey
ComplexItem holding the waypoints QGC generated, a return, an inclusion fence circle, an exclusion
polygon and a rally point.
"""

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
from pymavlink import mavutil

from uavsearch.errors import MissionError
from uavsearch.flight.sitl_process import SitlProcess, free_udp_port
from uavsearch.fly.plan_files import flown_search_items, load_plan, mission_items, plan_from_dict, save_plan
from uavsearch.testing.clean_env import clean_env

M = mavutil.mavlink
DATA = Path(__file__).parent / "data"
HOME = {"lat_deg": 47.397742, "lon_deg": 8.545594, "alt_m": 488.0}


def _same(a, b) -> bool:
    fa, fb = a.__dict__, b.__dict__
    return all((isinstance(fa[k], float) and math.isnan(fa[k]) and math.isnan(fb[k])) or fa[k] == fb[k] for k in fa)


def test_a_qgc_survey_plan_reads_as_mission_items():
    plan = load_plan(DATA / "survey.plan")
    items = mission_items(plan, "survey.plan")
    assert [i.command for i in items] == [22, 178, 16, 16, 16, 16, 20]  # the survey's generated waypoints inline
    assert [i.seq for i in items] == list(range(7))
    assert items[2].frame == 3 and items[2].x == round((47.397742 + 10 / 111132.0) * 1e7) and items[2].z == 15
    assert math.isnan(items[0].param4)  # QGC's null is NaN on the wire
    assert plan.home_lla == (47.397742, 8.545594, 488.0)
    assert len(plan.geoFence.circles) == 1 and len(plan.geoFence.polygons) == 1 and len(plan.rallyPoints.points) == 1


def test_plan_round_trip_keeps_every_item(tmp_path):
    wps = [[0.0, 0.0, 70.0], [0.0, 10.0, 70.0], [10.0, 10.0, 70.0]]
    items = flown_search_items(HOME, wps, "rtl")
    path = save_plan(tmp_path / "flown.plan", items, (HOME["lat_deg"], HOME["lon_deg"], HOME["alt_m"]),
                     fence_radius_m=200, rally_points=[(47.3978, 8.5456, 30.0)])
    again = mission_items(load_plan(path))
    assert len(again) == len(items) == 1 + 2 * len(wps) + 1
    assert all(_same(a, b) for a, b in zip(items, again))
    # and a second write is byte-identical
    path2 = save_plan(tmp_path / "again.plan", again, (HOME["lat_deg"], HOME["lon_deg"], HOME["alt_m"]),
                      fence_radius_m=200, rally_points=[(47.3978, 8.5456, 30.0)])
    assert path.read_bytes() == path2.read_bytes()
    doc = json.loads(path.read_text())
    assert doc["fileType"] == "Plan" and doc["version"] == 1 and doc["mission"]["version"] == 2
    assert doc["geoFence"]["version"] == 2 and doc["rallyPoints"]["version"] == 2
    assert all(len(it["params"]) == 7 and it["type"] == "SimpleItem" for it in doc["mission"]["items"])


@pytest.mark.parametrize("mutate, expect", [
    (lambda d: d.update(fileType="Mission"), "fileType"),
    (lambda d: d.update(version=2), "version"),
    (lambda d: d["mission"]["items"][0]["params"].pop(), "mission.items.0"),
    (lambda d: d["mission"].update(items=[]), "mission.items"),
    (lambda d: d["mission"].pop("plannedHomePosition"), "mission.plannedHomePosition"),
    (lambda d: d["geoFence"]["circles"][0]["circle"].update(radius=-5), "radius"),
])
def test_a_bad_plan_is_one_line(mutate, expect):
    doc = json.loads((DATA / "survey.plan").read_text())
    mutate(doc)
    with pytest.raises(MissionError) as e:
        plan_from_dict(doc, "x.plan")
    msg = str(e.value)
    assert msg.startswith("plan x.plan: ") and expect in msg and "\n" not in msg


def test_unflyable_commands_and_broken_files_are_one_line(tmp_path):
    doc = json.loads((DATA / "survey.plan").read_text())
    doc["mission"]["items"][1]["command"] = 206  # DO_SET_CAM_TRIGG_DIST: not flown by this vehicle
    with pytest.raises(MissionError, match=r"cannot fly MAV_CMD \[206\]"):
        mission_items(plan_from_dict(doc, "x.plan"), "x.plan")
    bad = tmp_path / "bad.plan"
    bad.write_text("{not json")
    with pytest.raises(MissionError, match="not JSON"):
        load_plan(bad)
    r = subprocess.run([sys.executable, "-m", "uavsearch", "mission", "upload", str(bad)], capture_output=True,
                       text=True, timeout=60, env=clean_env())
    assert r.returncode == 2 and r.stderr.startswith("uavsearch: error: plan ") and "Traceback" not in r.stderr


def test_a_qgc_plan_flies_and_downloads_as_uploaded(tmp_path):
    """`uavsearch mission upload survey.plan --start` on a running vehicle: every item is reached, it
    returns and lands; the mission downloaded afterwards is the file's items."""
    sitl = SitlProcess(tmp_path / "v", gcs_port=free_udp_port(), speed="max", camera=False, env=clean_env())
    try:
        r = subprocess.run([sys.executable, "-m", "uavsearch", "mission", "upload", str(DATA / "survey.plan"),
                            "--connect", f"udpin:127.0.0.1:{sitl.gcs_port}", "--start", "--timeout", "150"],
                           capture_output=True, text=True, timeout=200, env=clean_env())
        assert r.returncode == 0, r.stdout + r.stderr
        assert "uploaded 7 mission item(s)" in r.stdout
        assert "GF_MAX_HOR_DIST = 300 m" in r.stdout and "1 polygon / exclusion shape(s) skipped" in r.stdout
        assert "rally points: 1 skipped" in r.stdout
        assert "mission landed and disarmed" in r.stdout, r.stdout
        for seq in (2, 3, 4, 5):
            assert f"reached item {seq}" in r.stdout
        # download with a plain pymavlink ground station
        c = mavutil.mavlink_connection(f"udpin:127.0.0.1:{sitl.gcs_port}", source_system=255, dialect="common")
        try:
            c.wait_heartbeat(timeout=10)
            c.mav.mission_request_list_send(1, 1, M.MAV_MISSION_TYPE_MISSION)
            cnt = c.recv_match(type="MISSION_COUNT", blocking=True, timeout=5)
            assert cnt is not None and cnt.count == 7
            got = []
            for seq in range(cnt.count):
                c.mav.mission_request_int_send(1, 1, seq, M.MAV_MISSION_TYPE_MISSION)
                m = c.recv_match(type="MISSION_ITEM_INT", blocking=True, timeout=5)
                got.append(m)
            c.mav.mission_ack_send(1, 1, M.MAV_MISSION_ACCEPTED, M.MAV_MISSION_TYPE_MISSION)
        finally:
            c.close()
        want = mission_items(load_plan(DATA / "survey.plan"))
        assert [(m.command, m.frame, m.x, m.y) for m in got] == [(w.command, w.frame, w.x, w.y) for w in want]
        assert [m.z for m in got] == pytest.approx([w.z for w in want])
    finally:
        sitl.stop()


def _wpl_text(home_alt_amsl: float = 488.0) -> str:
    """A MAVProxy / QGC waypoint file: home (item 0, frame 0, AMSL), take-off, one waypoint, land."""
    lat, lon = 47.397742, 8.545594
    rows = [(0, 1, 0, 16, lat, lon, home_alt_amsl), (1, 0, 3, 22, lat, lon, 10.0),
            (2, 0, 3, 16, lat + 1e-4, lon, 10.0), (3, 0, 3, 21, lat + 1e-4, lon, 0.0)]
    return "QGC WPL 110\n" + "".join(f"{i}\t{cur}\t{frame}\t{cmd}\t0\t0\t0\t0\t{a:.7f}\t{o:.7f}\t{z}\t1\n"
                                     for i, cur, frame, cmd, a, o, z in rows)


def test_a_waypoint_file_s_item_0_is_home_not_a_mission_item(tmp_path):
    path = tmp_path / "m.waypoints"
    path.write_text(_wpl_text())
    plan = load_plan(path)
    items = mission_items(plan, str(path))
    assert [it.command for it in items] == [22, 16, 21] and [it.seq for it in items] == [0, 1, 2]
    assert plan.mission.plannedHomePosition == pytest.approx([47.397742, 8.545594, 488.0])
    bad = tmp_path / "short.waypoints"
    bad.write_text("QGC WPL 110\n0\t1\t0\t16\t0\t0\t0\t0\t47.3\t8.5\n")
    with pytest.raises(MissionError, match="line 2: 10 fields"):
        load_plan(bad)


def test_a_waypoint_file_uploads_without_its_home_item(tmp_path):
    """`mission upload FILE.waypoints`: the vehicle gets take-off first (the home row is not flown)."""
    from uavsearch.fly.connection import MavlinkConnection

    path = tmp_path / "m.waypoints"
    path.write_text(_wpl_text())
    sitl = SitlProcess(tmp_path / "v", gcs_port=free_udp_port(), speed="max", camera=False, env=clean_env())
    try:
        r = subprocess.run([sys.executable, "-m", "uavsearch", "mission", "upload", str(path),
                            "--connect", f"udpin:127.0.0.1:{sitl.gcs_port}"], capture_output=True, text=True,
                           timeout=120, env=clean_env())
        assert r.returncode == 0, r.stdout + r.stderr
        assert "uploaded 3 mission item(s)" in r.stdout
        with MavlinkConnection(f"udpin:127.0.0.1:{sitl.gcs_port}", source_system=250) as conn:
            vehicle = conn.first_autopilot(10)
            assert [it.command for it in vehicle.mission.download()] == [22, 16, 21]
    finally:
        sitl.stop()
