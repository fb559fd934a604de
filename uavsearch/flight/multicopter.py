"""The simulated multicopter: JSBSim airframe + sensors + EKF + control cascade, stepped in lockstep.

This is the vehicle the autopilot drives. It knows nothing of modes or MAVLink: it takes a
TrajectorySetpoint (NED, NaN = uncontrolled), arm/disarm, and advances exactly one physics step per
`step()`. Everything it reports is the EKF's estimate, except `true_state` (renderer, logs, error
measurement).

Rates (all in simulated time; each must divide the one above it):
  physics_hz  JSBSim step                           (default 100; the contacts are stable there)
  ctrl_hz     IMU sample, attitude + rate control   (default 100)
  ekf_hz      EKF prediction, position control,     (default 50; GPS fused at 5 Hz, baro and
              land detector, battery                 magnetometer at 10 Hz, 5 Hz if
                                                     ekf_hz is not a multiple of 10)

Ground handling (PX4's takeoff / land states): armed on the ground the rotors idle and nothing
integrates; a setpoint asking to climb (position above, or upward velocity) starts the flight; the land
detector (estimate-based) ends it, after which the rotors idle again until the autopilot disarms.
"""

from __future__ import annotations

import math
import weakref

import numpy as np

from ..errors import UavsearchError
from ..geometry import GeodeticOrigin
from .battery import BATTERY_PARAMS, Battery
from .control import CONTROL_PARAMS, AttitudeControl, PositionControl, QuadXMixer, RateControl
from .estimator import EKF_PARAMS, NavigationEkf
from .quaternion import quat_from_rotvec, quat_multiply, quat_normalize, quat_to_euler
from .fdm import QUADX, QuadFdm
from .land_detector import LAND_PARAMS, LandDetector
from .messages import (
    BatteryStatus,
    SensorHealth,
    TrajectorySetpoint,
    VehicleAttitude,
    VehicleGlobalPosition,
    VehicleLandDetected,
    VehicleLocalPosition,
    VehicleTrueState,
)
from .params import ParamDef, ParamStore
from .sensors import SENSOR_PARAMS, GpsFix, SensorSuite

WIND_PARAMS: list[ParamDef] = [
    ParamDef("SIM_WIND_N", 0.0, -20.0, 20.0, "m/s", description="steady wind towards north"),
    ParamDef("SIM_WIND_E", 0.0, -20.0, 20.0, "m/s", description="steady wind towards east"),
]

MC_PARAMS: list[ParamDef] = [
    *CONTROL_PARAMS, *EKF_PARAMS, *SENSOR_PARAMS, *LAND_PARAMS, *BATTERY_PARAMS, *WIND_PARAMS
]

GPS_HZ = 5
BARO_MAG_HZ = 10  # 5 when ekf_hz is not a multiple of 10 (e.g. 25): fused with the GPS then


def _baro_mag_hz(ekf_hz: int) -> int:
    return BARO_MAG_HZ if ekf_hz % BARO_MAG_HZ == 0 else GPS_HZ
IDLE_THRUST = 0.05
TAKEOFF_CLIMB_M = 0.3  # a position setpoint this far above the vehicle (or an upward velocity) means "take off"


def _frozen(values) -> np.ndarray:
    """A read-only array: cached messages are shared between readers, so nobody may edit them in place."""
    a = np.array(values, dtype=float)
    a.flags.writeable = False
    return a


def _check_rates(physics_hz, ctrl_hz, ekf_hz) -> None:
    for name, v in (("physics_hz", physics_hz), ("ctrl_hz", ctrl_hz), ("ekf_hz", ekf_hz)):
        if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v <= 0:
            raise UavsearchError(f"{name} must be a positive integer, got {v!r}")
    if physics_hz % ctrl_hz:
        raise UavsearchError(f"ctrl_hz={ctrl_hz} does not divide physics_hz={physics_hz}")
    if ctrl_hz % ekf_hz:
        raise UavsearchError(f"ekf_hz={ekf_hz} does not divide ctrl_hz={ctrl_hz}")
    if ekf_hz % GPS_HZ:
        raise UavsearchError(f"ekf_hz={ekf_hz} must be a multiple of {GPS_HZ} (the GPS rate)")
    if not 100 <= physics_hz <= 1000:
        raise UavsearchError(f"physics_hz={physics_hz} outside [100, 1000] (the contacts need >= 100 Hz)")


class Multicopter:
    """One simulated quadrotor. Deterministic: the same seed and setpoints give the same trajectory."""

    def __init__(
        self,
        params: ParamStore,
        home: GeodeticOrigin,
        seed: int,
        start_enu=(0.0, 0.0, 0.0),
        start_yaw_rad: float = 0.0,
        physics_hz: int = 100,
        ctrl_hz: int = 100,
        ekf_hz: int = 50,
    ):
        _check_rates(physics_hz, ctrl_hz, ekf_hz)
        missing = [d.name for d in MC_PARAMS if d.name not in params]
        if missing:
            raise UavsearchError(f"the ParamStore lacks the vehicle's parameters (e.g. {missing[0]}): add MC_PARAMS")
        self.params = params
        self.home = home
        self.physics_hz, self.ctrl_hz, self.ekf_hz = physics_hz, ctrl_hz, ekf_hz
        self._ctrl_div = physics_hz // ctrl_hz
        self._dt_ctrl = 1.0 / ctrl_hz
        self._ekf_div = physics_hz // ekf_hz
        self._gps_div = physics_hz // GPS_HZ if physics_hz % GPS_HZ == 0 else None
        self._baro_mag_hz = _baro_mag_hz(ekf_hz)
        self._baro_div = physics_hz // self._baro_mag_hz if physics_hz % self._baro_mag_hz == 0 else None
        if self._gps_div is None or self._baro_div is None or self._gps_div % self._baro_div:
            raise UavsearchError(f"physics_hz={physics_hz} must be a multiple of {GPS_HZ} and {self._baro_mag_hz}")
        self.fdm = QuadFdm(home, physics_hz, start_enu, start_yaw_rad)
        self.rng = np.random.default_rng(seed)
        self.sensors = SensorSuite(params, home, self.rng)
        self.ekf = NavigationEkf(params, gravity_m_s2=self.fdm.gravity_m_s2)
        g = self.fdm.gravity_m_s2
        self.pos_ctrl = PositionControl(g)
        self.att_ctrl = AttitudeControl()
        self.rate_ctrl = RateControl()
        self.mixer = QuadXMixer(QUADX.rotors, idle=IDLE_THRUST)
        self.land_detector = LandDetector(params)
        self.battery_model = Battery(params)
        self._configure()
        me = weakref.ref(self)  # the store must not keep a finished vehicle alive
        params.on_change(lambda _name, _value: (v := me()) is not None and v._configure())

        self.step_count = 0
        self.time_us = 0
        self.armed = False
        self.flying = False
        self._setpoint = TrajectorySetpoint(0)
        self._motors = [0.0, 0.0, 0.0, 0.0]
        self._att_sp = None
        self._q_out = (1.0, 0.0, 0.0, 0.0)  # EKF attitude propagated with the gyro between EKF updates
        self._rates = (0.0, 0.0, 0.0)
        self._acc_gyro = [0.0, 0.0, 0.0]
        self._acc_accel = [0.0, 0.0, 0.0]
        self._acc_n = 0
        self._gps_time_us = -1
        self._att_time_us = 0
        self._att_cache = None
        # a first IMU/GPS/baro/mag set from the resting airframe initialises the filter
        self._sample_and_estimate(initial=True)

    # ----------------------------------------------------------------------------------- params
    def _configure(self) -> None:
        p = self.params
        self.pos_ctrl.configure(p)
        self.att_ctrl.configure(p)
        self.rate_ctrl.configure(p)
        self.ekf.configure(p)
        self.sensors.configure(p)
        self.fdm.set_wind_ned(p["SIM_WIND_N"], p["SIM_WIND_E"])

    def set_cruise_speed(self, speed_m_s: float | None) -> None:
        """Override MPC_XY_CRUISE for position setpoints (MAV_CMD_DO_CHANGE_SPEED); None goes back to the param."""
        if speed_m_s is not None and not (0.0 < speed_m_s <= self.params["MPC_XY_VEL_MAX"]):
            raise UavsearchError(f"speed {speed_m_s} m/s outside (0, MPC_XY_VEL_MAX]")
        self.pos_ctrl.cruise_override_m_s = speed_m_s

    # ----------------------------------------------------------------------------------- commands
    def arm(self) -> None:
        self.armed = True

    def disarm(self) -> None:
        self.armed = False
        self.flying = False
        self._motors = [0.0, 0.0, 0.0, 0.0]
        self.fdm.set_motor_commands(self._motors)

    def set_setpoint(self, sp: TrajectorySetpoint) -> None:
        """Position / velocity / acceleration setpoint, NED about home; NaN components are not controlled."""
        pos = tuple(float(v) for v in np.asarray(sp.position_ned_m, dtype=float).reshape(3))
        vel = tuple(float(v) for v in np.asarray(sp.velocity_ned_m_s, dtype=float).reshape(3))
        acc = tuple(float(v) for v in np.asarray(sp.acceleration_ned_m_s2, dtype=float).reshape(3))
        if any(math.isinf(v) for v in (*pos, *vel, *acc)):
            raise UavsearchError("setpoint components must be finite or NaN")
        self._setpoint = sp
        self.pos_ctrl.set_setpoint(pos, vel, acc, float(sp.yaw_rad), float(sp.yawspeed_rad_s))

    # ----------------------------------------------------------------------------------- stepping
    def step(self) -> None:
        """Advance one physics step; sensors, EKF and controllers run on their own rate boundaries."""
        k = self.step_count
        if k % self._ctrl_div == 0:
            self._control_tick(k)
        self.fdm.step()
        self.step_count = k + 1
        self.time_us = (k + 1) * 1_000_000 // self.physics_hz

    def run_for(self, seconds: float) -> None:
        for _ in range(int(round(seconds * self.physics_hz))):
            self.step()

    def _control_tick(self, k: int) -> None:
        fdm = self.fdm
        dt_ctrl = self._dt_ctrl
        g, a = self.sensors.imu(fdm.body_rates_rad_s(), fdm.specific_force_frd_m_s2(), dt_ctrl)
        sg, sa = self._acc_gyro, self._acc_accel
        sg[0] += g[0]
        sg[1] += g[1]
        sg[2] += g[2]
        sa[0] += a[0]
        sa[1] += a[1]
        sa[2] += a[2]
        self._acc_n += 1
        bg = self._bias_g
        rates = (g[0] - bg[0], g[1] - bg[1], g[2] - bg[2])
        self._rates = rates
        self._att_time_us = self.time_us
        if k % self._ekf_div == 0:
            self._sample_and_estimate(initial=False)  # the prediction has consumed this sample
            self._position_tick()
        else:
            # output predictor: the EKF attitude moved forward by the gyro since its last update
            self._q_out = quat_normalize(
                quat_multiply(self._q_out, quat_from_rotvec(rates[0] * dt_ctrl, rates[1] * dt_ctrl, rates[2] * dt_ctrl))
            )
        if not self.armed:
            return
        if not self.flying or self._att_sp is None:
            self._motors = [IDLE_THRUST] * 4
        else:
            self.att_ctrl.set_state(self._q_out)
            self.att_ctrl.set_setpoint(self._att_sp.q_d, self._att_sp.yawspeed_ff_rad_s)
            self.rate_ctrl.set_state(rates)
            self.rate_ctrl.set_setpoint(self.att_ctrl.update(dt_ctrl))
            torque = self.rate_ctrl.update(dt_ctrl, integrate=not self.land_detector.ground_contact)
            self._motors = self.mixer.mix(self._att_sp.thrust, torque)
        fdm.set_motor_commands(self._motors)

    def _sample_and_estimate(self, initial: bool) -> None:
        fdm, sens, ekf = self.fdm, self.sensors, self.ekf
        k = self.step_count
        if initial or k % self._baro_div == 0:
            pos = fdm.position_enu_m()
        if initial:
            imu = sens.imu(fdm.body_rates_rad_s(), fdm.specific_force_frd_m_s2(), 1.0 / self.ctrl_hz)
            fix = sens.gps(self.time_us, pos, fdm.velocity_ned_m_s(), 1.0 / GPS_HZ)
            sens.baro(pos[2], 1.0 / self._baro_mag_hz)
            mag = sens.mag(*fdm.euler_rad())
            ekf.initialize(fix.position_ned_m, fix.velocity_ned_m_s, imu.accel_frd_m_s2, mag)
            self._gps_time_us = self.time_us
        else:
            n = self._acc_n
            dt = n / self.ctrl_hz
            ekf.predict([v / n for v in self._acc_gyro], [v / n for v in self._acc_accel], dt)
            self._acc_gyro = [0.0, 0.0, 0.0]
            self._acc_accel = [0.0, 0.0, 0.0]
            self._acc_n = 0
            if k % self._baro_div == 0:
                alt = sens.baro(pos[2], 1.0 / self._baro_mag_hz)
                mag = sens.mag(*fdm.euler_rad())
                if k % self._gps_div == 0 and not self.params["SIM_GPS_BLOCK"]:  # all three: one update
                    fix = sens.gps(self.time_us, pos, fdm.velocity_ned_m_s(), 1.0 / GPS_HZ)
                    ekf.fuse_all(fix.position_ned_m, fix.velocity_ned_m_s, alt - self.home.alt_m, mag)
                    self._gps_time_us = self.time_us
                else:
                    ekf.fuse_baro_heading(alt - self.home.alt_m, mag)
        self._q_out = ekf.q
        x = ekf.kf.x[:, 0].tolist()
        self._bias_g = (x[9], x[10], x[11])
        self._est_pos = (x[0], x[1], x[2])
        self._est_vel = (x[3], x[4], x[5])
        self._est_time_us = self.time_us
        self._lp_cache = self._gp_cache = None  # outputs are built lazily, once per filter update

    def _position_tick(self) -> None:
        dt = 1.0 / self.ekf_hz
        p = self.params
        roll, pitch, yaw = quat_to_euler(self.ekf.q)
        pc = self.pos_ctrl
        pc.set_state(self._est_pos, self._est_vel, yaw)
        self.battery_model.update(self.fdm.rotor_thrusts_n(), dt, self.armed)
        if not self.armed:
            self.flying = False
            self.land_detector.landed = True
            return
        if not self.flying:
            if self._takeoff_requested():
                self.flying = True
                pc.reset(self._est_vel)
                self.rate_ctrl.reset()
                self.land_detector.reset_flying()
            else:
                self._att_sp = None
                return
        self._att_sp = pc.update(dt)
        sp_pos_z, sp_vel_z = pc.sp_pos[2], pc.sp_vel[2]
        descend = (sp_vel_z == sp_vel_z and sp_vel_z > 0.1) or (sp_pos_z == sp_pos_z and sp_pos_z > self._est_pos[2] + 0.1)
        landed = self.land_detector.update(
            dt, self._est_vel, self._rates, pc.thrust, p["MPC_THR_HOVER"], p["MPC_THR_MIN"], descend
        )
        pc.ground_contact = self.land_detector.ground_contact
        pc.maybe_landed = self.land_detector.maybe_landed
        if landed:
            self.flying = False
            self._att_sp = None
            pc.reset()
            self.rate_ctrl.reset()

    def _takeoff_requested(self) -> bool:
        pz, vz = self.pos_ctrl.sp_pos[2], self.pos_ctrl.sp_vel[2]
        if pz == pz:
            return pz < self._est_pos[2] - TAKEOFF_CLIMB_M
        return vz == vz and vz < -0.2

    # ----------------------------------------------------------------------------------- outputs
    @property
    def local_position(self) -> VehicleLocalPosition:
        """The EKF's position/velocity, stamped with the time of the filter update that made it."""
        if self._lp_cache is None:
            P = self.ekf.kf.P
            w, x, y, z = self.ekf.q
            self._lp_cache = VehicleLocalPosition(
                self._est_time_us,
                _frozen(self._est_pos),
                _frozen(self._est_vel),
                math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)),
                eph_m=math.sqrt(float(P[0, 0]) + float(P[1, 1])),
                epv_m=math.sqrt(float(P[2, 2])),
            )
        return self._lp_cache

    @property
    def attitude(self) -> VehicleAttitude:
        if self._att_cache is None or self._att_cache.timestamp_us != self._att_time_us:
            self._att_cache = VehicleAttitude(self._att_time_us, _frozen(self._q_out), _frozen(self._rates))
        return self._att_cache

    @property
    def global_position(self) -> VehicleGlobalPosition:
        if self._gp_cache is None:
            n, e, d = self._est_pos
            lat, lon, alt = self.home.enu_to_geodetic(np.array([e, n, -d])).tolist()
            self._gp_cache = VehicleGlobalPosition(self._est_time_us, lat, lon, alt, -d)
        return self._gp_cache

    @property
    def true_state(self) -> VehicleTrueState:
        f = self.fdm
        vn, ve, vd = f.velocity_ned_m_s()
        roll, pitch, yaw = f.euler_rad()
        return VehicleTrueState(
            self.time_us,
            np.array(f.position_enu_m()),
            np.array([ve, vn, -vd]),
            roll,
            pitch,
            yaw,
            np.array(f.body_rates_rad_s()),
        )

    @property
    def land_detected(self) -> VehicleLandDetected:
        ld = self.land_detector
        landed = (not self.flying) or ld.landed
        return VehicleLandDetected(self.time_us, landed, landed or ld.ground_contact)

    @property
    def battery(self) -> BatteryStatus:
        b = self.battery_model
        return BatteryStatus(self.time_us, b.voltage_v, b.current_a, b.discharged_mah, b.remaining)

    @property
    def sensor_health(self) -> SensorHealth:
        gps_ok = self.time_us - self._gps_time_us < 1_000_000
        return SensorHealth(gyro=True, accel=True, mag=True, baro=True, gps=gps_ok)

    @property
    def gps_fix(self) -> GpsFix:
        """The latest GPS solution (for GPS_RAW_INT): fix_type, satellites, eph, epv, lat, lon, alt, ...

        Older than a second (SIM_GPS_BLOCK): the last solution with fix_type 0 and no satellites."""
        fix = self.sensors.last_gps
        if self.time_us - self._gps_time_us >= 1_000_000:
            return fix._replace(fix_type=0, satellites_visible=0)
        return fix

    @property
    def motor_outputs(self) -> tuple:
        """Normalised rotor commands in [0, 1] (SERVO_OUTPUT_RAW / ACTUATOR_OUTPUT_STATUS)."""
        return tuple(self._motors)

    @property
    def thrust_setpoint(self) -> float:
        return self._att_sp.thrust if self._att_sp is not None else 0.0
