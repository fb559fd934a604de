"""Controller cores, mixer, EKF, battery and land detector alone: no JSBSim, no MAVLink."""

import math

import numpy as np
import pytest

from uavsearch.errors import UavsearchError
from uavsearch.flight.battery import Battery
from uavsearch.flight.control import (
    AttitudeControl,
    PositionControl,
    QuadXMixer,
    RateControl,
    attitude_from_thrust,
)
from uavsearch.flight.estimator import NavigationEkf
from uavsearch.flight.quaternion import quat_to_euler, quat_to_matrix
from uavsearch.flight.fdm import QUADX
from uavsearch.flight.land_detector import LandDetector
from uavsearch.flight.multicopter import MC_PARAMS, _check_rates
from uavsearch.flight.params import ParamStore
from uavsearch.geometry import quaternion_from_euler

NAN = math.nan
G = 9.81


@pytest.fixture
def params():
    return ParamStore(MC_PARAMS)


def _pos_ctrl(params):
    pc = PositionControl(G)
    pc.configure(params)
    return pc


def test_hover_at_setpoint_gives_hover_thrust_and_level_attitude(params):
    pc = _pos_ctrl(params)
    pc.set_state((1.0, 2.0, -10.0), (0.0, 0.0, 0.0), 0.3)
    pc.set_setpoint((1.0, 2.0, -10.0), (NAN,) * 3, (NAN,) * 3, 0.3, NAN)
    sp = pc.update(0.02)
    assert sp.thrust == pytest.approx(params["MPC_THR_HOVER"], abs=1e-9)
    roll, pitch, yaw = quat_to_euler(sp.q_d)
    assert abs(roll) < 1e-9 and abs(pitch) < 1e-9 and yaw == pytest.approx(0.3)


def test_velocity_setpoint_respects_cruise_speed_and_acceleration(params):
    params.set("MPC_XY_CRUISE", 4.0)
    pc = _pos_ctrl(params)
    pc.set_state((0.0, 0.0, -10.0), (0.0, 0.0, 0.0), 0.0)
    pc.set_setpoint((100.0, 0.0, -10.0), (NAN,) * 3, (NAN,) * 3, 0.0, NAN)
    dt, prev = 0.02, 0.0
    for _ in range(300):
        pc.update(dt)
        vn = pc.v_sp[0]
        assert vn - prev <= params["MPC_ACC_HOR"] * dt + 1e-9  # slew-limited
        prev = vn
    assert prev == pytest.approx(4.0, abs=1e-6)  # capped by the cruise speed
    pc.cruise_override_m_s = 2.0  # DO_CHANGE_SPEED
    for _ in range(200):
        pc.update(dt)
    assert pc.v_sp[0] == pytest.approx(2.0, abs=1e-6)


def test_tilt_limit_holds_for_huge_velocity_error(params):
    params.set("MPC_TILTMAX_AIR", 25.0)
    pc = _pos_ctrl(params)
    pc.set_state((0.0, 0.0, -10.0), (-15.0, 10.0, 0.0), 0.0)
    pc.set_setpoint((NAN,) * 3, (15.0, -10.0, 0.0), (NAN,) * 3, 0.0, NAN)
    for _ in range(200):
        sp = pc.update(0.02)
    R = quat_to_matrix(sp.q_d)
    tilt = math.degrees(math.acos(R[2, 2]))
    assert 20.0 < tilt <= 25.0 + 1e-6


def test_nan_position_falls_back_to_velocity_and_both_nan_holds_still(params):
    pc = _pos_ctrl(params)
    pc.set_state((0.0, 0.0, -10.0), (0.0, 0.0, 0.0), 0.0)
    pc.set_setpoint((NAN, NAN, -10.0), (1.0, -0.5, NAN), (NAN,) * 3, 0.0, NAN)
    for _ in range(100):
        pc.update(0.02)
    assert pc.v_sp[:2] == pytest.approx([1.0, -0.5])
    pc.set_setpoint((NAN,) * 3, (NAN,) * 3, (NAN,) * 3, NAN, NAN)
    for _ in range(100):
        sp = pc.update(0.02)
    assert pc.v_sp == pytest.approx([0.0, 0.0, 0.0])
    assert sp.yaw_rad == pytest.approx(0.0)  # NaN yaw holds the current heading


def test_climb_speed_limits(params):
    pc = _pos_ctrl(params)
    pc.set_state((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.0)
    pc.set_setpoint((0.0, 0.0, -70.0), (NAN,) * 3, (NAN,) * 3, 0.0, NAN)
    for _ in range(200):
        pc.update(0.02)
    assert pc.v_sp[2] == pytest.approx(-params["MPC_Z_VEL_MAX_UP"])
    pc.set_setpoint((0.0, 0.0, 70.0), (NAN,) * 3, (NAN,) * 3, 0.0, NAN)
    for _ in range(300):
        pc.update(0.02)
    assert pc.v_sp[2] == pytest.approx(params["MPC_Z_VEL_MAX_DN"])


def test_landing_limit_levels_and_idles(params):
    pc = _pos_ctrl(params)
    pc.set_state((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), 0.0)
    pc.set_setpoint((3.0, 0.0, NAN), (NAN, NAN, 0.7), (NAN,) * 3, 0.0, NAN)
    pc.ground_contact = pc.maybe_landed = True
    sp = pc.update(0.02)
    roll, pitch, _ = quat_to_euler(sp.q_d)
    assert abs(roll) < 1e-9 and abs(pitch) < 1e-9
    assert sp.thrust == pytest.approx(params["MPC_THR_MIN"])


@pytest.mark.parametrize("yaw", [0.0, 1.0, -2.5, math.pi - 0.01])
def test_attitude_from_thrust_points_body_z_against_thrust(yaw):
    t = np.array([0.2, -0.3, -1.0])
    t /= np.linalg.norm(t)
    q = attitude_from_thrust(*t, yaw)
    R = quat_to_matrix(q)
    assert R[:, 2] == pytest.approx(-t)  # body down = -thrust
    # the heading of body x projected on the horizontal plane is the yaw
    assert math.atan2(R[1, 0], R[0, 0]) == pytest.approx(yaw, abs=0.2)


def test_attitude_control_commands_rates_towards_setpoint(params):
    ac = AttitudeControl()
    ac.configure(params)
    ac.set_state(tuple(quaternion_from_euler(0.0, 0.0, 0.0)))
    ac.set_setpoint(tuple(quaternion_from_euler(0.1, -0.05, 0.0)))
    p, q, r = ac.update()
    assert p == pytest.approx(params["MC_ROLL_P"] * 0.1, rel=0.05)
    assert q == pytest.approx(params["MC_PITCH_P"] * -0.05, rel=0.1)
    ac.set_setpoint(tuple(quaternion_from_euler(0.0, 0.0, 0.2)))
    assert ac.update()[2] == pytest.approx(params["MC_YAW_P"] * 0.2, rel=0.05)
    ac.set_setpoint(tuple(quaternion_from_euler(1.5, 0.0, 0.0)))
    assert ac.update()[0] == pytest.approx(math.radians(params["MC_ROLLRATE_MAX"]))  # rate limit


def test_attitude_control_puts_tilt_before_heading(params):
    """Level at heading 0, asked for 0.3 rad of roll at heading ~180 deg: the tilt is served at full gain,
    the heading at MC_YAW_P / MC_ROLL_P of it (a plain quaternion error would mix the two)."""
    ac = AttitudeControl()
    ac.configure(params)
    ac.set_state(tuple(quaternion_from_euler(0.0, 0.0, 0.0)))
    ac.set_setpoint(tuple(quaternion_from_euler(0.3, 0.0, math.pi - 0.01)))
    p, q, r = ac.update()
    assert math.hypot(p, q) == pytest.approx(2 * params["MC_ROLL_P"] * math.sin(0.15), rel=0.05)
    assert abs(r) == pytest.approx(math.radians(params["MC_YAWRATE_MAX"]))  # heading: rate-limited
    # a plain quaternion error would ask for the tilt about the wrong axis (pitch instead of roll)
    assert abs(p) > abs(q)


def test_rate_control_pid_and_integrator_limit(params):
    rc = RateControl()
    rc.configure(params)
    rc.set_state((0.0, 0.0, 0.0))
    rc.set_setpoint((1.0, -1.0, 0.5))
    out = rc.update(0.01)
    assert out[0] > 0 and out[1] < 0 and out[2] > 0
    for _ in range(10000):
        rc.update(0.01)
    assert abs(rc.integ[0]) == pytest.approx(params["MC_RR_INT_LIM"])
    assert rc.update(0.01, integrate=False)[0] <= 1.0


def test_mixer_signs_and_saturation():
    mx = QuadXMixer(QUADX.rotors, idle=0.05)
    assert mx.mix(0.5, (0.0, 0.0, 0.0)) == pytest.approx([0.5] * 4)
    m = mx.mix(0.5, (0.2, 0.0, 0.0))  # roll right: left rotors (1 rear-left, 2 front-left) push harder
    assert m[1] > m[0] and m[2] > m[3]
    m = mx.mix(0.5, (0.0, 0.2, 0.0))  # pitch up: front rotors (0, 2) push harder
    assert m[0] > m[1] and m[2] > m[3]
    m = mx.mix(0.5, (0.0, 0.0, 0.2))  # yaw right: the CCW rotors (0, 1) push harder
    assert m[0] > m[2] and m[1] > m[3]
    m = mx.mix(0.9, (0.6, 0.0, 1.0))  # saturated: yaw gives way, roll kept, outputs in range
    assert all(0.05 <= v <= 1.0 for v in m)
    assert (m[1] - m[0]) == pytest.approx(0.6, abs=1e-9)  # full roll differential kept
    assert mx.mix(0.0, (0.0, 0.0, 0.0)) == pytest.approx([0.05] * 4)  # never below idle


def test_ekf_static_convergence_with_noisy_gps(params):
    """A resting vehicle with accelerometer bias and noisy GPS: position, tilt and bias converge."""
    rng = np.random.default_rng(3)
    ekf = NavigationEkf(params, gravity_m_s2=G)
    truth = np.array([5.0, -3.0, -20.0])
    acc_bias = np.array([0.0, 0.0, 0.15])
    accel = np.array([0.0, 0.0, -G]) + acc_bias
    mag = (0.21, 0.0, 0.42)
    ekf.initialize(truth + rng.normal(0, 1.0, 3), (0.0, 0.0, 0.0), accel, mag)
    dt = 0.02
    for k in range(50 * 60):
        ekf.predict((0.0, 0.0, 0.0), accel + rng.normal(0, 0.05, 3), dt)
        if k % 5 == 0:
            ekf.fuse_baro_heading(-truth[2] + rng.normal(0, 0.1), mag)
        if k % 10 == 0:
            ekf.fuse_gps(truth + rng.normal(0, 0.5, 3), rng.normal(0, 0.1, 3))
    assert np.linalg.norm(ekf.position_ned[:2] - truth[:2]) < 0.5
    assert abs(ekf.position_ned[2] - truth[2]) < 0.3
    assert np.linalg.norm(ekf.velocity_ned) < 0.1
    roll, pitch, yaw = ekf.euler()
    assert abs(roll) < 0.01 and abs(pitch) < 0.01 and abs(yaw) < 0.05
    assert ekf.accel_bias[2] == pytest.approx(0.15, abs=0.05)


def test_the_ekf_is_filterpy_s_extended_kalman_filter_to_the_bit(params):
    """The written-out covariance algebra against filterpy's own EKF on the same inputs (a flight's worth of
    IMU periods, GPS, baro and heading, manoeuvring so every term moves): the same states and covariances."""
    from filterpy.kalman import ExtendedKalmanFilter

    class Filterpy(ExtendedKalmanFilter):
        def __init__(self, ekf):
            super().__init__(dim_x=NavigationEkf.N, dim_z=1)
            self.ekf = ekf

        def predict_x(self, u=0):
            self.ekf._propagate_nominal(*u)

        def update(self, z, H, hx, R):  # the _Ekf signature onto filterpy's
            super().update(z, lambda _x: H, hx, R=R)

    ours, theirs = NavigationEkf(params, gravity_m_s2=G), NavigationEkf(params, gravity_m_s2=G)
    fp = Filterpy(theirs)
    fp.F, fp.Q = theirs.kf.F, theirs.kf.Q
    theirs.kf = fp
    rng = np.random.default_rng(5)
    for ekf in (ours, theirs):
        ekf.initialize((1.0, 2.0, -3.0), (0.5, 0.0, 0.0), (0.1, -0.2, -G), (0.21, 0.02, 0.42))
    for k in range(600):
        gyro, accel = rng.normal(0, 0.3, 3), np.array([0.0, 0.0, -G]) + rng.normal(0, 1.0, 3)
        gps, vel, baro = rng.normal(0, 5.0, 3), rng.normal(0, 2.0, 3), rng.normal(3.0, 0.5)
        mag = (0.21 + rng.normal(0, 0.02), rng.normal(0, 0.05), 0.42)
        for ekf in (ours, theirs):
            ekf.predict(gyro, accel, 0.02)
            if k % 10 == 0:
                ekf.fuse_all(gps, vel, baro, mag)
            elif k % 5 == 0:
                ekf.fuse_baro_heading(baro, mag)
            elif k % 7 == 0:
                ekf.fuse_gps(gps, vel)
        assert np.array_equal(ours.kf.x, theirs.kf.x) and np.array_equal(ours.kf.P, theirs.kf.P)
        assert ours.q == theirs.q


def test_battery_drains_faster_with_more_thrust(params):
    hover, climb = Battery(params), Battery(params)
    for _ in range(600):
        hover.update([3.7] * 4, 0.1, armed=True)
        climb.update([6.0] * 4, 0.1, armed=True)
    assert 0.0 < climb.remaining < hover.remaining < 1.0
    assert 10.0 < hover.current_a < 15.0  # about 12 A at hover on 4S
    assert hover.voltage_v < 4 * 4.2


def test_land_detector_needs_time_and_low_thrust(params):
    ld = LandDetector(params)
    ld.reset_flying()
    args = dict(thrust_hover=0.49, thrust_min=0.12, descend_commanded=True)
    for _ in range(50):  # 1 s at 50 Hz, thrust still high: no landing
        assert not ld.update(0.02, (0, 0, 0.0), (0, 0, 0), thrust=0.45, **args)
    t = 0.0
    while not ld.update(0.02, (0, 0, 0.0), (0, 0, 0), thrust=0.12, **args):
        t += 0.02
        assert t < 3.0
    assert t >= params["LNDMC_TRIG_TIME"]


@pytest.mark.parametrize(
    "rates",
    [(200, 30, 10), (200, 100, 30), (250, 125, 50), (200, 0, 50), (200.0, 100, 50), (50, 50, 50), (100, 100, 4)],
)
def test_rates_that_do_not_divide_are_refused(rates):
    with pytest.raises(UavsearchError):
        _check_rates(*rates)
    _check_rates(100, 100, 50)  # the default passes
    _check_rates(200, 100, 25)


def test_sensor_noise_matches_its_parameters_and_the_seed(params):
    from uavsearch.flight.sensors import SensorSuite
    from uavsearch.geometry import GeodeticOrigin

    params.set("SIM_GYRO_NOISE", 0.01)
    params.set("SIM_GPS_DRIFT", 0.0)
    home = GeodeticOrigin()

    def record(seed):
        s = SensorSuite(params, home, np.random.default_rng(seed))
        gyro = np.array([s.imu((0.0, 0.0, 0.0), (0.0, 0.0, -G), 0.01)[0] for _ in range(4000)])
        gps = np.array([s.gps(0, (1.0, 2.0, 30.0), (0.0, 0.0, 0.0), 0.2).position_ned_m for _ in range(2000)])
        return s, gyro, gps

    s, gyro, gps = record(5)
    assert gyro.std(axis=0) == pytest.approx([0.01] * 3, rel=0.1)
    assert gyro.mean(axis=0) == pytest.approx(s.gyro_bias, abs=0.002)  # the bias is there, and known to the test
    assert gps.mean(axis=0) == pytest.approx([2.0, 1.0, -30.0], abs=0.1)  # NED from ENU
    assert gps.std(axis=0) == pytest.approx([0.5, 0.5, 0.8], rel=0.1)
    fix = s.last_gps
    assert home.geodetic_to_enu([fix.lat_deg, fix.lon_deg, fix.alt_amsl_m]) == pytest.approx(
        [fix.position_ned_m[1], fix.position_ned_m[0], -fix.position_ned_m[2]], abs=1e-6
    )
    _, gyro2, gps2 = record(5)
    _, gyro3, _ = record(6)
    assert np.array_equal(gyro, gyro2) and np.array_equal(gps, gps2)
    assert not np.array_equal(gyro, gyro3)


def test_making_an_fdm_prints_no_banner_and_leaves_the_environment_as_it_was(capfd, monkeypatch):
    import os

    from uavsearch.flight.fdm import QuadFdm
    from uavsearch.geometry import GeodeticOrigin

    monkeypatch.delenv("JSBSIM_DEBUG", raising=False)
    before = dict(os.environ)
    QuadFdm(GeodeticOrigin(47.0, 8.0, 400.0), 250)
    assert dict(os.environ) == before
    assert "JSBSim" not in capfd.readouterr().out
