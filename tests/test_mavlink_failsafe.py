"""Geofence refusal, datalink-loss failsafe and MAVLink 2 signing, over pymavlink against real sitl processes."""

import hashlib
import math

import pytest
from pymavlink import mavutil

from uavsearch.testing.mavlink_client import NAN, Client
from uavsearch.flight.sitl_process import SitlProcess
from uavsearch.testing.clean_env import clean_env

M = mavutil.mavlink
ORIGIN_ALT = 488.0


def _latlon(north_m, east_m):
    from uavsearch.geometry import GeodeticOrigin

    lla = GeodeticOrigin().enu_to_geodetic([east_m, north_m, 0.0])
    return float(lla[0]), float(lla[1])


@pytest.fixture(scope="module")
def flying(tmp_path_factory):
    p = SitlProcess(tmp_path_factory.mktemp("sitl"), "--param", "GF_MAX_HOR_DIST=40", "--param", "COM_DL_LOSS_T=1",
                    "--param", "NAV_DLL_ACT=2", "--param", "MIS_TAKEOFF_ALT=4", "--param", "RTL_RETURN_ALT=6",
                    camera=False, env=clean_env())
    c = Client(p.gcs_port)
    assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == M.MAV_RESULT_ACCEPTED
    assert c.command(M.MAV_CMD_NAV_TAKEOFF, *[NAN] * 7).result == M.MAV_RESULT_ACCEPTED
    assert c.wait_mode(4, 3), "takeoff did not end in Hold"
    yield p, c
    c.close()
    code, out = p.stop()
    assert code == 0, out


def test_geofence_refuses_goto_and_mission(flying):
    _, c = flying
    # Hold after takeoff settles at MIS_TAKEOFF_ALT.
    assert c.recv("GLOBAL_POSITION_INT", timeout=10, cond=lambda m: abs(m.relative_alt / 1000 - 4.0) < 0.3) is not None
    lat, lon = _latlon(60.0, 0.0)
    c.mav.command_int_send(1, 1, M.MAV_FRAME_GLOBAL_INT, M.MAV_CMD_DO_REPOSITION, 0, 0, -1, 1, 0, NAN,
                           int(lat * 1e7), int(lon * 1e7), ORIGIN_ALT + 5)
    ack = c.recv("COMMAND_ACK", cond=lambda m: m.command == M.MAV_CMD_DO_REPOSITION)
    assert ack.result == M.MAV_RESULT_DENIED
    assert c.recv("STATUSTEXT", cond=lambda m: "geofence" in m.text) is not None
    item = M.MAVLink_mission_item_int_message(1, 1, 0, 6, M.MAV_CMD_NAV_WAYPOINT, 0, 1, 0, 0, 0, NAN,
                                              int(lat * 1e7), int(lon * 1e7), 5.0)
    c.mav.mission_count_send(1, 1, 1, 0)
    assert c.recv("MISSION_REQUEST_INT").seq == 0
    c.mav.send(item)
    assert c.recv("MISSION_ACK").type == M.MAV_MISSION_DENIED
    # Inside the fence the same goto is accepted and flown.
    lat, lon = _latlon(8.0, 0.0)
    c.mav.command_int_send(1, 1, M.MAV_FRAME_GLOBAL_INT, M.MAV_CMD_DO_REPOSITION, 0, 0, -1, 1, 0, NAN,
                           int(lat * 1e7), int(lon * 1e7), ORIGIN_ALT + 5)
    assert c.recv("COMMAND_ACK", cond=lambda m: m.command == M.MAV_CMD_DO_REPOSITION).result == M.MAV_RESULT_ACCEPTED
    pos = c.recv("LOCAL_POSITION_NED", timeout=20, cond=lambda m: abs(m.x - 8.0) < 0.5 and abs(m.z + 5.0) < 0.5)
    assert pos is not None


def test_datalink_loss_triggers_return_and_landing(flying):
    _, c = flying
    c.send_heartbeat()  # the ground station appears ...
    assert c.wait_heartbeat() is not None
    # ... and goes silent: after COM_DL_LOSS_T (1 s, in both clocks) NAV_DLL_ACT=2 returns.
    assert c.recv("STATUSTEXT", timeout=10, cond=lambda m: "Data link lost" in m.text) is not None
    assert c.wait_mode(4, 5, timeout=5)
    # The return ends on the ground at home, disarmed.
    hb = None
    for _ in range(200):
        hb = c.wait_heartbeat(1.0)
        if hb is not None and not hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED:
            break
    assert hb is not None and not hb.base_mode & M.MAV_MODE_FLAG_SAFETY_ARMED
    pos = c.recv("LOCAL_POSITION_NED")
    assert math.hypot(pos.x, pos.y) < 1.5 and abs(pos.z) < 0.5


KEY = hashlib.sha256(b"uavsearch test key").digest()


def _signed_frame(m) -> bool:
    """The MAVLink 2 incompat flag says the frame carries a signature (whether or not we can check it)."""
    buf = m.get_msgbuf()
    return buf[0] == 0xFD and bool(buf[2] & M.MAVLINK_IFLAG_SIGNED)


@pytest.fixture(scope="module")
def signed(tmp_path_factory):
    p = SitlProcess(tmp_path_factory.mktemp("sitl"), "--signing-key", KEY.hex(), camera=False, env=clean_env())
    yield p
    code, out = p.stop()
    assert code == 0, out


def test_signing_gcs_link_rejects_unsigned_and_wrong_key(signed):
    c = Client(signed.gcs_port)
    hb = c.wait_heartbeat()
    assert _signed_frame(hb)  # the vehicle signs what it sends
    assert c.command(31999, timeout=1.0) is None  # unsigned: dropped, no answer
    c.setup_signing(hashlib.sha256(b"wrong").digest())
    assert c.command(31999, timeout=1.0) is None  # wrong key: dropped
    c.setup_signing(KEY)
    ack = c.command(31999)
    assert ack is not None and ack.result == M.MAV_RESULT_UNSUPPORTED and ack._signed  # verified with KEY
    st = c.recv("SYS_STATUS", cond=lambda m: m.errors_comm >= 2)
    assert st is not None  # the rejected frames were counted
    c.close()


def test_signing_api_link_signs_output_and_accepts_unsigned(signed):
    c = Client(signed.api_port)  # MAVSDK cannot sign, so the API link accepts unsigned input ...
    assert _signed_frame(c.wait_heartbeat())
    assert c.command(31999).result == M.MAV_RESULT_UNSUPPORTED
    c.setup_signing(hashlib.sha256(b"wrong").digest())
    assert c.command(31999, timeout=1.0) is None  # ... but never a frame signed with the wrong key
    c.close()
