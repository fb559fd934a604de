"""flight.ulg, the vehicle's PX4 ULog, read back by pyulog (the oracle): every topic Flight Review and PlotJuggler
plot, with PX4's names and types; positions and attitudes that match the vehicle's truth and its MAVLink telemetry;
parameters, their changes and the status texts; a file cut anywhere still reads; one log per vehicle of a team."""

import math
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from pymavlink import mavutil
from pyulog import ULog

from uavsearch.flight.commander import VehicleCommand
from uavsearch.flight.logger import ULOG_NAME
from uavsearch.flight.quaternion import quat_to_euler
from uavsearch.flight.sitl import Sitl, SitlConfig
from uavsearch.flight.sitl_process import SitlProcess
from uavsearch.flight.ulog import MessageDef
from uavsearch.logs.tlog import TlogWriter
from uavsearch.testing.clean_env import clean_env

M = mavutil.mavlink
TOPICS = ("vehicle_local_position", "vehicle_global_position", "vehicle_attitude", "vehicle_status",
          "actuator_outputs", "actuator_motors", "battery_status", "sensor_combined", "vehicle_gps_position",
          "position_setpoint_triplet", "vehicle_land_detected")
NAV_STATE_AUTO_LOITER, NAV_STATE_AUTO_TAKEOFF = 4, 17


@pytest.fixture(scope="module")
def flown(tmp_path_factory):
    """Take off, fly a 7 m leg, change a parameter; the truth and the estimate sampled every 0.25 s."""
    run = tmp_path_factory.mktemp("ulog")
    cfg = SitlConfig(seed=5, scene_seed=None, speed=math.inf, api_port=0, gcs_port=0, run_dir=run,
                     params={"MIS_TAKEOFF_ALT": 5.0})
    sitl = Sitl(cfg)
    samples = []
    try:
        sitl.run(2.0)
        c = sitl.commander
        assert c.handle_command(VehicleCommand(400, 1.0)) == 0
        assert c.handle_command(VehicleCommand(22)) == 0
        for i in range(48):
            if i == 20:
                lla = cfg.home.enu_to_geodetic([3.0, 6.0, 0.0])
                assert c.handle_command(VehicleCommand(192, -1, 1, 0, math.nan, lla[0], lla[1],
                                                       cfg.home.alt_m + 6.0)) == 0
            if i == 30:
                sitl.team[0].params.set("MPC_XY_CRUISE", 4.0)
            sitl.run(0.25)
            v = sitl.vehicle
            s = v.true_state
            samples.append((v.time_us, s.position_enu_m.copy(), (s.roll_rad, s.pitch_rad, s.yaw_rad)))
        params = {n: sitl.team[0].params[n] for n in sitl.team[0].params.names()}
        logger = sitl.team[0].logger
        assert logger.dropped == 0, logger.drop_reason  # every sample fitted its PX4 field
    finally:
        sitl.close()
    return run / ULOG_NAME, samples, params


def _data(ulog: ULog, name: str) -> dict:
    return ulog.get_dataset(name).data


def test_every_topic_parses_with_px4_s_names_and_types(flown):
    path, _, _ = flown
    u = ULog(str(path))
    assert not u.file_corruption
    assert set(TOPICS) <= {d.name for d in u.data_list}
    info = u.msg_info_dict
    assert info["sys_name"] == "uavsearch" and info["ver_sw"] and u.get_version_info_str() is not None
    assert info["time_ref_utc"] == 0 and u.initial_parameters["MAV_TYPE"] == 2  # a quadrotor, as pyulog reads it
    fields = {t: {name: kind for kind, _, name in u.message_formats[t].fields} for t in TOPICS}
    assert fields["vehicle_local_position"]["x"] == "float" and fields["vehicle_local_position"]["xy_valid"] == "bool"
    assert fields["vehicle_global_position"]["lat"] == "double" and fields["vehicle_status"]["nav_state"] == "uint8_t"
    assert fields["position_setpoint_triplet"]["current"] == "position_setpoint"  # the nested format
    assert u.message_formats["vehicle_local_position"].fields[0] == ("uint64_t", 0, "timestamp")
    status = _data(u, "vehicle_status")
    assert {NAV_STATE_AUTO_TAKEOFF, NAV_STATE_AUTO_LOITER} <= set(status["nav_state"].tolist())
    assert set(status["arming_state"].tolist()) == {1, 2} and set(status["vehicle_type"].tolist()) == {1}
    triplet = _data(u, "position_setpoint_triplet")
    assert triplet["current.valid"].any() and np.all(np.diff(triplet["timestamp"]) >= 200_000)
    land = _data(u, "vehicle_land_detected")
    assert land["landed"][0] == 1 and land["landed"][-1] == 0
    assert (_data(u, "battery_status")["discharged_mah"][-1] > 0) and _data(u, "vehicle_gps_position")["fix_type"][-1] == 3
    motors = _data(u, "actuator_motors")
    assert np.nanmax(motors["control[0]"]) > 0.3 and np.isnan(motors["control[4]"]).all()
    # PX4's default logging intervals: attitude 50 ms, local position 100 ms, GPS at its 5 Hz, IMU every sample
    for topic, dt_ms in (("vehicle_attitude", 50), ("vehicle_local_position", 100), ("vehicle_gps_position", 200),
                         ("sensor_combined", 10), ("battery_status", 200)):
        assert np.median(np.diff(_data(u, topic)["timestamp"])) == pytest.approx(dt_ms * 1000, rel=0.05), topic


def test_position_and_attitude_match_the_vehicle_s_truth(flown):
    path, samples, _ = flown
    samples = samples[:-1]  # the vehicle logs an instant at its next step: the last one was never stepped past
    u = ULog(str(path))
    t = np.array([s[0] for s in samples])
    truth_ned = np.array([[p[1], p[0], -p[2]] for _, p, _ in samples])
    gt = _data(u, "vehicle_local_position_groundtruth")  # every 100 ms
    assert gt["timestamp"][0] <= t[0] and gt["timestamp"][-1] >= t[-1]
    logged = np.stack([np.interp(t, gt["timestamp"], gt[k]) for k in ("x", "y", "z")], axis=1)
    assert np.abs(logged - truth_ned).max() < 0.5 and truth_ned[:, 2].min() < -4.5  # it did fly
    lp = _data(u, "vehicle_local_position")  # the estimate, against the truth
    est = np.stack([np.interp(t, lp["timestamp"], lp[k]) for k in ("x", "y", "z")], axis=1)
    assert np.abs(est - truth_ned).max() < 1.5
    att = _data(u, "vehicle_attitude")
    for ts, _, rpy in samples[::4]:
        i = np.searchsorted(att["timestamp"], ts, side="right") - 1
        q = [att[f"q[{k}]"][i] for k in range(4)]
        err = [math.remainder(a - b, 2 * math.pi) for a, b in zip(quat_to_euler(q), rpy)]
        assert max(abs(e) for e in err) < math.radians(4.0), (ts, err)


def test_parameters_their_changes_and_texts_are_logged(flown):
    path, _, params = flown
    u = ULog(str(path))
    for name, value in params.items():
        if name != "MPC_XY_CRUISE":
            assert u.initial_parameters[name] == pytest.approx(value, rel=1e-6), name
    assert u.initial_parameters["MPC_XY_CRUISE"] == 5.0
    assert [(n, v) for _, n, v in u.changed_parameters] == [("MPC_XY_CRUISE", 4.0)]
    texts = [(m.log_level_str(), m.message) for m in u.logged_messages]
    assert ("INFO", "Armed") in texts, texts


def test_pyulog_s_commands_read_it(flown, tmp_path):
    path, _, _ = flown
    info = subprocess.run(["ulog_info", str(path)], capture_output=True, text=True, timeout=60, env=clean_env())
    assert info.returncode == 0, info.stderr
    for topic in TOPICS:
        assert f" {topic} (0," in info.stdout, topic
    out = subprocess.run(["ulog2csv", "-o", str(tmp_path), str(path)], capture_output=True, text=True, timeout=60,
                         env=clean_env())
    assert out.returncode == 0, out.stderr
    csv = (tmp_path / f"{path.stem}_vehicle_local_position_0.csv").read_text().splitlines()
    assert csv[0].startswith("timestamp,timestamp_sample,") and len(csv) > 40


def test_a_file_cut_anywhere_reads_up_to_its_last_whole_message(flown, tmp_path):
    path, _, _ = flown
    data = path.read_bytes()
    whole = ULog(str(path))
    n_whole = len(_data(whole, "vehicle_local_position")["timestamp"])
    cut = tmp_path / "cut.ulg"
    rng = np.random.default_rng(0)
    ends = sorted(rng.integers(len(data) // 3, len(data), size=6).tolist()) + [len(data) - 1]
    for end in ends:
        cut.write_bytes(data[:end])
        u = ULog(str(cut))
        ts = _data(u, "vehicle_local_position")["timestamp"]
        assert 0 < len(ts) <= n_whole
        assert np.array_equal(ts, _data(whole, "vehicle_local_position")["timestamp"][:len(ts)]), end


def test_a_team_writes_one_log_per_vehicle(tmp_path):
    cfg = SitlConfig(scene_seed=None, speed=math.inf, api_port=0, gcs_port=0, run_dir=tmp_path, vehicles=2)
    sitl = Sitl(cfg)
    try:
        sitl.run(1.0)
    finally:
        sitl.close()
    for sysid in (1, 2):
        u = ULog(str(tmp_path / f"vehicle{sysid}" / ULOG_NAME))
        assert set(_data(u, "vehicle_status")["system_id"].tolist()) == {sysid}
        assert u.initial_parameters["MAV_SYS_ID"] == sysid
    gt = [_data(ULog(str(tmp_path / f"vehicle{i}" / ULOG_NAME)), "vehicle_local_position_groundtruth")["y"][-1]
          for i in (1, 2)]
    assert gt[1] - gt[0] == pytest.approx(10.0, abs=0.2)  # instance 1's home lies 10 m east
    off = SitlConfig(scene_seed=None, speed=math.inf, api_port=0, gcs_port=0, run_dir=tmp_path / "off", ulog=False)
    Sitl(off).close()
    assert not (tmp_path / "off" / ULOG_NAME).exists()


def test_a_killed_vehicle_s_log_matches_its_telemetry(tmp_path, monkeypatch):
    """`uavsearch sitl` as its own process, flown over MAVLink with the conversation in a tlog, then SIGKILLed:
    its flight.ulg reads up to where it was killed, and its position matches LOCAL_POSITION_NED's."""
    monkeypatch.setenv("MAVLINK20", "1")
    p = SitlProcess(tmp_path, "--param", "MIS_TAKEOFF_ALT=4", speed="4", gcs_port=0, camera=False, env=clean_env())
    tlog = TlogWriter(tmp_path / "telemetry.tlog", clock="sim")
    conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{p.api_port}", source_system=245, source_component=190,
                                      dialect="common")
    tlog.attach(conn, vehicle_sysid=1)
    try:
        assert conn.wait_heartbeat(timeout=10) is not None
        for cmd in (M.MAV_CMD_COMPONENT_ARM_DISARM, M.MAV_CMD_NAV_TAKEOFF):
            conn.mav.command_long_send(1, 1, cmd, 0, 1, 0, 0, 0, math.nan, math.nan, math.nan)
            assert conn.recv_match(type="COMMAND_ACK", blocking=True, timeout=5).result == 0
        end = time.monotonic() + 3.0  # about 12 simulated seconds at 4x
        while time.monotonic() < end:
            conn.recv_match(blocking=True, timeout=0.1)
    finally:
        p.proc.send_signal(signal.SIGKILL)
        p.proc.wait(timeout=10)
        p.stop()
        tlog.close()
        conn.close()
    assert p.exit_reason() == "was killed by SIGKILL"
    u = ULog(str(tmp_path / ULOG_NAME))
    lp = _data(u, "vehicle_local_position")
    mlog = mavutil.mavlink_connection(str(tmp_path / "telemetry.tlog"), dialect="common")
    tel = []
    while (m := mlog.recv_match(type="LOCAL_POSITION_NED")) is not None:
        if m.get_srcSystem() == 1 and m.time_boot_ms * 1000 <= lp["timestamp"][-1]:
            tel.append((m.time_boot_ms * 1000, m.x, m.y, m.z))
    tel = np.array(tel)
    assert len(tel) > 20 and tel[:, 3].min() < -3.0  # it took off before it was killed
    logged = np.stack([np.interp(tel[:, 0], lp["timestamp"], lp[k]) for k in ("x", "y", "z")], axis=1)
    assert np.abs(logged - tel[:, 1:]).max() < 0.5


def test_layout_follows_px4_s_generator():
    """Sorted by type size, nested types last and 8-byte aligned, trailing padding left out of the data (PX4's own
    logs show vehicle_attitude samples of 49 bytes)."""
    inner = MessageDef("position_setpoint", "uint64 timestamp\nbool valid\nfloat64 lat\nfloat32 alt")
    outer = MessageDef("triplet", "uint8 flag\nuint64 timestamp\nposition_setpoint current",
                       {"position_setpoint": inner})
    assert inner.format_text() == "position_setpoint:uint64_t timestamp;double lat;float alt;bool valid;uint8_t[3] _padding0;"
    assert outer.format_text() == "triplet:uint64_t timestamp;uint8_t flag;uint8_t[7] _padding0;position_setpoint current;"
    assert (inner.size, inner.size_no_padding, outer.size_no_padding) == (24, 21, 40)
    assert len(outer.pack({"timestamp": 1, "current": {"lat": 2.0}})) == 40
    from uavsearch.flight.logger import VEHICLE_ATTITUDE

    assert MessageDef("vehicle_attitude", VEHICLE_ATTITUDE).size_no_padding == 49
