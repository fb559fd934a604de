"""Mode logic of the commander and navigator, on a kinematic stand-in (no JSBSim, no MAVLink).

The MAVLink and MAVSDK tests fly the same logic on the real JSBSim vehicle; these check the state
machine's decisions quickly and exactly.
"""

import math

import numpy as np
import pytest

from kinematic_vehicle import KinematicVehicle
from uavsearch.flight.commander import Commander, Result, VehicleCommand, autopilot_params
from uavsearch.flight.messages import SensorHealth, TrajectorySetpoint
from uavsearch.flight.mission import MissionItem
from uavsearch.flight.params import ParamStore
from uavsearch.geometry import GeodeticOrigin

NAN = math.nan
ORIGIN = GeodeticOrigin()


class Rig:
    """Commander + stand-in vehicle advanced together; `wall` is a fake wall clock in seconds."""

    def __init__(self, **params):
        self.params = ParamStore(autopilot_params())
        for k, v in params.items():
            self.params.set(k, v)
        self.v = KinematicVehicle(self.params, ORIGIN, physics_hz=100)
        self.c = Commander(self.params, self.v, ORIGIN, autopilot_hz=50)
        self.wall = 0.0
        self.wall_rate = 1.0  # wall seconds per simulated second

    def run(self, seconds: float, until=None) -> bool:
        for _ in range(int(round(seconds * 50))):
            self.c.update(self.wall)
            self.v.step()
            self.v.step()
            self.wall += 0.02 * self.wall_rate
            if until is not None and until():
                return True
        return until is None

    def cmd(self, command, *p, frame=0) -> Result:
        p = list(p) + [NAN] * (7 - len(p))
        return self.c.handle_command(VehicleCommand(command, *p, frame=frame))

    @property
    def alt(self) -> float:
        return -self.v.p[2]

    def texts(self) -> list[str]:
        t = [x.text for x in self.c.texts]
        self.c.texts.clear()
        return t

    def takeoff(self, alt=None):
        self.run(0.5)
        assert self.cmd(400, 1) == Result.ACCEPTED
        assert self.cmd(22, *([NAN] * 6 + ([NAN] if alt is None else [ORIGIN.alt_m + alt]))) == Result.ACCEPTED
        assert self.run(30, until=lambda: self.c.mode == "HOLD")


def latlon(north_m, east_m):
    lla = ORIGIN.enu_to_geodetic([east_m, north_m, 0.0])
    return float(lla[0]), float(lla[1])


def test_takeoff_uses_mis_takeoff_alt_then_holds():
    r = Rig(MIS_TAKEOFF_ALT=4.0)
    r.takeoff()
    assert r.c.mode == "HOLD" and r.c.armed
    r.run(3)
    assert r.alt == pytest.approx(4.0, abs=0.3)


def test_takeoff_below_min_altitude_is_raised():
    r = Rig(MIS_TAKEOFF_ALT=5.0)
    r.takeoff(alt=2.0)
    r.run(3)
    assert r.alt == pytest.approx(5.0, abs=0.3)


def test_arming_refused_when_unhealthy_and_unknown_command_unsupported():
    r = Rig()
    r.run(0.5)
    r.v.sensor_health = SensorHealth(gps=False)
    assert r.cmd(400, 1) == Result.DENIED
    assert any("gps" in t for t in r.texts())
    assert not r.c.armed
    assert r.cmd(31337) == Result.UNSUPPORTED
    assert r.cmd(22) == Result.DENIED  # takeoff while disarmed
    r.v.sensor_health = SensorHealth()
    assert r.cmd(400, 1) == Result.ACCEPTED


def test_disarm_in_air_denied_unless_forced():
    r = Rig()
    r.takeoff()
    assert r.cmd(400, 0) == Result.DENIED and r.c.armed
    assert r.cmd(400, 0, 21196) == Result.ACCEPTED and not r.c.armed


def test_reposition_then_land_and_auto_disarm():
    r = Rig(MIS_TAKEOFF_ALT=5.0)
    r.takeoff()
    lat, lon = latlon(10.0, -5.0)
    assert r.cmd(192, -1, 1, 0, NAN, lat, lon, ORIGIN.alt_m + 8.0) == Result.ACCEPTED
    assert r.c.mode == "HOLD"
    assert r.run(30, until=lambda: np.allclose(r.v.p, [10.0, -5.0, -8.0], atol=0.2))
    assert r.cmd(21) == Result.ACCEPTED and r.c.mode == "LAND"
    assert r.run(40, until=lambda: not r.c.armed)
    assert r.alt < 0.05 and np.allclose(r.v.p[:2], [10.0, -5.0], atol=1.0)  # lands where it stops
    assert r.c.mode == "HOLD"  # back to a mode that can arm again


def test_geofence_refuses_goto_and_breach_triggers_gf_action():
    r = Rig(GF_MAX_HOR_DIST=30.0, GF_ACTION=3, RTL_RETURN_ALT=5.0, RTL_DESCEND_ALT=3.0)
    r.takeoff()
    lat, lon = latlon(40.0, 0.0)
    assert r.cmd(192, -1, 1, 0, NAN, lat, lon, ORIGIN.alt_m + 5.0) == Result.DENIED
    assert any("geofence" in t for t in r.texts())
    # Fly out in offboard (which the fence cannot refuse in advance): the breach sends it home.
    r.c.set_offboard_setpoint(TrajectorySetpoint(0, np.array([45.0, 0.0, -5.0])))
    assert r.cmd(176, 1, 6, 0) == Result.ACCEPTED
    for _ in range(400):
        r.c.set_offboard_setpoint(TrajectorySetpoint(0, np.array([45.0, 0.0, -5.0])))
        r.run(0.1)
        if r.c.mode != "OFFBOARD":
            break
    assert r.c.mode == "RTL"
    assert 29.0 < r.v.p[0] < 34.0


def test_mission_refused_outside_fence():
    r = Rig(GF_MAX_HOR_DIST=50.0)
    lat, lon = latlon(80.0, 0.0)
    items = [MissionItem(0, 6, 16, x=int(lat * 1e7), y=int(lon * 1e7), z=10.0)]
    result, reason = r.c.upload_mission(items)
    assert result != 0 and "geofence" in reason
    assert len(r.c.mission) == 0


def test_datalink_loss_triggers_nav_dll_act_in_wall_and_sim_time():
    r = Rig(COM_DL_LOSS_T=2.0, NAV_DLL_ACT=2, RTL_RETURN_ALT=4.0)
    r.takeoff()
    r.c.on_gcs_heartbeat()
    # At 50x real time, 10 simulated seconds are 0.2 wall seconds: not a loss yet.
    r.wall_rate = 0.02
    r.run(10)
    assert r.c.mode == "HOLD"
    r.wall_rate = 1.0
    r.run(2.5)
    assert r.c.mode == "RTL"
    assert any("Data link lost" in t for t in r.texts())


def test_offboard_needs_setpoints_and_falls_back_to_hold():
    r = Rig(COM_OF_LOSS_T=0.5)
    r.takeoff()
    assert r.cmd(176, 1, 6, 0) == Result.DENIED
    for _ in range(10):
        r.c.set_offboard_setpoint(TrajectorySetpoint(0, np.full(3, NAN), np.array([1.0, 0.0, 0.0])))
        r.run(0.1)
        if r.c.mode != "OFFBOARD":
            assert r.cmd(176, 1, 6, 0) == Result.ACCEPTED
    assert r.c.mode == "OFFBOARD" and r.v.v[0] > 0.5
    r.run(1.0)
    assert r.c.mode == "HOLD"


def test_mission_items_speed_camera_loiter_and_rtl_reported_in_order():
    r = Rig(MIS_TAKEOFF_ALT=3.0, RTL_RETURN_ALT=6.0, RTL_DESCEND_ALT=4.0)
    r.run(0.5)
    wp = []
    for n in (0.0, 8.0):
        lat, lon = latlon(n, 0.0)
        wp.append((int(lat * 1e7), int(lon * 1e7)))
    items = [
        MissionItem(0, 3, 22, z=6.0),
        MissionItem(1, 2, 178, param1=1, param2=2.0),  # DO_CHANGE_SPEED 2 m/s
        MissionItem(2, 6, 16, x=wp[1][0], y=wp[1][1], z=6.0),
        MissionItem(3, 2, 2000, param3=1),  # IMAGE_START_CAPTURE
        MissionItem(4, 6, 19, param1=2.0, x=wp[0][0], y=wp[0][1], z=6.0),  # loiter 2 s
        MissionItem(5, 2, 20),
    ]
    assert r.c.upload_mission(items)[0] == 0
    assert r.cmd(400, 1) == Result.ACCEPTED
    assert r.cmd(176, 1, 4, 4) == Result.ACCEPTED
    speeds = []
    ok = r.run(120, until=lambda: (speeds.append(np.hypot(*r.v.v[:2])) or False) or not r.c.armed)
    assert ok
    reached = [s for k, s in r.c.mission_events if k == "reached"]
    assert reached == [0, 1, 2, 3, 4, 5]
    assert len(r.c.captures) == 1
    assert max(speeds) < 3.0  # DO_CHANGE_SPEED (2 m/s) held it well below MPC_XY_CRUISE (5 m/s)
    assert np.hypot(*r.v.p[:2]) < 0.5  # landed at home after the RTL item


def test_battery_critical_returns():
    r = Rig(RTL_RETURN_ALT=4.0)
    r.takeoff()
    r.v.remaining = 0.06
    r.run(0.1)
    assert r.c.mode == "RTL"


def test_armed_without_takeoff_disarms_after_com_disarm_prflt_in_both_clocks():
    r = Rig(COM_DISARM_PRFLT=3.0)
    r.run(0.5)
    assert r.cmd(400, 1) == Result.ACCEPTED
    r.wall_rate = 0.02  # 50x real time: 5 simulated seconds are only 0.1 s for the operator
    r.run(5.0)
    assert r.c.armed
    r.wall_rate = 1.0
    assert r.run(4.0, until=lambda: not r.c.armed)
    assert any("no takeoff" in t for t in r.texts())


def test_gps_loss_in_flight_lands():
    r = Rig()
    r.takeoff()
    r.v.sensor_health = SensorHealth(gps=False)
    r.run(0.2)
    assert r.c.mode == "LAND"
    assert any("GPS lost" in t for t in r.texts())
    assert r.run(30, until=lambda: not r.c.armed)


def test_takeoff_in_air_never_descends_and_rtl_on_ground_is_denied():
    r = Rig(MIS_TAKEOFF_ALT=3.0)
    r.run(0.5)
    assert r.cmd(400, 1) == Result.ACCEPTED
    assert r.cmd(20) == Result.DENIED  # return to launch from the ground
    assert r.cmd(22, *[NAN] * 6, ORIGIN.alt_m + 8.0) == Result.ACCEPTED
    assert r.run(30, until=lambda: r.c.mode == "HOLD")
    r.run(3)
    assert r.cmd(22) == Result.ACCEPTED  # NaN altitude: MIS_TAKEOFF_ALT (3 m) is below us
    r.run(5)
    assert r.alt == pytest.approx(8.0, abs=0.4)


def test_land_slows_gradually_from_land_alt1_to_land_alt2_as_px4_does():
    """LAND descends at MPC_Z_V_AUTO_DN above MPC_LAND_ALT1 (10 m), at MPC_LAND_SPEED (0.7 m/s) below
    MPC_LAND_ALT2 (5 m), and at a speed linear in altitude in between."""
    r = Rig(MIS_TAKEOFF_ALT=15.0)
    r.takeoff()
    assert r.cmd(21) == Result.ACCEPTED and r.c.mode == "LAND"
    seen = []

    def record():
        if r.v.sp is not None and r.c.mode == "LAND":
            seen.append((r.alt, float(r.v.sp.velocity_ned_m_s[2])))
        return not r.c.armed

    assert r.run(80, until=record)
    fast = max(vz for _, vz in seen)
    assert fast > 1.0 and sum(5.2 < alt < 9.8 for alt, _ in seen) > 50
    for alt, vz in seen:
        if alt > 10.2:
            assert vz == pytest.approx(fast)
        elif 5.2 < alt < 9.8:
            assert vz == pytest.approx(0.7 + (fast - 0.7) * (alt - 5.0) / 5.0, abs=0.05)
        elif 0.5 < alt < 4.8:
            assert vz == pytest.approx(0.7)


def test_do_land_start_jumps_to_the_landing_sequence_or_lands_here():
    """MAVProxy's `land` is MAV_CMD_DO_LAND_START: with a DO_LAND_START marker the mission continues from it
    (PX4); without one the vehicle lands where it is (PX4 only warns)."""
    r = Rig(MIS_TAKEOFF_ALT=4.0)
    r.takeoff()
    lat, lon = latlon(6.0, 0.0)
    items = [MissionItem(0, 6, 16, x=int(lat * 1e7), y=int(lon * 1e7), z=4.0),
             MissionItem(1, 2, 189),  # DO_LAND_START
             MissionItem(2, 6, 21, x=int(lat * 1e7), y=int(lon * 1e7), z=0.0)]
    assert r.c.upload_mission(items)[0] == 0
    assert r.cmd(189) == Result.ACCEPTED
    assert r.c.mode == "MISSION" and r.c.mission.current_seq == 1
    assert r.run(60, until=lambda: not r.c.armed)
    assert np.hypot(r.v.p[0] - 6.0, r.v.p[1]) < 0.6  # landed at the sequence's NAV_LAND, not where it was
    r2 = Rig(MIS_TAKEOFF_ALT=4.0)
    r2.takeoff()
    r2.texts()
    assert r2.cmd(189) == Result.ACCEPTED and r2.c.mode == "LAND"
    assert "No mission landing sequence: landing here" in r2.texts()
    assert r2.cmd(189) == Result.ACCEPTED  # repeated: still landing
