"""The real vehicle (JSBSim + sensors + EKF + control) flown in simulated time; bounds set from measurements.

Measured with `mission_profile(seed, alt_m=15, hover_s=10, move_window_s=12)` for seeds 0-3 (the same
code as tools/flight_step_response.py): estimate-based 10 m move settle 4.6-6.6 s, overshoot 0.08-0.28 m;
climb to 90 % in 5.0-5.2 s; touchdown 0.71-0.75 m/s; EKF horizontal error RMS 0.28-0.38 m, max
0.57-1.08 m. The bounds leave margin for other seeds but catch a broken loop.
"""

import math

import numpy as np
import pytest

from uavsearch.errors import UavsearchError
from uavsearch.flight.fdm import QUADX, QuadFdm
from uavsearch.flight.messages import TrajectorySetpoint
from uavsearch.flight.multicopter import MC_PARAMS, Multicopter
from uavsearch.flight.params import ParamStore
from uavsearch.flight.step_response import Flight, mission_profile
from uavsearch.geometry import GeodeticOrigin

NAN = math.nan


def _airborne_fdm(hz: int = 100) -> QuadFdm:
    return QuadFdm(GeodeticOrigin(), hz, start_enu=(0.0, 0.0, 50.0))


def test_airframe_matches_its_declared_constants():
    """The XML and AirframeInfo agree: thrust/weight, motor lag, yaw moment, roll sign."""
    af = QUADX
    fdm = _airborne_fdm()
    fdm.set_motor_commands([1.0] * 4)
    steps = 0
    while fdm.rotor_thrusts_n()[0] < 0.63 * af.rotor_thrust_max_n:
        fdm.step()
        steps += 1
    assert 0.03 <= steps * fdm.dt <= 0.06  # first-order lag, tau 0.04 s (+ one step of the FCS)
    for _ in range(50):
        fdm.step()
    thrust_n = -fdm.specific_force_frd_m_s2()[2] * fdm.mass_kg
    assert thrust_n / (fdm.mass_kg * fdm.gravity_m_s2) == pytest.approx(2.0, rel=0.05)  # thrust/weight ~2
    fdm = _airborne_fdm()
    fdm.set_motor_commands([0.6, 0.6, 0.4, 0.4])  # CCW rotors harder: yaw right
    for _ in range(50):
        fdm.step()
    torque = af.yaw_moment_per_thrust_m * 2 * 0.2 * af.rotor_thrust_max_n
    expected_r = torque / af.inertia_kg_m2[2] * (0.5 - 0.04)  # lag costs about one time constant
    assert fdm.body_rates_rad_s()[2] == pytest.approx(expected_r, rel=0.1)
    fdm = _airborne_fdm()
    fdm.set_motor_commands([0.45, 0.55, 0.55, 0.45])  # left rotors harder: roll right
    for _ in range(10):
        fdm.step()
    p, q, r = fdm.body_rates_rad_s()
    assert p > 0.1 and abs(q) < 1e-3 and abs(r) < 1e-3


@pytest.mark.parametrize("hz", [100, 200])
def test_contacts_are_stable_at_the_physics_rate(hz):
    """Dropped unpowered from 1 m (about 4 m/s at impact): no bounce, no tip-over, comes to rest on its feet."""
    fdm = QuadFdm(GeodeticOrigin(), hz, start_enu=(0.0, 0.0, 1.0))
    z = []
    for _ in range(3 * hz):
        fdm.step()
        z.append(fdm.position_enu_m()[2])
    z = np.array(z)
    impact = int(np.argmax(z < 0.13))
    rest = z[-hz // 2 :]
    assert rest.std() < 1e-5 and 0.10 < rest.mean() < 0.13
    assert z[impact:].max() - rest.mean() < 0.02  # rebound under 2 cm
    assert np.abs(fdm.euler_rad()[:2]).max() < 1e-3
    assert np.linalg.norm(fdm.velocity_ned_m_s()) < 1e-3


def test_a_fall_is_a_crash_and_the_wreck_stays_at_rest():
    """Dropped unpowered from 30 m (about 24 m/s at impact): a crash, held as a wreck on the ground where it hit,
    every reading finite and at rest from then on (JSBSim's contacts alone diverge at such an impact)."""
    hz = 100
    fdm = QuadFdm(GeodeticOrigin(), hz, start_enu=(3.0, -2.0, 30.0))
    hit = None
    for k in range(12 * hz):
        fdm.step()
        if fdm.crashed and hit is None:
            hit = k
    assert hit is not None and 2 * hz < hit < 3 * hz  # sqrt(2 * 30 / g) = 2.5 s
    e, n, u = fdm.position_enu_m()
    assert u == 0.0 and abs(e - 3.0) < 0.5 and abs(n + 2.0) < 0.5
    assert fdm.velocity_ned_m_s() == (0.0, 0.0, 0.0) and fdm.body_rates_rad_s() == (0.0, 0.0, 0.0)
    assert fdm.specific_force_frd_m_s2()[2] == pytest.approx(-fdm.gravity_m_s2)
    assert fdm.rotor_thrusts_n() == [0.0] * 4 and fdm.ground_force_n() > 0.0


def test_imu_readings_saturate_at_the_parts_full_scale():
    from uavsearch.flight.sensors import ACCEL_RANGE_M_S2, GYRO_RANGE_RAD_S, SensorSuite

    params = ParamStore(MC_PARAMS)
    sens = SensorSuite(params, GeodeticOrigin(), np.random.default_rng(0))
    imu = sens.imu((1e6, -1e6, 0.1), (-1e9, 0.0, 1e9), 0.004)
    assert imu.gyro_frd_rad_s[:2] == (GYRO_RANGE_RAD_S, -GYRO_RANGE_RAD_S) and abs(imu.gyro_frd_rad_s[2]) < 1.0
    assert imu.accel_frd_m_s2[0] == -ACCEL_RANGE_M_S2 and imu.accel_frd_m_s2[2] == ACCEL_RANGE_M_S2


@pytest.fixture(scope="module")
def profile():
    res, flight = mission_profile(seed=0, alt_m=15.0, hover_s=10.0, move_window_s=12.0)
    return res, flight


def test_climb_is_fast_and_does_not_overshoot(profile):
    res, _ = profile
    assert 4.0 < res["climb_time_to_90pct_s"] < 7.0  # 13.5 m at MPC_Z_VEL_MAX_UP = 3 m/s
    assert res["climb_overshoot_m"] < 0.5


def test_ten_metre_moves_settle_within_seconds(profile):
    res, _ = profile
    assert all(t < 8.0 for t in res["move_settle_est_s"]), res["move_settle_est_s"]
    assert all(o < 0.5 for o in res["move_overshoot_est_m"]), res["move_overshoot_est_m"]
    assert all(o < 1.5 for o in res["move_overshoot_m"]), res["move_overshoot_m"]  # truth: + GPS error


def test_hover_hold_and_estimation_error(profile):
    res, _ = profile
    assert res["hover_err_h_rms_m"] < 0.8
    assert res["hover_err_h_rms_est_m"] < 0.3  # the controller alone, against its own estimate
    assert res["hover_err_v_rms_m"] < 0.5
    assert res["ekf_pos_err_h_rms_m"] < 0.6
    assert res["ekf_pos_err_h_max_m"] < 1.5
    assert res["ekf_pos_err_v_rms_m"] < 0.5
    assert res["ekf_vel_err_rms_m_s"] < 0.2
    assert res["ekf_tilt_err_rms_deg"] < 2.0
    assert res["ekf_yaw_err_rms_deg"] < 3.0


def test_landing_is_gentle_and_detected(profile):
    res, flight = profile
    assert res["touchdown_speed_m_s"] < 1.0
    assert res["land_detect_s"] < 15.0
    v = flight.vehicle
    assert v.land_detected.landed and not v.flying
    assert v.true_state.position_enu_m[2] < 0.2  # on its feet
    assert v.motor_outputs == pytest.approx([0.05] * 4)  # armed on the ground: idle
    assert 0.0 < v.battery.remaining < 1.0 and v.battery.discharged_mah > 100.0


def test_telemetry_is_the_estimate_not_the_truth(profile):
    _, flight = profile
    a = flight.trace.arrays()
    diff = np.abs(a["est_pos"] - a["true_pos"])
    assert diff.max() > 0.05  # noisy sensors: not a copy of the truth
    v = flight.vehicle
    gp = v.global_position
    back = v.home.geodetic_to_enu([gp.lat_deg, gp.lon_deg, gp.alt_amsl_m])
    lp = v.local_position.position_ned_m
    assert back == pytest.approx([lp[1], lp[0], -lp[2]], abs=1e-6)


def _short_flight(seed: int) -> np.ndarray:
    f = Flight(seed=seed)
    f.vehicle.arm()
    f.goto(3.0, -2.0, -5.0)
    f.run(6.0)
    return f.trace.arrays()["true_pos"]


def test_same_seed_same_trajectory_different_seed_differs():
    a, b, c = _short_flight(7), _short_flight(7), _short_flight(8)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_sits_on_its_contacts_until_asked_to_climb():
    v = Multicopter(ParamStore(MC_PARAMS), GeodeticOrigin(), seed=0)
    v.run_for(2.0)
    z0 = v.true_state.position_enu_m[2]
    assert 0.05 < z0 < 0.2 and v.land_detected.landed
    v.arm()
    v.set_setpoint(TrajectorySetpoint(v.time_us, np.array([NAN, NAN, NAN]), np.array([0.0, 0.0, 0.5])))
    v.run_for(2.0)
    assert not v.flying and abs(v.true_state.position_enu_m[2] - z0) < 0.01
    assert np.linalg.norm(v.true_state.velocity_enu_m_s) < 0.01
    v.disarm()
    assert v.motor_outputs == (0.0, 0.0, 0.0, 0.0)


def test_param_change_takes_effect_in_flight():
    f = Flight(seed=1)
    v = f.vehicle
    v.arm()
    f.goto(0.0, 0.0, -10.0)
    f.run(8.0)
    f.params.set("MPC_XY_CRUISE", 1.5)  # as a PARAM_SET would
    i0 = len(f.trace.t)
    f.goto(20.0, 0.0, -10.0)
    f.run(8.0)
    vn = f.trace.arrays()["true_vel"][i0:, 0]
    assert 1.2 < vn.max() < 2.0
    f.params.set("MPC_XY_CRUISE", 5.0)
    i0 = len(f.trace.t)
    f.goto(0.0, 0.0, -10.0)
    f.run(8.0)
    assert f.trace.arrays()["true_vel"][i0:, 0].min() < -3.0


def test_wind_is_held_against_and_gps_loss_is_reported():
    f = Flight(seed=2, params={"SIM_WIND_N": 6.0})
    v = f.vehicle
    v.arm()
    f.goto(0.0, 0.0, -10.0)
    f.run(15.0)
    ts = v.true_state
    assert 5.0 < math.degrees(ts.pitch_rad) < 12.0  # leaning into the wind (nose up, thrust to the south)
    assert np.hypot(*ts.position_enu_m[:2]) < 1.5
    f.params.set("SIM_GPS_BLOCK", 1)
    f.run(1.5)
    assert not v.sensor_health.gps and v.gps_fix.fix_type == 0
    f.params.set("SIM_GPS_BLOCK", 0)
    f.run(0.5)
    assert v.sensor_health.gps and v.gps_fix.fix_type == 3


def test_heading_reversal_during_a_move_keeps_the_tilt_limit():
    f = Flight(seed=0)
    v = f.vehicle
    v.arm()
    f.goto(0.0, 0.0, -20.0, yaw=0.0)
    f.run(10.0)
    f.goto(30.0, 0.0, -20.0, yaw=math.pi - 0.001)
    tilt = []
    for _ in range(150):
        f.run(0.1)
        ts = v.true_state
        tilt.append(math.degrees(math.acos(math.cos(ts.roll_rad) * math.cos(ts.pitch_rad))))
    assert max(tilt) < v.params["MPC_TILTMAX_AIR"]
    assert abs(math.degrees(v.true_state.yaw_rad)) > 178.0
    assert np.hypot(v.true_state.position_enu_m[1] - 30.0, v.true_state.position_enu_m[0]) < 1.5


def test_bad_construction_is_a_clear_error():
    with pytest.raises(UavsearchError, match="does not divide"):
        Multicopter(ParamStore(MC_PARAMS), GeodeticOrigin(), seed=0, physics_hz=200, ctrl_hz=30)
    with pytest.raises(UavsearchError, match="MC_PARAMS"):
        Multicopter(ParamStore([]), GeodeticOrigin(), seed=0)
    v = Multicopter(ParamStore(MC_PARAMS), GeodeticOrigin(), seed=0)
    with pytest.raises(UavsearchError):
        v.set_setpoint(TrajectorySetpoint(0, np.array([math.inf, 0.0, 0.0])))


@pytest.mark.slow
def test_full_mission_profile_at_70_m():
    res, _ = mission_profile(seed=0)
    assert res["climb_time_to_90pct_s"] < 25.0 and res["climb_overshoot_m"] < 0.5
    assert all(t < 8.0 for t in res["move_settle_est_s"])
    assert res["ekf_pos_err_h_rms_m"] < 0.8
