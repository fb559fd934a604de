"""A team on one clock: `uavsearch sitl --vehicles 3` as a real process over loopback UDP, PX4 SITL's
conventions (system id I + 1, API link on base + I, every vehicle on the one GCS port), one lockstep
grant for all, the separation rule, and three MAVSDK clients flying their own vehicle at once."""

import math
import subprocess
import sys
import time
from pathlib import Path

import pytest
from pymavlink import mavutil

from uavsearch.flight.lockstep import MAV_CMD_SIM_ADVANCE
from uavsearch.flight.sitl_process import SitlProcess, free_udp_port, free_udp_ports
from uavsearch.testing.clean_env import clean_env
from uavsearch.testing.mavlink_client import Client
from uavsearch.testing.mavproxy_session import MavProxy, Observer, needs_mavproxy

M = mavutil.mavlink
ROOT = Path(__file__).resolve().parents[1]
N = 3


def _team(tmp_path, *args, speed="max", lockstep=False):
    base, gcs = free_udp_ports(N), free_udp_port()
    p = SitlProcess(tmp_path, "--vehicles", str(N), *args, api_port=base, gcs_port=gcs, speed=speed,
                    lockstep=lockstep, camera=False, env=clean_env())
    return p, base, gcs


@pytest.fixture
def team(tmp_path):
    p, base, gcs = _team(tmp_path, speed="1")
    yield p, base, gcs
    code, out = p.stop()
    assert code == 0, out


def test_ids_ports_and_one_ground_station_port(team):
    p, base, gcs = team
    assert f"{N} vehicles (sysid 1, 2, 3) on one clock" in "".join(p.banner)
    gs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{gcs}", source_system=255, dialect="common")
    try:  # a plain pymavlink ground station on the GCS port hears every autopilot and its camera
        seen, end = set(), time.monotonic() + 15
        while time.monotonic() < end and len(seen) < 2 * N:
            m = gs.recv_match(type="HEARTBEAT", blocking=True, timeout=0.5)
            if m is not None:
                seen.add((m.get_srcSystem(), m.get_srcComponent()))
        assert seen == {(s, c) for s in range(1, N + 1) for c in (1, 100)}
    finally:
        gs.close()
    lons = []
    for i in range(N):  # vehicle I's API link is base + I, and it is system I + 1
        c = Client(base + i)
        try:
            assert c.sysid == i + 1 and c.system.params.get("MAV_SYS_ID") == i + 1
            pos = c.recv("GLOBAL_POSITION_INT", 5)
            lons.append(pos.lon * 1e-7)
        finally:
            c.close()
    east = [(lon - lons[0]) * 111_320.0 * math.cos(math.radians(47.397742)) for lon in lons]
    assert east == pytest.approx([0.0, 10.0, 20.0], abs=1.0)  # homes 10 m apart


def _grant(c: Client, until_ms: int):
    c.mav.command_int_send(c.sysid, 1, M.MAV_FRAME_MISSION, MAV_CMD_SIM_ADVANCE, 0, 0, 0, 0, 0, 0, until_ms, 0, 0.0)
    return c.recv("COMMAND_ACK", 10, cond=lambda m: m.command == MAV_CMD_SIM_ADVANCE)


def _clock(c: Client) -> list:
    """[latest time_boot_ms] of the vehicle's position reports, kept up to date as frames arrive."""
    latest = [0]

    def keep(m):
        if m.get_type() == "GLOBAL_POSITION_INT" and m.get_srcSystem() == c.sysid:
            latest[0] = max(latest[0], m.time_boot_ms)

    c.connection.add_listener(keep)
    return latest


def _latest_time_ms(c: Client, clock: list, wall_s: float = 0.5) -> int:
    end = time.monotonic() + wall_s
    while time.monotonic() < end:
        c.recv("GLOBAL_POSITION_INT", 0.05)
    return clock[0]


def test_one_grant_runs_every_vehicle(tmp_path):
    p, base, _ = _team(tmp_path, lockstep=True)
    clients = []
    try:
        clients = [Client(base + i) for i in range(N)]
        clocks = [_clock(c) for c in clients]
        assert _grant(clients[1], 1500).result_param2 == 1500  # granted through vehicle 2 ...
        for c, clock in zip(clients, clocks):  # ... every vehicle ran that far (its stream's last tick), no further
            assert 1300 <= _latest_time_ms(c, clock) <= 1500
        assert _grant(clients[0], 0).result_param2 == 1500  # a barrier on vehicle 1 reads the one clock
        assert _grant(clients[2], 2000).result_param2 == 2000
        assert 1800 <= _latest_time_ms(clients[0], clocks[0]) <= 2000
    finally:
        for c in clients:
            c.close()
        code, out = p.stop()
        assert code == 0, out


def _reposition(c: Client, lat: float, lon: float, alt_amsl: float):
    return c.command(M.MAV_CMD_DO_REPOSITION, -1, 1, 0, math.nan, lat, lon, alt_amsl)


def test_a_goto_near_another_vehicle_is_refused(tmp_path):
    p, base, _ = _team(tmp_path, "--param", "MIS_TAKEOFF_ALT=5")
    one, two = Client(base), Client(base + 1)
    try:
        for c in (one, two):
            c.send_heartbeat()
            assert c.command(M.MAV_CMD_COMPONENT_ARM_DISARM, 1).result == M.MAV_RESULT_ACCEPTED
            assert c.command(M.MAV_CMD_NAV_TAKEOFF, *[math.nan] * 7).result == M.MAV_RESULT_ACCEPTED
        first = one.recv("GLOBAL_POSITION_INT", 30, cond=lambda m: m.relative_alt > 4000)
        here = (first.lat * 1e-7, first.lon * 1e-7, first.alt * 1e-3)
        ack = _reposition(two, *here)  # onto vehicle 1
        assert ack.result == M.MAV_RESULT_DENIED
        text = two.recv("STATUSTEXT", 3, cond=lambda m: "Reposition denied" in m.text)
        assert text is not None and "within 5 m of vehicle 1" in text.text
        north = here[0] + 40.0 / 111_200.0  # 40 m north: clear of both
        assert _reposition(two, north, here[1], here[2]).result == M.MAV_RESULT_ACCEPTED
        ack = _reposition(one, north + 2.0 / 111_200.0, here[1], here[2])  # next to vehicle 2's goal
        assert ack.result == M.MAV_RESULT_DENIED
        assert one.system.params.set_float("SIM_SEP_DIST", 0.0)  # the rule is a parameter; 0 turns it off
        assert _reposition(one, north + 2.0 / 111_200.0, here[1], here[2]).result == M.MAV_RESULT_ACCEPTED
    finally:
        one.close()
        two.close()
        code, out = p.stop()
        assert code == 0, out


def test_three_mavsdk_clients_fly_their_own_vehicle(tmp_path):
    pytest.importorskip("mavsdk.asyncio")
    p, base, _ = _team(tmp_path, "--param", "MIS_TAKEOFF_ALT=5")
    try:
        run = subprocess.run([sys.executable, "mavsdk_team.py", "--vehicles", str(N), "--port", str(base)],
                             cwd=ROOT / "tools", env=clean_env(), capture_output=True, text=True, timeout=240)
    finally:
        code, log = p.stop()
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    for i in range(N):
        lines = [ln for ln in run.stdout.splitlines() if ln.startswith(f"[vehicle {i + 1} :{base + i}")]
        said = "\n".join(lines)
        assert f"system id {i + 1}:" in said and "arrived" in said and "landed and disarmed" in said, said
    assert f"all {N} vehicles landed and disarmed" in run.stdout
    assert code == 0, log


@needs_mavproxy
def test_mavproxy_addresses_each_vehicle_of_the_team(tmp_path):
    """MAVProxy on the one ground-station port sees the team; `vehicle 2` then `arm throttle` arms vehicle 2 only."""
    p, base, gcs = _team(tmp_path, speed="4")
    mp, observers = None, []
    try:
        observers = [Observer(base + i) for i in range(N)]
        pump = lambda: [o.pump() for o in observers]  # noqa: E731
        mp = MavProxy(gcs, tmp_path)
        mp.expect(r"online system 1", timeout_s=30, pump=pump)
        for sysid in (1, 2, 3):  # each autopilot and its camera, as MAVProxy's `vehicle` command lists them
            for compid in (1, 100):
                mp.expect(rf"Detected vehicle {sysid}:{compid} on link 0", timeout_s=30, pump=pump)
        k = mp.send("vehicle 2")
        mp.expect(r"[Ss]et vehicle 2|vehicle 2", k, pump=pump)
        mp.send("arm throttle")
        observers[1].wait(lambda: observers[1].armed, "vehicle 2 armed")
        time.sleep(0.5)
        pump()
        assert not observers[0].armed and not observers[2].armed  # the others stay disarmed
        mp.send("disarm")
        observers[1].wait(lambda: not observers[1].armed, "vehicle 2 disarmed")
    finally:
        if mp is not None:
            mp.stop()
        for o in observers:
            o.c.close()
        code, out = p.stop()
        assert code == 0, out


def test_instance_conventions_follow_px4_sitl():
    """--instance I (PX4's `px4 -i I`): system id I + 1, ports + I, noise seed + I, home 10 m east per instance;
    --one-api-port keeps every API link on the one port."""
    from uavsearch.flight.sitl import HOME_SPACING_M, SitlConfig, instance_config

    cfg = SitlConfig(seed=7, vehicles=3)
    for i in range(3):
        c = instance_config(cfg, i)
        assert (c.instance, c.params["MAV_SYS_ID"], c.seed) == (i, i + 1, 7 + i)
        assert (c.api_port, c.api_local_port, c.gcs_port, c.gcs_local_port) == (14540 + i, 14580 + i, 14550, 18570 + i)
        assert c.start_enu == (HOME_SPACING_M * i, 0.0, 0.0) and c.vehicles == 1
    alone = instance_config(SitlConfig(instance=2), 0)  # `uavsearch sitl --instance 2`
    assert (alone.params["MAV_SYS_ID"], alone.api_port, alone.start_enu[0]) == (3, 14542, 2 * HOME_SPACING_M)
    shared = instance_config(SitlConfig(vehicles=3, one_api_port=True, api_port=30000), 2)
    assert shared.api_port == 30000 and shared.api_local_port == 14582
    off = instance_config(SitlConfig(vehicles=2, api_port=0, api_local_port=0), 1)
    assert (off.api_port, off.api_local_port) == (0, 0)  # a link that is off stays off; "any port" stays any


@pytest.mark.parametrize("args, words", [(["--vehicles", "0"], "--vehicles must be 1..16"),
                                         (["--vehicles", "2", "--param", "MAV_SYS_ID=5"], "do not set MAV_SYS_ID"),
                                         (["--setting", "nowhere"], "unknown setting")])
def test_bad_team_options_are_one_line(tmp_path, args, words):
    r = subprocess.run([sys.executable, "-m", "uavsearch.flight.sitl", "--no-camera-scene", "--duration", "0.1",
                        "--out", str(tmp_path / "run"), "--api-local-port", "0", "--gcs-local-port", "0",
                        "--api-port", "0", "--gcs-port", "0", *args],
                       capture_output=True, text=True, timeout=60, env=clean_env())
    assert r.returncode != 0 and "Traceback" not in r.stderr and words in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
