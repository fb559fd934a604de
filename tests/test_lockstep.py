"""Lockstep (MAV_CMD_SIM_ADVANCE) against a real `uavsearch sitl --lockstep` process over loopback UDP:
the clock moves only as far as the client grants, grants are exact and idempotent, and a free-running
vehicle refuses the command."""

import time

import pytest
from pymavlink import mavutil

from uavsearch.testing.mavlink_client import Client
from uavsearch.flight.lockstep import MAV_CMD_SIM_ADVANCE
from uavsearch.flight.sitl_process import SitlProcess
from uavsearch.testing.clean_env import clean_env

M = mavutil.mavlink


def _grant(c: Client, until_ms: int, timeout: float = 5.0):
    c.mav.command_int_send(c.sysid, 1, M.MAV_FRAME_MISSION, MAV_CMD_SIM_ADVANCE, 0, 0, 0, 0, 0, 0,
                           until_ms, 0, 0.0)
    return c.recv("COMMAND_ACK", timeout, cond=lambda m: m.command == MAV_CMD_SIM_ADVANCE)


def _drain(c: Client, seconds: float) -> list:
    """Every message that arrives within `seconds` of wall time."""
    out, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        m = c.recv(None, 0.05)
        if m is not None:
            out.append(m)
    return out


@pytest.fixture
def lockstep(tmp_path):
    p = SitlProcess(tmp_path, lockstep=True, gcs_port=0, camera=False, env=clean_env())
    assert "lockstep" in "".join(p.banner)
    c = Client(p.api_port)  # the vehicle heartbeats while it waits for its first grant
    yield c
    c.close()
    code, out = p.stop()
    assert code == 0, out  # Ctrl-C stops a vehicle that is standing still


def test_the_clock_runs_exactly_as_far_as_granted(lockstep):
    c = lockstep
    ack = _grant(c, 0)  # a barrier: answered at once, at time 0
    assert ack.result == M.MAV_RESULT_ACCEPTED and ack.result_param2 == 0
    # Nothing moves without a grant: half a wall second, no telemetry time beyond 0.
    stamps = [m.time_boot_ms for m in _drain(c, 0.5) if hasattr(m, "time_boot_ms")]
    assert all(t == 0 for t in stamps)
    ack = _grant(c, 1500)
    assert ack.result == M.MAV_RESULT_ACCEPTED and ack.result_param2 == 1500
    # Every stamped message the grant caused arrived before its ACK, and none is later than the grant.
    late = [m for m in _drain(c, 0.3) if getattr(m, "time_boot_ms", 0) > 1500]
    assert not late
    # The same grant again (a retransmission) and an earlier one cost no simulation time.
    assert _grant(c, 1500).result_param2 == 1500
    assert _grant(c, 700).result_param2 == 1500
    assert _grant(c, 1510).result_param2 == 1510


def test_telemetry_stamps_follow_the_grants(lockstep):
    c = lockstep
    _grant(c, 0)
    _drain(c, 0.2)
    seen = []
    for until in (200, 400, 600):
        c.mav.command_int_send(c.sysid, 1, M.MAV_FRAME_MISSION, MAV_CMD_SIM_ADVANCE, 0, 0, 0, 0, 0, 0,
                               until, 0, 0.0)
        while True:  # everything up to the ACK belongs to this grant
            m = c.recv(None, 5)
            assert m is not None
            if m.get_type() == "COMMAND_ACK" and m.command == MAV_CMD_SIM_ADVANCE:
                assert m.result_param2 == until
                break
            if m.get_type() == "GLOBAL_POSITION_INT":
                seen.append((until, m.time_boot_ms))
    assert seen and all(until - 200 <= t < until for until, t in seen)


def test_commands_are_handled_while_the_clock_stands_still(lockstep):
    c = lockstep
    _grant(c, 0)
    ack = c.command(M.MAV_CMD_SET_MESSAGE_INTERVAL, M.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 50_000)
    assert ack is not None and ack.result == M.MAV_RESULT_ACCEPTED
    assert _grant(c, 0).result_param2 == 0  # answering took no simulation time


def test_bad_grants_are_denied(lockstep):
    assert _grant(lockstep, -5).result == M.MAV_RESULT_DENIED


def test_a_free_running_vehicle_refuses_grants(tmp_path):
    p = SitlProcess(tmp_path, gcs_port=0, camera=False, env=clean_env())
    c = Client(p.api_port)
    try:
        assert _grant(c, 10_000).result == M.MAV_RESULT_UNSUPPORTED
    finally:
        c.close()
        assert p.stop()[0] == 0


def _fly_a_leg(tmp_path, one_tick_per_grant: bool, monkeypatch) -> tuple[list, int]:
    """Take off, fly to (20, 22) at 40 m and back to (-5, 0), as the mission controller does; when the take-off
    ended and both legs settled, where it reported itself then, and the number of grants."""
    import numpy as np

    from uavsearch.fly import vehicle as vehicle_module
    from uavsearch.fly.lockstep import Lockstep
    from uavsearch.fly.vehicle import FlightSettings, MavlinkVehicle

    if one_tick_per_grant:
        monkeypatch.setattr(vehicle_module, "ticks_until", lambda system, tick_s, earliest_s: tick_s)
    grants = []
    real = Lockstep.grant
    monkeypatch.setattr(Lockstep, "grant", lambda self, until_ms: grants.append(until_ms) or real(self, until_ms))
    v = MavlinkVehicle("udpin:127.0.0.1:0", settings=FlightSettings(lockstep=True))
    p = SitlProcess(tmp_path, lockstep=True, gcs_port=0, camera=False, api_port=v.conn.port.getsockname()[1],
                    env=clean_env())
    try:
        v.connect()
        n0 = len(grants)
        v.take_off()
        legs = [(round(v.sim_time_s, 3), np.round(v.position_enu(), 4).tolist())]
        for target in ([20.0, 22.0, 40.0], [-5.0, 0.0, 40.0]):
            v.begin_goto(np.array(target))
            took = v.wait_arrived()
            legs.append((round(took, 3), round(v.sim_time_s, 3), np.round(v.position_enu(), 4).tolist()))
        return legs, len(grants) - n0
    finally:
        v.close()
        p.stop()


def test_a_goto_is_granted_the_ticks_it_cannot_settle_in_at_once_and_flies_the_same(tmp_path, monkeypatch):
    """While a take-off cannot be up or a goto cannot have settled (too far, at any speed the autopilot allows),
    the client grants those ticks in one: the end is judged at the same tick, the flight is the same, and the
    round trips are a fraction."""
    chunked, n_chunked = _fly_a_leg(tmp_path / "chunked", False, monkeypatch)
    monkeypatch.undo()
    ticked, n_ticked = _fly_a_leg(tmp_path / "ticked", True, monkeypatch)
    assert chunked == ticked, (chunked, ticked)
    assert n_chunked < n_ticked / 3
