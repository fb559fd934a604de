"""`uavsearch sitl`: the simulated vehicle as a MAVLink system, stepped in lockstep on simulation time.

One loop advances the physics one step at a time; the autopilot (commander + navigator) runs at
`autopilot_hz` and MAVLink I/O (receive, handle, stream) at `io_hz`, both on simulation time, so the
flight is the same for a given seed whatever the pacing. Pacing only decides how long the loop waits:
`--speed 1` keeps simulation time on the wall clock (for ground stations), `--speed N` runs N times
faster, `--speed max` never waits. While waiting, the loop sleeps in select() on the sockets and
answers packets at once, so a real-time vehicle still acknowledges commands within a millisecond.
`--lockstep` hands the clock to one client (see lockstep.py): the simulation runs only as far as that
client has granted, which makes a flight commanded from another process reproducible.

`--vehicles N` simulates a team on the one clock, with PX4 SITL's conventions per instance I (0-based):
system id I + 1, the API link to UDP 14540 + I from 14580 + I, the GCS link to 14550 from 18570 + I,
noise seed + I, home HOME_SPACING_M * I east of the first. Every vehicle steps, ticks and (in lockstep)
waits together: one grant, sent to any of them, runs them all. A goto (DO_REPOSITION) whose target lies
within SIM_SEP_DIST of another vehicle's position or goal is refused. `--instance I` runs instance I alone
(PX4's `px4 -i I`): its own process and clock, no separation check.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import select
import signal
import sys
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

from ..errors import UavsearchError, run_command
from ..geometry import CameraIntrinsics, GeodeticOrigin, ned_to_enu
from ..paths import RUNS_DIR
from .camera import CAPTURE_MIN_FREE_MB, Camera, background_scene_renderer
from .commander import Commander, autopilot_params
from .lockstep import LockstepGate
from .logger import ULOG_NAME, FlightLogger
from .mavlink.endpoint import MavlinkEndpoint
from .mavlink.links import LinkConfig
from .mavlink.signing import parse_signing_key
from .mavlink.streams import GCS_RATES_HZ
from .params import ParamDef, ParamError, ParamStore


@dataclass
class SitlConfig:
    seed: int = 0  # vehicle noise (sensors, estimator): the same seed flies the same trajectory
    scene_seed: int | None = 0  # None: no camera rendering (captures fail with capture_result 0)
    occupied_cells: int = 5
    scene_file: Path | None = None  # a saved scene spec (JSON) instead of generating scene_seed
    home: GeodeticOrigin = field(default_factory=GeodeticOrigin)
    speed: float = 1.0  # math.inf = as fast as possible
    lockstep: bool = False  # run only as far as a client grants (MAV_CMD_SIM_ADVANCE)
    api_port: int = 14540  # remote ports: 0 disables the link
    gcs_port: int = 14550
    api_local_port: int = 14580  # PX4 SITL's source ports
    gcs_local_port: int = 18570
    signing_key: bytes | None = None
    sign_api_strict: bool = False  # MAVSDK cannot sign: by default the API link signs but accepts unsigned
    run_dir: Path | None = None
    autopilot_hz: int = 50
    io_hz: int = 100  # receive + handle packets (non-blocking)
    stream_hz: int = 50  # telemetry scheduling (each message keeps its own interval)
    params: dict = field(default_factory=dict)
    start_enu: tuple = (0.0, 0.0, 0.0)
    start_yaw_rad: float = 0.0
    intrinsics: CameraIntrinsics = field(default_factory=CameraIntrinsics)
    setting: str | None = None  # a scene family ("wide", "2"): scene_seed's scene and the images as the family draws them
    vehicles: int = 1  # simulated in this process on one clock
    instance: int = 0  # the first vehicle's instance number I (sysid, ports, seed and home follow it)
    one_api_port: bool = False  # every vehicle's API link sends to api_port itself (one client for the team)
    ulog: bool = True  # each vehicle writes its flight.ulg (PX4's ULog) into its run directory


HOME_SPACING_M = 10.0  # instance I's home lies this far east of instance 0's (PX4's multi-vehicle SITL spaces them)
MAX_VEHICLES = 16
SEPARATION_M = 5.0  # SIM_SEP_DIST's default: half the homes' spacing


def instance_config(cfg: SitlConfig, i: int) -> SitlConfig:
    """The config of vehicle I = cfg.instance + i, by PX4 SITL's conventions (a port of 0 stays off / any)."""
    inst = cfg.instance + i
    start = tuple(cfg.start_enu)
    return dataclasses.replace(
        cfg, vehicles=1, instance=inst, seed=cfg.seed + inst,
        api_port=cfg.api_port + inst if cfg.api_port and not cfg.one_api_port else cfg.api_port,
        api_local_port=cfg.api_local_port + inst if cfg.api_local_port else 0,
        gcs_local_port=cfg.gcs_local_port + inst if cfg.gcs_local_port else 0,
        start_enu=(start[0] + HOME_SPACING_M * inst, start[1], start[2]),
        params={**cfg.params, "MAV_SYS_ID": inst + 1} if (cfg.vehicles > 1 or inst) else cfg.params)


# What the vehicle simulates, readable by any MAVLink client with PARAM_REQUEST_READ (a standard protocol every
# ground station and MAVSDK speak), so a client can check it flies the scene it scores against.
NO_SCENE = -1
SITL_PARAMS = [
    ParamDef("SIM_SCENE_SEED", NO_SCENE, NO_SCENE, 2**31 - 1, type="int", readonly=True,
             description="seed of the simulated scene (-1: none)"),
    ParamDef("SIM_SCENE_CELLS", NO_SCENE, NO_SCENE, 10_000, type="int", readonly=True,
             description="occupied cells of the simulated scene (-1: none)"),
    ParamDef("SIM_SCENE_HASH", 0, 0, 2**31 - 1, type="int", readonly=True,
             description="CRC-32 (31 bits) of the scene spec file it was given (0: generated from seed and cells)"),
    ParamDef("SIM_CAM_FREE_MB", CAPTURE_MIN_FREE_MB, 0.0, 1e7, unit="MB",
             description="interval capture stops (and does not start) below this much free disk in the run directory"),
    ParamDef("SIM_SEP_DIST", SEPARATION_M, 0.0, 1000.0, unit="m",
             description="a goto within this distance of another simulated vehicle's position or goal is refused "
                         "(0: off)"),
]


def scene_hash(spec) -> int:
    """SIM_SCENE_HASH of a scene spec (what a client compares with its own spec)."""
    import zlib

    from ..world.scene import scene_to_json

    return zlib.crc32(scene_to_json(spec).encode()) & 0x7FFFFFFF


def _default_vehicle(params: ParamStore, cfg: SitlConfig):
    from .multicopter import Multicopter  # lazy: ~0.8 s (JSBSim, EKF), and every `uavsearch` command imports sitl

    return Multicopter(params, cfg.home, cfg.seed, start_enu=cfg.start_enu, start_yaw_rad=cfg.start_yaw_rad)


def _vehicle_params():
    from .multicopter import MC_PARAMS  # lazy: see _default_vehicle

    return MC_PARAMS


def _next_tick(due_us: int, period_us: int, now_us: int) -> int:
    """The next due time on the fixed grid, skipping ticks missed (e.g. after stepping the vehicle directly)."""
    due_us += period_us
    if due_us <= now_us:
        due_us += ((now_us - due_us) // period_us + 1) * period_us
    return due_us


class SimVehicle:
    """One simulated vehicle: physics + autopilot + camera + MAVLink endpoint, and when each of them is due.

    `cfg` is this vehicle's own config (instance_config); the runner owns the clock and the pacing."""

    def __init__(self, cfg: SitlConfig, run_dir: Path, render, vehicle_factory=None, vehicle_params=None,
                 scene_params: dict | None = None):
        self.cfg = cfg
        mc_params = list(vehicle_params if vehicle_params is not None else _vehicle_params())
        self.params = ParamStore(mc_params, autopilot_params(mc_params), SITL_PARAMS)
        for name, value in cfg.params.items():
            self.params.set(name, value)
        for name, value in (scene_params or {}).items():
            self.params.set(name, value, force=True)
        self.run_dir = run_dir
        self.vehicle = (vehicle_factory or _default_vehicle)(self.params, cfg)  # the scene builds meanwhile
        self.commander = Commander(self.params, self.vehicle, cfg.home, autopilot_hz=cfg.autopilot_hz)
        self.camera = Camera(self.vehicle, cfg.intrinsics, run_dir, render,
                             home_alt_amsl_m=lambda: self.commander.home_alt_amsl_m,
                             min_free_mb=lambda: self.params["SIM_CAM_FREE_MB"])
        links = []
        if cfg.api_port:
            links.append(LinkConfig("api", cfg.api_port, local_port=cfg.api_local_port, signing_key=cfg.signing_key,
                                    require_signed=cfg.sign_api_strict))
        if cfg.gcs_port:
            links.append(LinkConfig("gcs", cfg.gcs_port, local_port=cfg.gcs_local_port, signing_key=cfg.signing_key,
                                    require_signed=True, rates_hz=GCS_RATES_HZ))
        try:
            self.endpoint = MavlinkEndpoint(self.commander, self.params, links, self.camera,
                                            sysid=int(self.params["MAV_SYS_ID"]))
        except OSError as e:
            self.camera.close()
            from .sitl_process import udp_port_in_use

            busy = [f"{port} (--{name}-local-port)" for name, port in (("api", cfg.api_local_port),
                                                                       ("gcs", cfg.gcs_local_port))
                    if port and udp_port_in_use(port)]
            raise UavsearchError(f"vehicle {cfg.instance + 1}: UDP source port {' and '.join(busy)} is in use (another "
                                 "sitl?); change that flag (0: any free port)" if busy else
                                 f"cannot open the MAVLink UDP ports of vehicle {cfg.instance + 1} ({e})") from None
        self._ap_period_us = int(1e6 / cfg.autopilot_hz)
        self._io_period_us = int(1e6 / cfg.io_hz)
        self._stream_period_us = int(1e6 / cfg.stream_hz)
        self._next_ap_us = self._next_io_us = self._next_stream_us = int(self.vehicle.time_us)
        self.logger = None
        if cfg.ulog:
            try:
                self.logger = FlightLogger(self, run_dir / ULOG_NAME)
            except OSError as e:
                self.close()
                raise UavsearchError(f"cannot write {run_dir / ULOG_NAME} ({e.strerror or e})") from None
            self.endpoint.text_listeners.append(self.logger.on_text)

    @property
    def sysid(self) -> int:
        return int(self.params["MAV_SYS_ID"])

    def position_enu(self):
        """Where the autopilot believes it is (its estimate: what a fleet would share)."""
        return ned_to_enu(self.vehicle.local_position.position_ned_m)

    def goal_enu(self):
        """Where it is flying to (a goto's point, a take-off's or mission item's target), or None."""
        nav = self.commander.navigator
        if nav.pending_hold is not None:
            return ned_to_enu(nav.pending_hold[0])
        mode = nav.modes[nav.active_name]
        tgt = getattr(mode, "item_target", None) if nav.active_name == "MISSION" else getattr(mode, "target", None)
        return None if tgt is None else ned_to_enu(tgt)

    def tick(self, wall_s: float) -> bool:
        """The autopilot and I/O when due at this instant; True when I/O ran (the runner paces then)."""
        now = self.vehicle.time_us
        if now >= self._next_ap_us:
            self._next_ap_us = _next_tick(self._next_ap_us, self._ap_period_us, now)
            self.commander.update(wall_s)
        if self.logger is not None:
            self.logger.update()
        if now < self._next_io_us:
            return False
        self._next_io_us = _next_tick(self._next_io_us, self._io_period_us, now)
        self.endpoint.poll(time.monotonic())
        if now >= self._next_stream_us:
            self._next_stream_us = _next_tick(self._next_stream_us, self._stream_period_us, now)
            self.endpoint.send_streams()
        return True

    def close(self) -> None:
        self.camera.close()  # the images in flight are written before the renderer goes
        self.endpoint.close()
        if self.logger is not None:
            self.logger.close()


def separation_check(team: list[SimVehicle], me: SimVehicle):
    """The commander's goto check for `me`: why a target is too close to another vehicle, or None."""

    def check(target_ned) -> str | None:
        limit = float(me.params["SIM_SEP_DIST"])
        if limit <= 0:
            return None
        tgt = ned_to_enu(target_ned)
        for other in team:
            if other is me:
                continue
            for what, p in (("position", other.position_enu()), ("goal", other.goal_enu())):
                if p is not None and float(math.dist(tgt, p)) < limit:
                    return f"within {limit:g} m of vehicle {other.sysid}'s {what}"
        return None

    return check


class Sitl:
    """The simulation: one or more SimVehicles advanced one physics step at a time on one clock."""

    def __init__(self, cfg: SitlConfig, vehicle_factory=None, vehicle_params=None, render=None):
        if not 1 <= cfg.vehicles <= MAX_VEHICLES:
            raise UavsearchError(f"--vehicles must be 1..{MAX_VEHICLES}, got {cfg.vehicles}")
        if cfg.vehicles > 1 and "MAV_SYS_ID" in cfg.params:
            raise UavsearchError("a team's system ids are instance + 1: do not set MAV_SYS_ID with --vehicles")
        self.cfg = cfg
        stamp = datetime.now(timezone.utc).strftime("%Y%m%d-%H%M%S")
        self.run_dir = Path(cfg.run_dir) if cfg.run_dir else RUNS_DIR / f"sitl__{cfg.seed}__{stamp}"
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self._close_render = None
        team = [instance_config(cfg, i) for i in range(cfg.vehicles)]
        renders = [render] * cfg.vehicles
        scene_params = {}
        if render is None and cfg.scene_seed is not None:
            spec, options = None, None
            if cfg.scene_file is not None:
                from ..world.scene import load_scene  # lazy: ~0.4 s, only for --scene-file

                spec = load_scene(cfg.scene_file)
                cfg.scene_seed = spec.seed
            elif cfg.setting is not None:
                from ..world.settings import setting_params  # lazy, as above

                fam = setting_params(cfg.setting)
                options, cfg.occupied_cells = fam.task.render, fam.k  # the family's images, as teleport draws them
                if not fam.generic_scenes:  # else seed and K make it, in the render worker (SIM_SCENE_HASH 0)
                    spec = fam.scene(cfg.scene_seed)
            renders, self._close_render = background_scene_renderer(
                cfg.scene_seed, cfg.occupied_cells, cfg.intrinsics, self.run_dir, spec=spec, seeds=[c.seed for c in team],
                options=options)
            scene_params = {"SIM_SCENE_SEED": cfg.scene_seed,
                            "SIM_SCENE_CELLS": cfg.occupied_cells if spec is None else int(spec.occupancy_array().sum()),
                            "SIM_SCENE_HASH": 0 if spec is None else scene_hash(spec)}
        self.team: list[SimVehicle] = []
        try:
            for c, r in zip(team, renders):
                where = self.run_dir if cfg.vehicles == 1 else self.run_dir / f"vehicle{c.instance + 1}"
                self.team.append(SimVehicle(c, where, r, vehicle_factory, vehicle_params, scene_params))
        except BaseException:
            self.close()
            raise
        if cfg.vehicles > 1:
            for m in self.team:
                m.commander.separation = separation_check(self.team, m)
        self.gate = LockstepGate() if cfg.lockstep else None
        for m in self.team:
            m.endpoint.lockstep = self.gate
        self._fds = [fd for m in self.team for fd in m.endpoint.fileno_list()]
        self._stop = None
        self._wall = time.monotonic()
        self._pace_wall0 = None
        self._pace_sim0 = 0

    # the first vehicle's parts (a one-vehicle simulation is all of it)
    @property
    def vehicle(self):
        return self.team[0].vehicle

    @property
    def commander(self) -> Commander:
        return self.team[0].commander

    @property
    def endpoint(self) -> MavlinkEndpoint:
        return self.team[0].endpoint

    @property
    def time_s(self) -> float:
        return self.vehicle.time_us * 1e-6

    def step(self) -> None:
        """One physics step of every vehicle, then the autopilots and I/O when due (simulation time)."""
        gate = self.gate
        if gate is not None and self.vehicle.time_us >= gate.until_us and not self._hold(gate):
            return
        io = False
        for m in self.team:
            io = m.tick(self._wall) or io
        if io:
            self._wall = time.monotonic()
            self._pace()
        for m in self.team:
            m.vehicle.step()

    def _wait_readable(self, timeout_s: float) -> bool:
        if timeout_s <= 0:
            return False
        r, _, _ = select.select(self._fds, [], [], timeout_s)
        return bool(r)

    def _poll(self) -> None:
        self._wall = time.monotonic()
        for m in self.team:
            m.endpoint.poll(self._wall)

    def _hold(self, gate: LockstepGate) -> bool:
        """Stand still, answering packets, until a client grants more time; False when asked to stop."""
        while self.vehicle.time_us >= gate.until_us:
            if self._stop is not None and self._stop():
                return False
            self._wall = time.monotonic()
            for m in self.team:
                m.endpoint.hold(self._wall)
                if m.logger is not None:
                    m.logger.flush()  # a vehicle killed while it waits leaves its log up to now
            if self._wait_readable(0.005 if any(m.camera.busy for m in self.team) else 0.2):  # an image may come
                self._poll()
        self._pace_wall0 = None  # pacing starts afresh: no burst to catch up the time stood still
        return True

    def _pace(self) -> None:
        speed = self.cfg.speed
        if not math.isfinite(speed):
            return
        if self._pace_wall0 is None:
            self._pace_wall0, self._pace_sim0 = self._wall, self.vehicle.time_us
        target = self._pace_wall0 + (self.vehicle.time_us - self._pace_sim0) * 1e-6 / speed
        while True:
            remaining = target - time.monotonic()
            if remaining <= 0:
                break
            if self._wait_readable(remaining):
                self._poll()
        if time.monotonic() - target > 0.5:  # far behind (a slow machine): do not try to catch up in a burst
            self._pace_wall0, self._pace_sim0 = time.monotonic(), self.vehicle.time_us

    def run(self, duration_s: float | None = None, stop=None) -> None:
        end_us = None if duration_s is None else self.vehicle.time_us + int(duration_s * 1e6)
        self._stop = stop
        while (end_us is None or self.vehicle.time_us < end_us) and not (stop and stop()):
            self.step()

    def close(self) -> None:
        for m in self.team:
            m.close()
        if self._close_render:
            self._close_render()
            self._close_render = None

    def banner(self) -> str:
        c = self.cfg
        speed = "max" if not math.isfinite(c.speed) else f"{c.speed:g}x real time"
        if c.lockstep:
            speed += ", lockstep (runs only as far as a client grants)"
        ids = ", ".join(str(m.sysid) for m in self.team)
        team = "" if len(self.team) == 1 else f"{len(self.team)} vehicles (sysid {ids}) on one clock, "
        lines = [
            f"uavsearch sitl: {team}sysid {self.team[0].sysid}, seed {c.seed}, "
            f"scene {c.scene_seed if c.scene_seed is not None else 'none'}"
            f"{'' if c.setting is None else f' ({c.setting})'}, speed {speed}",
            f"  home      lat {c.home.lat_deg:.7f}  lon {c.home.lon_deg:.7f}  alt {c.home.alt_m:.1f} m AMSL",
        ]
        for m in self.team:
            if len(self.team) > 1:
                e, n, _ = m.cfg.start_enu
                lines.append(f"  vehicle {m.sysid} (instance {m.cfg.instance}, seed {m.cfg.seed}) starts at "
                             f"E {e:.1f} N {n:.1f} m; images in {m.run_dir}")
            for link in m.endpoint.links:
                hint = "MAVSDK: udpin://0.0.0.0:{p}" if link.cfg.name == "api" else "QGC / MAVProxy: udpin:0.0.0.0:{p}"
                lines.append(
                    f"  {link.cfg.name.upper()} link  sends to udp {link.cfg.remote_host}:{link.cfg.remote_port} "
                    f"from 127.0.0.1:{link.local_port}   ({hint.format(p=link.cfg.remote_port)})"
                )
        if len(self.team) > 1:
            lines.append(f"  separation  a goto within SIM_SEP_DIST ({self.team[0].params['SIM_SEP_DIST']:g} m) of another "
                         "vehicle's position or goal is refused")
        sign = "off" if c.signing_key is None else ("required on all links" if c.sign_api_strict
                                                    else "required on GCS link; API link signs, accepts unsigned")
        lines.append(f"  signing   {sign}")
        cam = c.intrinsics
        lines.append(f"  camera    {cam.width_px}x{cam.height_px} px, {cam.hfov_deg:g} deg horizontal FOV, nadir "
                     "(compid 100)")
        lines.append(f"  run dir   {self.run_dir}")
        if c.ulog:
            lines.append(f"  ULog      {ULOG_NAME} per vehicle, in its run dir (PX4 Flight Review, PlotJuggler, pyulog)")
        lines.append("ready; Ctrl-C to stop")
        return "\n".join(lines)


# ---------------------------------------------------------------------------------------------------- CLI


def _parse_speed(text: str) -> float:
    if text.lower() == "max":
        return math.inf
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"speed must be a number or 'max', got {text!r}") from None
    if not v > 0:
        raise argparse.ArgumentTypeError("speed must be positive")
    return v


def _parse_home(text: str) -> GeodeticOrigin:
    try:
        parts = [float(x) for x in text.split(",")]
    except ValueError:
        parts = []
    if len(parts) not in (2, 3) or not (-90 <= parts[0] <= 90 and -180 <= parts[1] <= 180):
        raise argparse.ArgumentTypeError(f"--home takes LAT,LON[,ALT] in degrees and metres, got {text!r}")
    return GeodeticOrigin(*parts)


def _parse_size(text: str) -> tuple[int, int]:
    w, sep, h = text.lower().partition("x")
    try:
        size = (int(w), int(h))
    except ValueError:
        size = (0, 0)
    if not sep or not all(16 <= v <= 4096 for v in size):
        raise argparse.ArgumentTypeError(f"--camera-size takes WIDTHxHEIGHT in pixels (16-4096), got {text!r}")
    return size


def _parse_hfov(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not 1.0 < v < 170.0:
        raise argparse.ArgumentTypeError(f"--camera-hfov takes degrees between 1 and 170, got {text!r}")
    return v


def _parse_param(text: str) -> tuple[str, float]:
    name, sep, value = text.partition("=")
    try:
        return name.strip(), float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--param takes NAME=VALUE, got {text!r}") from None


def add_sitl_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser("sitl", help="run the simulated vehicle as a PX4-flavoured MAVLink system",
                              description="Simulated quadrotor (JSBSim) + PX4-style autopilot + camera, "
                                          "reachable over MAVLink UDP like PX4 SITL.")
    add_sitl_arguments(p)
    p.set_defaults(func=run_sitl_command)
    return p


def add_sitl_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", type=int, default=0, metavar="SEED", help="scene seed for the camera (default 0)")
    p.add_argument("--no-camera-scene", action="store_true", help="do not build the scene (faster start; captures fail)")
    p.add_argument("--scene-file", type=Path, default=None, metavar="JSON",
                   help="render a saved scene spec (uavsearch scene save) instead of --scene")
    p.add_argument("--cells", type=int, default=5, metavar="K", help="occupied cells in the scene (default 5)")
    p.add_argument("--setting", default=None, metavar="FAMILY",
                   help="generate --scene from a scene family (e.g. wide: 150 m area, people in groups) instead of "
                        "the paper's generator with --cells, and render it with the family's render options")
    p.add_argument("--vehicles", type=int, default=1, metavar="N",
                   help=f"simulate N vehicles on one clock (1-{MAX_VEHICLES}), PX4 SITL style: instance I has sysid "
                        "I+1, its API link on 14540+I, all on 14550, home 10 m east per instance")
    p.add_argument("--one-api-port", action="store_true",
                   help="every vehicle's API link sends to --api-port itself instead of --api-port + I (one client "
                        "socket for the team, demultiplexed by system id, as `uavsearch fly --vehicles N` uses)")
    p.add_argument("--instance", type=int, default=0, metavar="I",
                   help="the (first) vehicle's instance number: sysid I+1, ports +I, home offset I (default 0)")
    cam = CameraIntrinsics()
    p.add_argument("--camera-hfov", type=_parse_hfov, default=cam.hfov_deg, metavar="DEG",
                   help=f"the nadir camera's horizontal field of view (default {cam.hfov_deg:g}, what the models "
                        "were trained with)")
    p.add_argument("--camera-size", type=_parse_size, default=(cam.width_px, cam.height_px), metavar="WxH",
                   help=f"the camera's image size in pixels (default {cam.width_px}x{cam.height_px})")
    p.add_argument("--seed", type=int, default=0, help="vehicle noise seed (default 0)")
    p.add_argument("--speed", type=_parse_speed, default=1.0, help="1 (real time, default), N (N x real time) or max")
    p.add_argument("--lockstep", action="store_true",
                   help="run only as far as a client grants with MAV_CMD_SIM_ADVANCE (reproducible flights "
                        "from another process; plain MAVSDK / QGC clients cannot drive it)")
    p.add_argument("--home", type=_parse_home, default=GeodeticOrigin(), metavar="LAT,LON[,ALT]",
                   help="WGS84 position of the scene origin (default PX4 SITL's Zurich home)")
    p.add_argument("--signing-key", default=None, metavar="HEX", help="32-byte MAVLink 2 signing key, 64 hex digits")
    p.add_argument("--sign-api-strict", action="store_true", help="also require signed input on the API link")
    p.add_argument("--out", type=Path, default=None, metavar="RUN_DIR", help="run directory (images, captures.jsonl)")
    p.add_argument("--api-port", type=int, default=14540, help="UDP port the API link sends to (0: off)")
    p.add_argument("--gcs-port", type=int, default=14550, help="UDP port the GCS link sends to (0: off)")
    p.add_argument("--api-local-port", type=int, default=None,
                   help="source port of the API link (0: any; default PX4's 14580 + I with --api-port 14540, else any)")
    p.add_argument("--gcs-local-port", type=int, default=None,
                   help="source port of the GCS link (0: any; default PX4's 18570 + I with --gcs-port 14550, else any)")
    p.add_argument("--param", type=_parse_param, action="append", default=[], metavar="NAME=VALUE",
                   help="set a parameter at start (repeatable)")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds of simulation time")
    p.add_argument("--no-ulog", action="store_true", help=f"do not write {ULOG_NAME} (PX4's ULog flight log)")


def config_from_args(args) -> SitlConfig:
    if not 1 <= args.vehicles <= MAX_VEHICLES:
        raise UavsearchError(f"--vehicles must be 1..{MAX_VEHICLES}, got {args.vehicles}")
    if not 0 <= args.instance < 250:
        raise UavsearchError(f"--instance must be 0..249, got {args.instance}")
    last = args.instance + args.vehicles - 1
    # a source port follows its link: PX4's on PX4's ports, any free one once --api-port / --gcs-port move
    if args.api_local_port is None:
        args.api_local_port = SitlConfig.api_local_port if args.api_port == SitlConfig.api_port else 0
    if args.gcs_local_port is None:
        args.gcs_local_port = SitlConfig.gcs_local_port if args.gcs_port == SitlConfig.gcs_port else 0
    for port in (args.api_port, args.gcs_port, args.api_local_port, args.gcs_local_port):
        if not 0 <= port <= 65535 or (port and port != args.gcs_port and port + last > 65535):
            raise UavsearchError(f"UDP port {port} out of range")
    if args.setting is not None and args.scene_file is not None:
        raise UavsearchError("give --setting (a generated family scene) or --scene-file, not both")
    if args.setting is not None:
        from ..world.settings import setting_params

        args.setting = setting_params(args.setting).name  # an unknown family is a one-line error here
        args.cells = setting_params(args.setting).k
    return SitlConfig(
        seed=args.seed,
        scene_seed=None if args.no_camera_scene else args.scene,
        occupied_cells=args.cells,
        scene_file=args.scene_file,
        home=args.home,
        speed=args.speed,
        lockstep=args.lockstep,
        api_port=args.api_port,
        gcs_port=args.gcs_port,
        api_local_port=args.api_local_port,
        gcs_local_port=args.gcs_local_port,
        signing_key=parse_signing_key(args.signing_key) if args.signing_key else None,
        sign_api_strict=args.sign_api_strict,
        run_dir=args.out,
        params=dict(args.param),
        intrinsics=CameraIntrinsics(*args.camera_size, args.camera_hfov),
        setting=args.setting,
        vehicles=args.vehicles,
        instance=args.instance,
        one_api_port=args.one_api_port,
        ulog=not args.no_ulog,
    )


def run_sitl_command(args) -> int:
    if args.out is not None:
        from ..paths import prepare_output

        prepare_output(args.out)
    cfg = config_from_args(args)
    scene = "no camera scene" if cfg.scene_seed is None else f"the camera's scene {cfg.scene_file or cfg.scene_seed}"
    print(f"uavsearch sitl: building the vehicle (JSBSim, estimator) and {scene} ...", flush=True)
    try:
        sitl = Sitl(cfg)
    except ParamError as e:
        raise UavsearchError(str(e)) from None
    print(sitl.banner(), flush=True)
    wall0 = time.monotonic()
    sim0 = sitl.time_s
    stop = []

    def request_stop(signum, _frame):
        stop.append(signum)

    # Explicit handlers: a background job's SIGINT may be ignored by the shell, and SIGTERM should be clean too.
    previous = {s: signal.signal(s, request_stop) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        sitl.run(args.duration, stop=lambda: bool(stop))
    except KeyboardInterrupt:
        pass
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        sitl.close()
        wall = time.monotonic() - wall0
        sim = sitl.time_s - sim0
        links = [l for m in sitl.team for l in m.endpoint.links]
        print(
            f"\nstopped: {sim:.1f} s simulated in {wall:.1f} s wall ({sim / max(wall, 1e-9):.1f}x real time); "
            f"packets in {sum(l.rx_packets for l in links)}, out {sum(l.tx_packets for l in links)}, "
            f"dropped {sum(m.endpoint.rx_dropped for m in sitl.team)}; "
            f"images {sum(m.camera.image_count for m in sitl.team)}",
            flush=True,
        )
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="uavsearch sitl")
    add_sitl_arguments(parser)
    args = parser.parse_args(argv)
    return run_command(run_sitl_command, args, prog="uavsearch sitl")


if __name__ == "__main__":
    sys.exit(main())
