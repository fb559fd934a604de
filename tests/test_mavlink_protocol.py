"""pymavlink against a real `uavsearch sitl` process (real UDP, real JSBSim): params, commands,
message intervals, the mission protocol, and robustness to malformed bytes."""

import struct
from pathlib import Path

import numpy as np
import pytest
from pymavlink import mavutil

from uavsearch.testing.mavlink_client import NAN, Client
from uavsearch.flight.sitl_process import SitlProcess
from uavsearch.testing.clean_env import clean_env

M = mavutil.mavlink
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def sitl(tmp_path_factory):
    p = SitlProcess(tmp_path_factory.mktemp("sitl"), camera=False, env=clean_env())
    yield p
    code, out = p.stop()
    assert code == 0, out  # Ctrl-C stops it cleanly
    assert "stopped:" in out


@pytest.fixture
def gcs(sitl):
    c = Client(sitl.gcs_port)
    yield c
    c.close()


def _as_int(value: float) -> int:
    return struct.unpack("<i", struct.pack("<f", value))[0]


def test_banner_lists_ports_home_and_speed(sitl):
    text = "".join(sitl.banner)
    assert f"127.0.0.1:{sitl.api_port}" in text and f"127.0.0.1:{sitl.gcs_port}" in text
    assert "speed max" in text and "lat 47.3977420" in text


def test_heartbeat_is_px4_quadrotor_in_hold(gcs):
    hb = gcs.wait_heartbeat()
    assert hb.autopilot == M.MAV_AUTOPILOT_PX4 and hb.type == M.MAV_TYPE_QUADROTOR
    assert hb.base_mode & M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert hb.custom_mode == (3 << 24) | (4 << 16)  # AUTO.LOITER (Hold)
    st = gcs.recv("SYS_STATUS")
    for bit in (M.MAV_SYS_STATUS_SENSOR_3D_GYRO, M.MAV_SYS_STATUS_SENSOR_3D_ACCEL, M.MAV_SYS_STATUS_SENSOR_3D_MAG,
                M.MAV_SYS_STATUS_SENSOR_GPS, M.MAV_SYS_STATUS_GEOFENCE):
        assert st.onboard_control_sensors_present & bit and st.onboard_control_sensors_health & bit
    ext = gcs.recv("EXTENDED_SYS_STATE")
    assert ext.landed_state == M.MAV_LANDED_STATE_ON_GROUND


def test_params_list_read_set_with_bytewise_ints(gcs):
    gcs.mav.param_request_list_send(1, 1)
    seen = {}
    while True:
        m = gcs.recv("PARAM_VALUE", timeout=2.0)
        if m is None:
            break
        seen[m.param_index] = m
        if len(seen) == m.param_count:
            break
    count = next(iter(seen.values())).param_count
    assert len(seen) == count > 50 and sorted(seen) == list(range(count))
    quoted = f"all {count} of the vehicle's parameters"
    doc = " ".join((ROOT / "docs" / "mavlink.md").read_text().split())
    assert quoted in doc, f"docs/mavlink.md should say '{quoted}' (the count this vehicle reports)"
    by_name = {m.param_id: m for m in seen.values()}
    assert by_name["MAV_SYS_ID"].param_type == M.MAV_PARAM_TYPE_INT32 and _as_int(by_name["MAV_SYS_ID"].param_value) == 1
    assert by_name["MIS_TAKEOFF_ALT"].param_type == M.MAV_PARAM_TYPE_REAL32

    gcs.mav.param_request_read_send(1, 1, b"MIS_TAKEOFF_ALT", -1)
    assert gcs.recv("PARAM_VALUE", cond=lambda m: m.param_id == "MIS_TAKEOFF_ALT").param_value == pytest.approx(2.5)
    idx = by_name["GF_ACTION"].param_index
    gcs.mav.param_request_read_send(1, 1, b"", idx)
    assert gcs.recv("PARAM_VALUE", cond=lambda m: m.param_index == idx).param_id == "GF_ACTION"

    gcs.mav.param_set_send(1, 1, b"MIS_TAKEOFF_ALT", 6.5, M.MAV_PARAM_TYPE_REAL32)
    assert gcs.recv("PARAM_VALUE", cond=lambda m: m.param_id == "MIS_TAKEOFF_ALT").param_value == pytest.approx(6.5)
    enc = struct.unpack("<f", struct.pack("<i", 3))[0]
    gcs.mav.param_set_send(1, 1, b"NAV_DLL_ACT", enc, M.MAV_PARAM_TYPE_INT32)
    assert _as_int(gcs.recv("PARAM_VALUE", cond=lambda m: m.param_id == "NAV_DLL_ACT").param_value) == 3
    # Out of range: refused, the stored value comes back, with a status text saying why.
    gcs.mav.param_set_send(1, 1, b"GF_ACTION", struct.unpack("<f", struct.pack("<i", 9))[0], M.MAV_PARAM_TYPE_INT32)
    assert _as_int(gcs.recv("PARAM_VALUE", cond=lambda m: m.param_id == "GF_ACTION").param_value) == 2
    assert "GF_ACTION" in gcs.recv("STATUSTEXT", cond=lambda m: "GF_ACTION" in m.text).text
    for name, value in ((b"MIS_TAKEOFF_ALT", 2.5), (b"NAV_DLL_ACT", struct.unpack("<f", struct.pack("<i", 0))[0])):
        gcs.mav.param_set_send(1, 1, name, value, M.MAV_PARAM_TYPE_REAL32 if b"ALT" in name else M.MAV_PARAM_TYPE_INT32)
        assert gcs.recv("PARAM_VALUE", cond=lambda m, n=name: m.param_id == n.decode()) is not None


def test_unsupported_and_denied_commands(gcs):
    assert gcs.command(31999).result == M.MAV_RESULT_UNSUPPORTED
    assert gcs.command(M.MAV_CMD_NAV_TAKEOFF, *[NAN] * 7).result == M.MAV_RESULT_DENIED  # disarmed
    assert gcs.command(M.MAV_CMD_DO_SET_MODE, 1, 3, 0).result == M.MAV_RESULT_DENIED  # POSCTL: no RC
    assert gcs.command(M.MAV_CMD_NAV_RETURN_TO_LAUNCH).result == M.MAV_RESULT_DENIED  # disarmed
    assert gcs.command(M.MAV_CMD_REQUEST_MESSAGE, 99999).result == M.MAV_RESULT_UNSUPPORTED
    # Another system's command gets no answer at all.
    gcs.mav.command_long_send(42, 1, M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
    assert gcs.recv("COMMAND_ACK", timeout=0.5) is None
    ack = gcs.command(M.MAV_CMD_REQUEST_MESSAGE, M.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
    assert ack.result == M.MAV_RESULT_ACCEPTED and ack.target_system == 255 and ack.target_component == 190
    av = gcs.recv("AUTOPILOT_VERSION")
    assert av.capabilities & M.MAV_PROTOCOL_CAPABILITY_MISSION_INT
    assert av.capabilities & M.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE


def test_set_message_interval_in_simulation_time(gcs):
    assert gcs.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_ATTITUDE, 40_000).result == M.MAV_RESULT_ACCEPTED
    gcs.recv("ATTITUDE")
    stamps = [gcs.recv("ATTITUDE").time_boot_ms for _ in range(12)]
    gaps = np.diff(stamps)
    assert np.median(gaps) == 40  # 25 Hz of simulated time, whatever the pacing
    assert gcs.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_ATTITUDE, 0).result == M.MAV_RESULT_ACCEPTED
    assert gcs.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, 12345, 1000).result == M.MAV_RESULT_UNSUPPORTED


def _latlon_e7(north_m: float, east_m: float) -> tuple[int, int]:
    from uavsearch.geometry import GeodeticOrigin

    lla = GeodeticOrigin().enu_to_geodetic([east_m, north_m, 0.0])
    return int(round(lla[0] * 1e7)), int(round(lla[1] * 1e7))


def upload(gcs, items) -> int:
    """The mission upload protocol, step by step; returns the MISSION_ACK type."""
    gcs.mav.mission_count_send(1, 1, len(items), 0)
    while True:
        m = gcs.recv(["MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"])
        assert m is not None and m.get_type() != "MISSION_REQUEST", "vehicle must ask with MISSION_REQUEST_INT"
        if m.get_type() == "MISSION_ACK":
            return m.type
        gcs.mav.send(items[m.seq])


def test_mission_upload_download_clear(gcs):
    lat, lon = _latlon_e7(10.0, 5.0)
    items = [
        M.MAVLink_mission_item_int_message(1, 1, 0, 3, M.MAV_CMD_NAV_TAKEOFF, 0, 1, 0, 0, 0, NAN, 0, 0, 8.0),
        M.MAVLink_mission_item_int_message(1, 1, 1, 6, M.MAV_CMD_NAV_WAYPOINT, 0, 1, 1.5, 0, 0, NAN, lat, lon, 8.0),
        M.MAVLink_mission_item_int_message(1, 1, 2, 2, M.MAV_CMD_DO_CHANGE_SPEED, 0, 1, 1, 3.0, -1, 0, 0, 0, 0),
        M.MAVLink_mission_item_int_message(1, 1, 3, 2, M.MAV_CMD_NAV_RETURN_TO_LAUNCH, 0, 1, 0, 0, 0, 0, 0, 0, 0),
    ]
    assert upload(gcs, items) == M.MAV_MISSION_ACCEPTED
    cur = gcs.recv("MISSION_CURRENT", cond=lambda m: m.total == 4)
    assert cur.seq == 0 and cur.mission_state == M.MISSION_STATE_NOT_STARTED

    gcs.mav.mission_request_list_send(1, 1, 0)
    assert gcs.recv("MISSION_COUNT").count == 4
    for i, sent in enumerate(items):
        gcs.mav.mission_request_int_send(1, 1, i, 0)
        got = gcs.recv("MISSION_ITEM_INT", cond=lambda m, i=i: m.seq == i)
        assert (got.command, got.frame, got.x, got.y) == (sent.command, sent.frame, sent.x, sent.y)
        assert got.z == pytest.approx(sent.z) and got.param1 == pytest.approx(sent.param1)
    gcs.mav.mission_ack_send(1, 1, 0, 0)

    # Unsupported command and out-of-range sequence numbers are refused.
    bad = [M.MAVLink_mission_item_int_message(1, 1, 0, 2, 31999, 0, 1, 0, 0, 0, 0, 0, 0, 0)]
    assert upload(gcs, bad) == M.MAV_MISSION_UNSUPPORTED
    gcs.mav.mission_request_int_send(1, 1, 17, 0)
    assert gcs.recv("MISSION_ACK").type == M.MAV_MISSION_INVALID_SEQUENCE

    gcs.mav.mission_set_current_send(1, 1, 1)
    assert gcs.recv("MISSION_CURRENT", cond=lambda m: m.seq == 1) is not None
    gcs.mav.mission_clear_all_send(1, 1, 0)
    assert gcs.recv("MISSION_ACK").type == M.MAV_MISSION_ACCEPTED
    gcs.mav.mission_request_list_send(1, 1, 0)
    assert gcs.recv("MISSION_COUNT").count == 0
    assert gcs.command(M.MAV_CMD_DO_SET_MODE, 1, 4, 4).result == M.MAV_RESULT_DENIED  # no mission to fly


def test_malformed_bytes_are_dropped_and_counted(gcs):
    rng = np.random.default_rng(3)
    before = gcs.recv("SYS_STATUS").errors_comm
    valid = gcs.mav.command_long_encode(1, 1, 31999, 0, 0, 0, 0, 0, 0, 0, 0).pack(gcs.mav)
    for _ in range(100):
        gcs.send_raw(rng.integers(0, 256, rng.integers(1, 300), dtype=np.uint8).tobytes())
    for cut in range(1, len(valid)):
        gcs.send_raw(valid[:cut])  # truncated frames
    corrupt = bytearray(valid)
    corrupt[-1] ^= 0xFF  # bad CRC
    gcs.send_raw(bytes(corrupt))
    gcs.send_raw(b"\xfd" + b"\xff" * 600)  # a length that does not fit
    # Still alive and answering, and the drops show in SYS_STATUS.errors_comm.
    assert gcs.command(31999).result == M.MAV_RESULT_UNSUPPORTED
    st = gcs.recv("SYS_STATUS", timeout=5.0, cond=lambda m: m.errors_comm > before)
    assert st is not None and st.errors_comm - before >= len(valid)


def test_commands_with_hostile_numbers_are_answered_not_fatal(gcs):
    """Valid frames, absurd contents: NaN, infinities and huge values in every command parameter."""
    rng = np.random.default_rng(11)
    values = [float("nan"), float("inf"), -float("inf"), 1e30, -1e30, 0.0, 1.0, -1.0, 21196.0]
    commands = [M.MAV_CMD_COMPONENT_ARM_DISARM, M.MAV_CMD_NAV_TAKEOFF, M.MAV_CMD_DO_SET_MODE, M.MAV_CMD_DO_REPOSITION,
                M.MAV_CMD_DO_CHANGE_SPEED, M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAV_CMD_REQUEST_MESSAGE,
                M.MAV_CMD_MISSION_START, M.MAV_CMD_DO_SET_HOME, M.MAV_CMD_IMAGE_START_CAPTURE, M.MAV_CMD_NAV_LAND]
    answered = 0
    for i in range(60):
        cmd = commands[i % len(commands)]
        params = [values[j] for j in rng.integers(0, len(values), 7)]
        ack = gcs.command(cmd, *params, target_component=100 if cmd == M.MAV_CMD_IMAGE_START_CAPTURE else 1,
                          timeout=2.0)
        answered += ack is not None
    for _ in range(20):
        p = [values[j] for j in rng.integers(0, len(values), 11)]
        gcs.mav.set_position_target_local_ned_send(0, 1, 1, M.MAV_FRAME_LOCAL_NED, 0, *p[:9], p[9], p[10])
    assert answered == 60  # every command got an ACK (accepted, denied, unsupported or failed)
    # Whatever that did, the vehicle still flies its loop: disarm it and check it answers.
    gcs.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 0, 21196)
    assert gcs.command(31999).result == M.MAV_RESULT_UNSUPPORTED
    assert gcs.wait_heartbeat() is not None
