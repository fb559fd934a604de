"""Hostile MAVLink cannot stall or silence the vehicle; signing without lock-out; no silently wrong results.

Real `uavsearch sitl` processes on loopback UDP, real pymavlink clients, bounded in time. The fuzz run is
CI-sized (tools/fuzz_mavlink.py runs the full one and prints the table).
"""

import json
import math
import signal
import struct
import subprocess
import sys
import time

import numpy as np
import pytest
from pymavlink import mavutil

from uavsearch.testing.mavlink_client import Client
from uavsearch.flight.mavlink.params import decode_param
from uavsearch.flight.sitl_process import SitlProcess
from uavsearch.research import fuzz_mavlink
from uavsearch.testing.clean_env import clean_env

M = mavutil.mavlink
NAN, INF = math.nan, math.inf
CAMERA = 100
DENIED_OR_WORSE = (M.MAV_RESULT_DENIED, M.MAV_RESULT_UNSUPPORTED, M.MAV_RESULT_FAILED, M.MAV_RESULT_TEMPORARILY_REJECTED)


def _acks(c: Client, command: int, seconds: float) -> list:
    """Every COMMAND_ACK for `command` within `seconds` (to check there is exactly one)."""
    out, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        m = c.recv("COMMAND_ACK", 0.1)
        if m is not None and m.command == command:
            out.append(m)
    return out


def _send(c: Client, command: int, *params, comp: int = 1) -> None:
    p = list(params) + [0.0] * (7 - len(params))
    c.mav.command_long_send(1, comp, command, 0, *p)


def _heartbeat_gap(c: Client, seconds: float) -> float:
    """The largest wall gap between autopilot heartbeats over `seconds` (from now)."""
    last, gap, end = time.monotonic(), 0.0, time.monotonic() + seconds
    while time.monotonic() < end:
        hb = c.wait_heartbeat(timeout=max(0.05, end - time.monotonic()))
        now = time.monotonic()
        if hb is None:
            break
        gap, last = max(gap, now - last), now
    return max(gap, time.monotonic() - last)


# ------------------------------------------------------------------------------------------------ camera


def _sitl_at_speed_1(tmp_path_factory, name: str, camera: bool):
    """A module's vehicle at --speed 1; yields it, then returns its log after checking it exited cleanly."""
    p = SitlProcess(tmp_path_factory.mktemp(name), speed="1", camera=camera, env=clean_env())
    yield p
    code, out = p.stop()
    assert code == 0, out
    return out


@pytest.fixture(scope="module")
def camera_sitl(tmp_path_factory):
    out = yield from _sitl_at_speed_1(tmp_path_factory, "cam", camera=True)
    assert "Traceback" not in out


BAD_CAPTURES = [(1e-7, 1e9), (NAN, 5), (INF, 5), (1e-9, 0), (0.0, 1e9), (0.5, 1e9), (0.5, NAN), (0.5, 2.5), (-1.0, 3)]


def test_capture_values_it_cannot_honour_are_denied_once(camera_sitl):
    """Each (interval, count) gets exactly one DENIED; afterwards the vehicle still heartbeats and answers."""
    c = Client(camera_sitl.api_port)
    try:
        for interval, count in BAD_CAPTURES:
            _send(c, M.MAV_CMD_IMAGE_START_CAPTURE, 0, interval, count, comp=CAMERA)
            acks = _acks(c, M.MAV_CMD_IMAGE_START_CAPTURE, 1.5)
            assert [a.result for a in acks] == [M.MAV_RESULT_DENIED], (interval, count)
        assert _heartbeat_gap(c, 2.5) <= 1.5  # still heartbeating at --speed 1
        assert c.command(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION).result == M.MAV_RESULT_ACCEPTED
    finally:
        c.close()


def test_interval_capture_renders_while_the_vehicle_keeps_answering(camera_sitl):
    c = Client(camera_sitl.api_port)
    try:
        ack = c.command(M.MAV_CMD_IMAGE_START_CAPTURE, 0, 0.2, 0, target_component=CAMERA)  # until stopped
        assert ack.result == M.MAV_RESULT_ACCEPTED
        t0, shots = time.monotonic(), []
        gap = _heartbeat_gap(c, 3.0)
        for _ in range(50):
            m = c.recv("CAMERA_IMAGE_CAPTURED", timeout=0.5)
            if m is not None:
                shots.append(m)
        assert c.command(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION).result == M.MAV_RESULT_ACCEPTED
        assert c.command(M.MAV_CMD_IMAGE_STOP_CAPTURE, target_component=CAMERA).result == M.MAV_RESULT_ACCEPTED
        assert gap <= 1.5 and time.monotonic() - t0 < 60
        assert len(shots) >= 3 and all(s.capture_result == 1 for s in shots[:3])
    finally:
        c.close()


# ------------------------------------------------------------------------------------------------ protocol


@pytest.fixture(scope="module")
def sitl(tmp_path_factory):
    yield from _sitl_at_speed_1(tmp_path_factory, "proto", camera=False)


@pytest.fixture
def gcs(sitl):
    c = Client(sitl.gcs_port)
    yield c
    c.close()


@pytest.mark.parametrize("mid, interval", [(0.5, -1.0), (0.0, -1.0), (0.99, 1e6), (1e-9, -1.0), (-0.5, -1.0),
                                           (NAN, -1.0), (0.0, 5e6)])
def test_heartbeat_cannot_be_silenced(gcs, mid, interval):
    _send(gcs, M.MAV_CMD_SET_MESSAGE_INTERVAL, mid, interval)
    acks = _acks(gcs, M.MAV_CMD_SET_MESSAGE_INTERVAL, 1.0)
    assert len(acks) == 1 and acks[0].result in DENIED_OR_WORSE
    assert _heartbeat_gap(gcs, 2.5) <= 1.5


@pytest.mark.parametrize("mid", [65536.0, 2.0**31, 1e20, 0.5, -1.0, NAN, INF])
def test_get_message_interval_of_bad_ids_gets_exactly_one_ack(gcs, mid):
    _send(gcs, M.MAV_CMD_GET_MESSAGE_INTERVAL, mid)
    acks = _acks(gcs, M.MAV_CMD_GET_MESSAGE_INTERVAL, 1.0)
    assert len(acks) == 1 and acks[0].result in DENIED_OR_WORSE


@pytest.mark.parametrize("as_int, x, z", [(False, NAN, 10.0), (False, INF, 10.0), (False, 47.4, NAN), (False, 47.4, -INF),
                                           (True, 47.4, NAN), (True, 47.4, -INF)])  # MISSION_ITEM_INT's x is an int
def test_mission_item_with_non_finite_values_gets_a_mission_ack(gcs, as_int, x, z):
    gcs.mav.mission_count_send(1, 1, 1, 0)
    req = gcs.recv(["MISSION_REQUEST_INT", "MISSION_REQUEST"], timeout=3)
    assert req is not None and req.seq == 0
    if as_int:
        gcs.mav.mission_item_int_send(1, 1, 0, M.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, M.MAV_CMD_NAV_WAYPOINT, 0, 1,
                                      0, 0, 0, NAN, int(47.3978 * 1e7), int(8.5456 * 1e7), z, 0)
    else:
        gcs.mav.mission_item_send(1, 1, 0, M.MAV_FRAME_GLOBAL_RELATIVE_ALT, M.MAV_CMD_NAV_WAYPOINT, 0, 1,
                                  0, 0, 0, NAN, x, 8.5456, z, 0)
    ack = gcs.recv("MISSION_ACK", timeout=2)
    assert ack is not None and ack.type != M.MAV_MISSION_ACCEPTED


def test_commands_with_hostile_params_get_exactly_one_ack(gcs):
    """Every COMMAND_LONG / COMMAND_INT to an existing component: exactly one COMMAND_ACK, whatever is in it."""
    gen = fuzz_mavlink.Packets(11, categories=("hostile_command",))
    sent: dict = {}
    for _ in range(150):
        _, data, acks = gen.next()
        gcs.send_raw(data)
        for k, n in acks.items():
            sent[k] = sent.get(k, 0) + n
        time.sleep(0.01)
    got: dict = {}
    end = time.monotonic() + 3.0
    while time.monotonic() < end:
        m = gcs.recv("COMMAND_ACK", 0.1)
        if m is not None:
            got[m.command] = got.get(m.command, 0) + 1
    assert got == sent
    gcs.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 0)  # back to defaults, for the other tests
    assert gcs.wait_heartbeat(3) is not None


def _param(m) -> float:
    """A PARAM_VALUE's value, int32 parameters decoded PX4's bytewise way."""
    return decode_param(m.param_value, m.param_type, is_int=True)


def test_params_take_px4_bounds_over_mavlink(gcs):
    """A set outside the bounds (or NaN, or of a read-only parameter) is answered with the value kept."""
    for name, bad in (("MC_ROLLRATE_P", 0.0), ("MC_PITCHRATE_P", 0.0), ("MPC_XY_VEL_P_ACC", 0.5),
                      ("MC_ROLLRATE_P", NAN), ("SIM_SCENE_SEED", 4.0)):
        gcs.mav.param_request_read_send(1, 1, name.encode(), -1)
        before = gcs.recv("PARAM_VALUE", cond=lambda m, n=name: m.param_id == n)
        assert before is not None, name
        gcs.mav.param_set_send(1, 1, name.encode(), bad, M.MAV_PARAM_TYPE_REAL32)
        m = gcs.recv("PARAM_VALUE", cond=lambda m, n=name: m.param_id == n)
        assert m is not None and m.param_type == before.param_type, name
        assert math.isfinite(_param(m)) and _param(m) == _param(before), (name, bad, _param(m))


# ------------------------------------------------------------------------------------------------ signing


def test_signing_accepts_nothing_forged_and_never_locks_out():
    r = fuzz_mavlink.signing_check(count=40, replays=20, speed="max")
    for link in ("api", "gcs"):
        s = r[link]
        assert s["legit_before"] == 20 and s["legit_after_forgery"] == 20, (link, s)  # no lock-out
        assert s["wrong_key"] == 0 and s["wrong_key_after_junk_or_unsigned"] == 0, (link, s)
        assert s["replay_original"] == 1 and s["replayed"] == 0 and s["forged_timestamp"] == 0, (link, s)
    assert r["gcs"]["unsigned"] == 0
    assert r["api"]["unsigned"] == 40  # by design: MAVSDK cannot sign (README; --sign-api-strict refuses them)


# ------------------------------------------------------------------------------------------------ fuzz


@pytest.mark.slow  # 37 s: `make test-all` runs it; tools/fuzz_mavlink.py is the full fuzzer
def test_fuzz_mid_flight_leaves_it_flying_answering_and_landing():
    r = fuzz_mavlink.fuzz_flight(seed=5, packets=2000, speed="1", rate_hz=250.0)
    assert r.alive and r.answers and r.landed, r
    assert r.max_hb_gap_api_s <= 1.5 and r.max_hb_gap_gcs_s <= 1.5, r
    assert r.commands_unanswered == 0, r
    assert r.max_deviation_m < 1.5, r
    assert not r.notes, r.notes
    assert sum(r.per_category.values()) == 2000 and min(r.per_category.values()) > 100


# ------------------------------------------------------------------------------------------------ missions, CLI


def _uavsearch(*args, timeout=240):
    return subprocess.run([sys.executable, "-m", "uavsearch", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, env=clean_env())


def _one_line_error(r, *words):
    assert r.returncode == 2, (r.stdout, r.stderr)
    lines = [ln for ln in r.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in r.stderr, r.stderr
    for w in words:
        assert w in lines[0], lines[0]


def test_unwritable_out_is_one_line(tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("x")
    _one_line_error(_uavsearch("fly", "--out", afile / "run"), "cannot write")
    _one_line_error(_uavsearch("fly", "--out", afile), "a folder is needed")
    _one_line_error(_uavsearch("replay", tmp_path, "--out", afile / "x"), "cannot write", "is a file")
    _one_line_error(_uavsearch("replay", tmp_path, "--html", afile / "x.html"), "cannot write")
    _one_line_error(_uavsearch("eval", "search", "--setting", "2", "--out", afile / "x"), "cannot write")
    _one_line_error(_uavsearch("sitl", "--out", afile / "x", "--duration", "1"), "cannot write")


def test_mission_outside_what_the_models_were_trained_for_is_refused(tmp_path):
    from uavsearch.fly.missions import TRAINED_FOR, load_mission
    from uavsearch.search.config import SearchConfig

    assert TRAINED_FOR == {"altitude_m": SearchConfig().altitude_m, "step_m": SearchConfig().step_m}
    path = tmp_path / "low.yaml"
    path.write_text("search: {altitude_m: 40}\n")
    _one_line_error(_uavsearch("fly", "--mission", path, "--out", tmp_path / "run"), "altitude_m 40", "allow_untrained")
    path.write_text("search: {altitude_m: 40, allow_untrained: true}\n")
    assert load_mission(path).search.altitude_m == 40
    path.write_text("search: {step_m: 5}\n")
    with pytest.raises(Exception, match="step_m 5"):
        load_mission(path)


def test_fly_connect_refuses_a_vehicle_simulating_another_scene(tmp_path):
    sitl = SitlProcess(tmp_path / "vehicle", "--scene", "5", "--cells", "5", lockstep=True, env=clean_env())
    try:
        r = _uavsearch("fly", "--mission", "default", "--connect", f"udpin:127.0.0.1:{sitl.api_port}", "--out",
                        tmp_path / "run")
        _one_line_error(r, "simulates scene 5", "scene 3")
    finally:
        sitl.stop()
    c = None
    sitl = SitlProcess(tmp_path / "vehicle2", "--scene", "3", "--cells", "5", env=clean_env())
    try:  # what the vehicle reports, over plain PARAM_REQUEST_READ
        c = Client(sitl.gcs_port)
        values = {}
        for name in ("SIM_SCENE_SEED", "SIM_SCENE_CELLS"):
            c.mav.param_request_read_send(1, 1, name.encode(), -1)
            m = c.recv("PARAM_VALUE", cond=lambda m, n=name: m.param_id == n)
            values[name] = struct.unpack("<i", struct.pack("<f", m.param_value))[0]
        assert values == {"SIM_SCENE_SEED": 3, "SIM_SCENE_CELLS": 5}
    finally:
        if c is not None:
            c.close()
        sitl.stop()


@pytest.mark.slow  # 28 s of a real-time landing: `make test-all` runs it
def test_second_ctrl_c_says_what_became_of_the_end_action(tmp_path):
    proc = subprocess.Popen([sys.executable, "-m", "uavsearch", "fly", "--mission", "default", "--speed", "1", "--out",
                             str(tmp_path / "run"),
                             "--gcs-port", "0"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=clean_env())
    out = []
    try:
        end = time.monotonic() + 180
        while time.monotonic() < end:
            line = proc.stdout.readline()
            out.append(line)
            if not line or "step 1/" in line:
                break
        proc.send_signal(signal.SIGINT)
        while time.monotonic() < end:
            line = proc.stdout.readline()
            out.append(line)
            if not line or "interrupted" in line or "landing" in line.lower():
                break
        time.sleep(1.0)
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=60)
        out.append(rest)
    finally:
        if proc.poll() is None:
            proc.kill()
    text = "".join(out)
    assert "end action failed: \n" not in text and "Traceback" not in text, text
    assert "end action abandoned: Ctrl-C again during the land" in text, text


# ------------------------------------------------------------------------------------------------ logs


@pytest.fixture(scope="module")
def flown(tmp_path_factory):
    out = tmp_path_factory.mktemp("fly") / "run"
    r = _uavsearch("fly", "--mission", "default", "--out", out, "--gcs-port", "0", "--speed", "max", timeout=400)
    assert r.returncode == 0, r.stdout + r.stderr
    return out


def test_tlog_stamps_follow_simulated_time(flown):
    mlog = mavutil.mavlink_connection(str(flown / "telemetry.tlog"), dialect="common")
    pairs, armed_stamps = [], []
    while True:
        m = mlog.recv_match(blocking=False)
        if m is None:
            break
        if m.get_type() == "GLOBAL_POSITION_INT" and m.get_srcSystem() == 1:
            pairs.append((m._timestamp, m.time_boot_ms * 1e-3))
        if m.get_type() == "HEARTBEAT" and m.get_srcSystem() == 1 and m.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED:
            armed_stamps.append(m._timestamp)
    stamps, sim = np.array(pairs).T
    assert np.all(np.diff(stamps) >= 0)
    np.testing.assert_allclose(stamps - stamps[0], sim - sim[0], atol=0.05)  # the tlog clock is the vehicle's
    summary = json.loads((flown / "summary.json").read_text())
    assert armed_stamps[-1] - armed_stamps[0] > 0.5 * summary["sim_time_s"]  # in the air for what was flown


@pytest.mark.slow  # renders every view again from the tlog (about 30 s): `make test-all` runs it
def test_replay_from_tlog_agrees_with_the_run_directory(flown, tmp_path):
    r1 = _uavsearch("replay", flown, "--out", tmp_path / "dir", timeout=300)
    r2 = _uavsearch("replay", flown / "telemetry.tlog", "--out", tmp_path / "tlog", "--scene", "3", "--setting", "2",
                    timeout=300)
    assert r1.returncode == 0 and r2.returncode == 0, r1.stderr + r2.stderr
    s1 = json.loads((tmp_path / "dir" / "replay.json").read_text())
    s2 = json.loads((tmp_path / "tlog" / "replay.json").read_text())
    np.testing.assert_allclose(s1["positions_enu"], s2["positions_enu"], atol=1e-3)  # the same views
    assert s1["f1"] == pytest.approx(s2["f1"], abs=1e-4) and s1["acc"] == pytest.approx(s2["acc"], abs=1e-4)
    np.testing.assert_allclose(s1["final_map"], s2["final_map"], atol=1e-3)
