"""Two autopilots on one link: the client routes every frame by system id and never flips between them.

Two `uavsearch sitl` processes (system ids 1 and 2, as PX4 SITL's -i gives) send their API links to the
same client port on 127.0.0.1, real UDP.
"""

from __future__ import annotations

import time

import pytest

from uavsearch.flight.commander import PX4_MODES

from uavsearch.fly.connection import MavlinkConnection
from uavsearch.fly.vehicle import MavlinkVehicle
from uavsearch.flight.sitl_process import SitlProcess
from uavsearch.testing.clean_env import clean_env


def _two_vehicles(tmp_path, port: int) -> list[SitlProcess]:
    return [SitlProcess(tmp_path / f"v{sysid}", "--param", f"MAV_SYS_ID={sysid}", api_port=port, gcs_port=0,
                        speed="1", camera=False, env=clean_env()) for sysid in (1, 2)]


@pytest.fixture
def link(tmp_path):
    conn = MavlinkConnection("udpin:127.0.0.1:0")
    vehicles = _two_vehicles(tmp_path, conn.port.getsockname()[1])
    yield conn
    conn.close()
    for v in vehicles:
        v.stop()


def test_each_system_sees_only_its_own_frames(link):
    one, two = link.wait_system(1, 20), link.wait_system(2, 20)
    assert one is not None and two is not None and one is not two
    assert [s.sysid for s in link.systems() if s.is_autopilot] == [1, 2]
    strays = []
    for s in (one, two):
        for t in ("HEARTBEAT", "GLOBAL_POSITION_INT", "SYS_STATUS", "COMMAND_ACK", "PARAM_VALUE"):
            s.subscribe(t, lambda m, s=s: strays.append((s.sysid, m.get_srcSystem())) if m.get_srcSystem() != s.sysid
                        else None)
    assert one.params.get("MAV_SYS_ID") == 1 and two.params.get("MAV_SYS_ID") == 2
    assert type(two.params.get("MAV_SYS_ID")) is int and type(two.params.get("MPC_XY_CRUISE")) is float
    assert str(one.telemetry.mode()) in ("HOLD", "LAND", "TAKEOFF", "POSCTL") and one.telemetry.mode() == (
        PX4_MODES[str(one.telemetry.mode())])  # readable, and still the (main, sub) tuple
    assert two.params.set_float("MPC_XY_CRUISE", 7.0)  # a change on system 2 only
    assert two.params.get("MPC_XY_CRUISE") == pytest.approx(7.0)
    assert one.params.get("MPC_XY_CRUISE") == pytest.approx(5.0)
    end = time.monotonic() + 3.0
    while time.monotonic() < end:  # both keep heartbeating and streaming
        link.pump(0.1)
    assert one.telemetry.global_position is not None and two.telemetry.global_position is not None
    assert strays == []


def test_the_vehicle_keeps_the_first_autopilot_while_another_heartbeats(tmp_path):
    """The facade flies one System: with a second vehicle on the link, every answer comes from the first."""
    v = MavlinkVehicle("udpin:127.0.0.1:0")
    vehicles = _two_vehicles(tmp_path, v.conn.port.getsockname()[1])
    try:
        v.connect()
        first = v.read_param("MAV_SYS_ID")
        assert first in (1.0, 2.0)
        seen = set()
        end = time.monotonic() + 4.0
        while time.monotonic() < end:  # heartbeats of both arrive all the while
            seen.add(v.read_param("MAV_SYS_ID"))
        assert seen == {first}
    finally:
        v.close()
        for p in vehicles:
            p.stop()


def test_a_named_system_is_the_one_flown(tmp_path):
    v = MavlinkVehicle("udpin:127.0.0.1:0", system_id=2)
    vehicles = _two_vehicles(tmp_path, v.conn.port.getsockname()[1])
    try:
        v.connect()
        assert v.system.sysid == 2 and v.read_param("MAV_SYS_ID") == 2.0
    finally:
        v.close()
        for p in vehicles:
            p.stop()
