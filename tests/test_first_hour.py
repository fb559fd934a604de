"""What a newcomer sees: waits that say what they wait for, messages that name real ports, no run folder
left behind by a flight that never connected. Real UDP on 127.0.0.1, a real `uavsearch sitl` process."""

import subprocess
import sys

import pytest
import yaml

from uavsearch.flight.sitl_process import SitlProcess, free_udp_port
from uavsearch.search.config import SearchConfig
from uavsearch.fly.vehicle import FlightError, FlightSettings, MavlinkVehicle
from uavsearch.testing.clean_env import clean_env


def test_client_names_the_port_it_listens_on():
    v = MavlinkVehicle("udpin:127.0.0.1:0")
    try:
        port = v.conn.port.getsockname()[1]
        assert port > 0 and v.link_text == f"udpin:127.0.0.1:{port}"
    finally:
        v.close()


def test_bad_host_is_one_line_without_library_prints(capfd):
    with pytest.raises(FlightError) as e:
        MavlinkVehicle("tcp:nosuchhost.invalid:5760")
    assert "\n" not in str(e.value) and "cannot open MAVLink connection" in str(e.value)
    assert capfd.readouterr().out == ""  # no pymavlink "... sleeping" retries


def test_bad_url_leaves_no_run_folder(tmp_path):
    from uavsearch.fly.missions import load_mission
    from uavsearch.fly.mission_controller import fly

    with pytest.raises(FlightError):
        fly(load_mission(), connect="udpin:nosuchhost.invalid:14540", out=tmp_path / "run", progress=lambda s: None)
    assert not (tmp_path / "run").exists()


def test_connect_to_nothing_says_so_and_leaves_no_run_folder(tmp_path):
    port = free_udp_port()
    (tmp_path / "m.yaml").write_text(yaml.safe_dump({"name": "nothing", "flight": {"connect_timeout_s": 4.5}}))
    r = subprocess.run([sys.executable, "-m", "uavsearch", "fly", "--mission", str(tmp_path / "m.yaml"),
                        "--connect", f"udpin:127.0.0.1:{port}", "--out", str(tmp_path / "run")],
                       capture_output=True, text=True, timeout=120, env=clean_env())
    assert r.returncode == 2, r.stdout + r.stderr
    assert f"connecting  no heartbeat yet on udpin:127.0.0.1:{port}  2 s of 4 s" in r.stdout
    assert "not flown" not in r.stdout and "flight log:" not in r.stdout
    assert "nothing flown, no flight log kept" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "run").exists()


def test_real_time_take_off_reports_progress(tmp_path):
    """A take-off that lasts seconds of wall clock prints where the vehicle is, in the per-step lines' style."""
    sitl = SitlProcess(tmp_path, api_port=free_udp_port(), gcs_port=0, speed="1", camera=False, env=clean_env())
    lines = []
    v = MavlinkVehicle(f"udpin:127.0.0.1:{sitl.api_port}", SearchConfig(altitude_m=6.0),
                       settings=FlightSettings(end_action="none"), progress=lines.append)
    try:
        v.connect()
        v.take_off()
    finally:
        v.close()
        sitl.stop()
    assert lines[0] == f"connecting to udpin:127.0.0.1:{sitl.api_port} ..."
    climb = [ln for ln in lines if ln.startswith("take-off  at E")]
    assert climb, lines
    u = [float(ln.split(" U ")[1].split(" m")[0]) for ln in climb]
    assert all(0.0 <= x < 6.5 for x in u) and u == sorted(u)
    assert all("flew" in ln and "(to 6 m)" in ln for ln in climb)


