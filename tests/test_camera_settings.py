"""The camera's field of view and image size: a mission field (checked against what the models were trained
with) and `uavsearch sitl` options, reported over MAVLink (CAMERA_INFORMATION) like any camera's."""

import math
import subprocess
import sys

import pytest
from pymavlink.dialects.v20 import common as M

from uavsearch.errors import MissionError
from uavsearch.flight.sitl_process import SitlProcess, free_udp_port
from uavsearch.geometry import CameraIntrinsics
from uavsearch.fly.missions import TRAINED_CAMERA, load_mission, mission_from_dict

from uavsearch.testing.mavlink_client import Client
from uavsearch.testing.clean_env import clean_env

WIDE = {"hfov_deg": 75, "width_px": 320, "height_px": 240}


def test_default_mission_flies_the_trained_camera():
    assert load_mission().search_config().intrinsics == TRAINED_CAMERA == CameraIntrinsics()


def test_untrained_camera_is_refused_in_one_line():
    with pytest.raises(MissionError) as e:
        mission_from_dict({"camera": WIDE}, "wide.yaml")
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith("mission wide.yaml: camera: hfov_deg 75 (trained 60)")
    assert "width_px 320 (trained 224)" in msg and "search.allow_untrained: true" in msg


def test_untrained_camera_when_allowed_reaches_the_search():
    m = mission_from_dict({"camera": WIDE, "search": {"allow_untrained": True}})
    assert m.search_config().intrinsics == CameraIntrinsics(320, 240, 75.0)


@pytest.mark.parametrize("bad", [{"hfov_deg": 0}, {"hfov_deg": 180}, {"width_px": 8}, {"fov": 60}])
def test_bad_camera_fields_are_one_line(bad):
    with pytest.raises(MissionError, match="^mission m.yaml: camera"):
        mission_from_dict({"camera": bad, "search": {"allow_untrained": True}}, "m.yaml")


def test_sitl_camera_options_reach_camera_information(tmp_path):
    port = free_udp_port()
    sitl = SitlProcess(tmp_path, "--camera-hfov", "75", "--camera-size", "320x240", api_port=port, gcs_port=0,
                       camera=False, env=clean_env())
    try:
        assert "camera    320x240 px, 75 deg horizontal FOV" in "".join(sitl.banner)
        c = Client(port)
        c.mav.command_long_send(1, 100, M.MAV_CMD_REQUEST_MESSAGE, 0, M.MAVLINK_MSG_ID_CAMERA_INFORMATION,
                                0, 0, 0, 0, 0, 0)
        info = c.recv("CAMERA_INFORMATION", timeout=10.0)
        c.close()
    finally:
        sitl.stop()
    assert info is not None and (info.resolution_h, info.resolution_v) == (320, 240)
    fx_px = info.focal_length * info.resolution_h / info.sensor_size_h
    assert fx_px == pytest.approx(CameraIntrinsics(320, 240, 75.0).fx, rel=1e-3)
    assert math.degrees(2 * math.atan(160 / fx_px)) == pytest.approx(75.0, abs=0.05)


@pytest.mark.parametrize("args", [["--camera-size", "320"], ["--camera-size", "8x8"], ["--camera-hfov", "wide"]])
def test_bad_sitl_camera_options_are_one_line(args):
    r = subprocess.run([sys.executable, "-m", "uavsearch.flight.sitl", *args], capture_output=True, text=True,
                       timeout=60, env=clean_env())
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith("uavsearch sitl: error: argument --camera-")


def test_replay_draws_the_grid_with_the_flights_camera(tmp_path):
    """A run folder's replay projects its grid overlay with the camera the mission flew, not the default."""
    import numpy as np

    from uavsearch.logs.flight_log import FlightLogWriter
    from uavsearch.logs.step_record import StepRecord
    from uavsearch.replay.replay import replay_run_dir

    mission = mission_from_dict({"camera": WIDE, "search": {"allow_untrained": True}, "fusion": "average",
                                 "policy": "random"})
    w = FlightLogWriter(tmp_path, tlog=False)
    w.header(mission=mission.model_dump(mode="json"), labels=[0] * 100, grid={"n": 10, "cell_m": 5.0},
             fusion="average", agent="average fusion + random policy")
    p = np.full(100, 0.2)
    w.step(StepRecord(t=0, waypoint_enu=[0.0, 0.0, 70.0], reported_position_enu=[0.0, 0.0, 70.0],
                      reported_rpy_rad=[0, 0, 0], image="images/img_0000.png", p_occ=p, valid=np.ones(100, bool),
                      cell_area_px=np.full(100, 100.0), fused=p, sim_time_s=30.0))
    w.close()
    assert replay_run_dir(tmp_path).intrinsics == CameraIntrinsics(320, 240, 75.0)
