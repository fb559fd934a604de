"""Flight log files: tlog records both directions over real UDP and reads back with pymavlink; search.jsonl
survives a torn last line (a flight killed mid-write) with a warning."""

import json
import time

import numpy as np
import pytest
from pymavlink import mavutil

from uavsearch.errors import LogError
from uavsearch.flight.sitl_process import free_udp_port
from uavsearch.logs.flight_log import FlightLogWriter, read_flight_log
from uavsearch.logs.step_record import StepRecord
from uavsearch.replay.replay import read_tlog
from uavsearch.logs.tlog import TlogWriter

M = mavutil.mavlink


@pytest.fixture
def recorded_tlog(tmp_path, monkeypatch):
    """A pymavlink 'vehicle' and a recorded pymavlink client exchanging real UDP packets (MAVLink 2)."""
    monkeypatch.setenv("MAVLINK20", "1")
    port = free_udp_port()
    path = tmp_path / "telemetry.tlog"
    tlog = TlogWriter(path)
    client = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=245, source_component=190,
                                        dialect="common")
    tlog.attach(client)
    vehicle = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1,
                                         dialect="common")
    for i in range(5):
        vehicle.mav.global_position_int_send(1000 * i, 473977420 + i, 85455940, 558000, 70000, 0, 0, 0, 0)
    vehicle.mav.camera_image_captured_send(4000, 0, 0, 473977420, 85455940, 558000, 70000, [1, 0, 0, 0], 0, 1,
                                           b"file:///tmp/img_0000.png")
    got = []
    end = time.monotonic() + 5
    while len(got) < 6 and time.monotonic() < end:
        m = client.recv_match(blocking=True, timeout=0.2)
        if m is not None:
            got.append(m)
    client.mav.command_long_send(1, 100, M.MAV_CMD_IMAGE_START_CAPTURE, 0, 0, 0, 1, 1, 0, 0, 0)
    assert vehicle.recv_match(type="COMMAND_LONG", blocking=True, timeout=5) is not None
    tlog.close()
    client.close()
    vehicle.close()
    return path


def test_tlog_records_both_directions_and_pymavlink_reads_it(recorded_tlog):
    log = mavutil.mavlink_connection(str(recorded_tlog), dialect="common")
    types = []
    while True:
        m = log.recv_match()
        if m is None:
            break
        types.append((m.get_type(), m.get_srcSystem()))
        assert abs(m._timestamp - time.time()) < 600  # tlog timestamps are UNIX time
    assert types.count(("GLOBAL_POSITION_INT", 1)) == 5
    assert ("CAMERA_IMAGE_CAPTURED", 1) in types
    assert ("COMMAND_LONG", 245) in types  # what the client sent is in the log too


def test_read_tlog_stops_at_truncation_and_corruption(recorded_tlog, tmp_path):
    full = read_tlog(recorded_tlog)
    assert full.warning is None and full.messages == 7
    assert len(full.lla) == 5 and len(full.captures) == 1
    data = recorded_tlog.read_bytes()
    cut = tmp_path / "cut.tlog"
    cut.write_bytes(data[: len(data) - 5])
    part = read_tlog(cut)
    assert part.messages == 6 and "truncated" in part.warning and "\n" not in part.warning
    bad = bytearray(data)
    # the third record starts after two GLOBAL_POSITION_INT records: 8 + 10 + 28 + 2 bytes each (MAVLink 2)
    rec = 8 + 10 + M.MAVLink_global_position_int_message.unpacker.size + 2
    bad[2 * rec + 8] = 0x00  # destroy its start byte
    broken = tmp_path / "broken.tlog"
    broken.write_bytes(bytes(bad))
    part = read_tlog(broken)
    assert part.messages == 2 and "corrupt" in part.warning and len(part.lla) == 2
    garbage = tmp_path / "garbage.tlog"
    garbage.write_bytes(b"\x00" * 100)
    with pytest.raises(LogError):
        read_tlog(garbage)


def _step(t, **kw):
    base = dict(t=t, waypoint_enu=[0.0, 0.0, 70.0], reported_position_enu=[0.1, 0.0, 70.0], reported_rpy_rad=[0.0] * 3,
                image=f"images/img_{t:04d}.png", p_occ=np.full(100, 0.1), valid=np.ones(100, bool),
                cell_area_px=np.full(100, 190.0), fused=np.full(100, 0.2), reward=0.0)
    return StepRecord(**{**base, **kw})


def test_flight_log_round_trip_and_torn_last_line(tmp_path):
    w = FlightLogWriter(tmp_path, tlog=False)
    labels = np.zeros(100, dtype=int)
    labels[[3, 50]] = 1
    w.header(labels=labels, fusion="bayes", grid={"n": 10, "cell_m": 5.0}, mission={})
    for t in range(3):
        w.step(_step(t, p_occ=np.full(100, 0.1 * t), sim_time_s=float("nan")))
    w.close()
    log = read_flight_log(tmp_path)
    assert [s.t for s in log.steps] == [0, 1, 2] and log.warning is None
    assert log.labels.sum() == 2 and log.array("p_occ").shape == (3, 100)
    assert log.steps[0].sim_time_s is None  # NaN is written as null: the file stays strict JSON
    with open(tmp_path / "search.jsonl", "a") as f:
        f.write('{"type": "step", "t": 3, "p_oc')  # killed while writing
    with pytest.warns(UserWarning, match="damaged at line 5"):
        log = read_flight_log(tmp_path)
    assert len(log.steps) == 3


def test_a_header_known_later_comes_first_and_once(tmp_path):
    """header_later: a flight arms while its models load; whatever is written first (the header itself, a
    failure, a step or the summary), the header leads the log, and only once."""
    asked = []

    def fields():
        asked.append(1)
        return dict(labels=np.zeros(100, dtype=int), grid={"n": 10, "cell_m": 5.0}, mission={"name": "m"})

    for first in ("failure", "step", "summary", "header"):
        run = tmp_path / first
        w = FlightLogWriter(run, tlog=False)
        w.header_later(fields)
        if first == "failure":
            w.failure(step=None, error="arming refused")
        elif first == "step":
            w.step(_step(0))
        elif first == "summary":
            w.summary({"status": "failed: arming refused"})
        w.write_header()
        w.step(_step(1))
        w.close()
        lines = [json.loads(ln) for ln in (run / "search.jsonl").read_text().splitlines()]
        assert lines[0]["type"] == "header" and [ln["type"] for ln in lines].count("header") == 1, first
        assert read_flight_log(run).header["mission"] == {"name": "m"}
    assert len(asked) == 4


def test_not_a_flight_log(tmp_path):
    with pytest.raises(LogError, match="no search.jsonl"):
        read_flight_log(tmp_path)
    (tmp_path / "search.jsonl").write_text(json.dumps({"type": "step"}) + "\n")
    with pytest.raises(LogError, match="no header"):
        read_flight_log(tmp_path)


def test_step_record_reads_and_writes_a_flown_line_byte_for_byte():
    """The typed record keeps search.jsonl's format exactly: key order, 6-decimal floats, ints as ints, nulls."""
    line = ('{"type":"step","t":4,"sim_time_s":49.5,"wall_s":0.12059,"flight_time_s":6.0,"lattice_idx":4,'
            '"waypoint_enu":[20.0,20.0,70.0],"reported_position_enu":[20.102919,20.31233,70.036],'
            '"reported_rpy_rad":[0.046742,-0.024023,0.000543],"true_pose":{"position_enu":[19.827568,19.969327,'
            '70.107888],"rpy_rad":[0.044812,-0.023704,-0.002379]},"image_index":4,"image":"images/img_0004.png",'
            '"p_occ":[0.196198,0.013106],"scores":[0.282766,-7.680727],"valid":[true,false],'
            '"cell_area_px":[191.912262,191.912262],"fused":[0.360248,null],"action":null,"action_name":null,'
            '"revisit":false,"reward":-1.0,"acc":0.94,"f1":0.4}')
    rec = StepRecord.from_json(line)
    assert rec.to_json() == line
    assert rec.true_pose.position_enu == [19.827568, 19.969327, 70.107888] and rec.valid.dtype == bool
    assert np.isnan(rec.fused[1]) and rec.action is None and rec.reward == -1.0
    fresh = _step(0, sim_time_s=25.7, reward=0.0, acc=np.float64(0.94))
    assert StepRecord.from_json(fresh.to_json()).to_json() == fresh.to_json()


@pytest.mark.parametrize("bad, why", [
    ({"t": 0}, "lacks sim_time_s"),
    ({"p_occ": "x"}, "field p_occ: 'x' is not a list"),
    ({"t": 1.5}, "field t: 1.5 is not an integer"),
    ({"valid": [1, 0]}, "field valid: 1 is not true/false"),
])
def test_a_malformed_step_line_is_a_one_line_log_error(tmp_path, bad, why):
    good = json.loads(_step(0).to_json())
    rec = bad if "t" in bad and len(bad) == 1 and bad["t"] == 0 else {**good, **bad}
    rec = {"type": "step", **rec}
    with pytest.raises(LogError, match=why) as e:
        StepRecord.from_json(json.dumps(rec))
    assert "\n" not in str(e.value)
    w = FlightLogWriter(tmp_path, tlog=False)
    w.header(labels=[0] * 100, grid={"n": 10, "cell_m": 5.0}, mission={})
    w.close()
    with open(tmp_path / "search.jsonl", "a") as f:
        f.write(json.dumps(rec) + "\n")
    with pytest.raises(LogError, match=f"search.jsonl: line 2: .*{why}"):
        read_flight_log(tmp_path)


def test_the_summary_is_provisional_from_the_header_and_survives_a_full_disk(tmp_path):
    """summary.json says "running" and what is kept from the header on; a rewrite that hits a full disk (its
    temporary file is /dev/full, whose every write fails with ENOSPC) keeps the last good one; the final one
    gets the reserve's room and says what a flight that did not complete kept."""
    import os

    from uavsearch.logs.flight_log import RESERVE

    w = FlightLogWriter(tmp_path, tlog=False)
    (tmp_path / "images" / "img_0000.png").write_bytes(b"\x89PNG")
    w.header(labels=np.zeros(100, dtype=int), fusion="bayes", grid={"n": 10, "cell_m": 5.0},
             mission={"name": "m"}, scene={"seed": 3})
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s == {"status": "running", "mission": "m", "scene_seed": 3, "kept": {"views": 0, "photos": 1, "tlog_bytes": 0}}
    assert (tmp_path / RESERVE).stat().st_size >= 100 * 40
    w.step(_step(0))
    assert json.loads((tmp_path / "summary.json").read_text())["kept"]["views"] == 1
    tmp = tmp_path / ".summary.json.tmp"
    os.symlink("/dev/full", tmp)  # the disk is full from here on
    w.step(_step(1))  # the flight goes on; its provisional summary cannot be rewritten
    assert json.loads((tmp_path / "summary.json").read_text())["kept"]["views"] == 1  # the last good one
    os.symlink("/dev/full", tmp)
    w.summary({"status": "failed: no space left on device", "steps": 2})  # the reserve makes room for it
    w.close()
    s = json.loads((tmp_path / "summary.json").read_text())
    assert s["status"].startswith("failed") and s["kept"] == {"views": 2, "photos": 1, "tlog_bytes": 0}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["images", "search.jsonl", "summary.json"]
    assert read_flight_log(tmp_path).summary == s


def test_a_completed_flight_s_summary_is_as_given(tmp_path):
    w = FlightLogWriter(tmp_path, tlog=False)
    w.header(labels=np.zeros(100, dtype=int), fusion="bayes", grid={"n": 10, "cell_m": 5.0}, mission={})
    w.step(_step(0))
    w.summary({"status": "completed", "steps": 1})
    w.step(_step(1))  # nothing replaces the final summary
    w.close()
    assert json.loads((tmp_path / "summary.json").read_text()) == {"status": "completed", "steps": 1}
