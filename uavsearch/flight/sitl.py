"""`uavsearch sitl`: the simulated vehicle as a MAVLink system, stepped in lockstep on simulation time.

One loop advances the physics one step at a time; the autopilot (commander + navigator) runs at
`autopilot_hz` and MAVLink I/O (receive, handle, stream) at `io_hz`, both on simulation time, so the
flight is the same for a given seed whatever the pacing. Pacing only decides how long the loop waits:
`--speed 1` keeps simulation time on the wall clock (for ground stations), `--speed N` runs N times
faster, `--speed max` never waits. While waiting, the loop sleeps in select() on the sockets and
answers packets at once, so a real-time vehicle still acknowledges commands within a millisecond.
`--lockstep` hands the clock to one client (see lockstep.py): the simulation runs only as far as that
client has granted, which makes a flight commanded from another process reproducible.
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

from ..errors import UavsearchError, run_command
from ..geometry import CameraIntrinsics, GeodeticOrigin
from ..paths import RUNS_DIR
from .camera import CAPTURE_MIN_FREE_MB, Camera, background_scene_renderer
from .commander import Commander, autopilot_params
from .lockstep import LockstepGate
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


class Sitl:
    """Vehicle + autopilot + camera + MAVLink endpoint, advanced one physics step at a time."""

    def __init__(self, cfg: SitlConfig, vehicle_factory=None, vehicle_params=None, render=None):
        self.cfg = cfg
        mc_params = list(vehicle_params if vehicle_params is not None else _vehicle_params())
        self.params = ParamStore(mc_params, autopilot_params(mc_params), SITL_PARAMS)
        for name, value in cfg.params.items():
            self.params.set(name, value)
        stamp = datetime.now(timezone.utc).strftime("%Y%m%d-%H%M%S")
        self.run_dir = Path(cfg.run_dir) if cfg.run_dir else RUNS_DIR / f"sitl__{cfg.seed}__{stamp}"
        self.run_dir.mkdir(parents=True, exist_ok=True)
        self._close_render = None
        if render is None and cfg.scene_seed is not None:
            spec = None
            if cfg.scene_file is not None:
                from ..world.scene import load_scene  # lazy: ~0.4 s, only for --scene-file

                spec = load_scene(cfg.scene_file)
                cfg.scene_seed = spec.seed
            render, self._close_render = background_scene_renderer(cfg.scene_seed, cfg.occupied_cells, cfg.intrinsics,
                                                                   self.run_dir, seed=cfg.seed, spec=spec)
            self.params.set("SIM_SCENE_SEED", cfg.scene_seed, force=True)
            self.params.set("SIM_SCENE_CELLS", cfg.occupied_cells if spec is None else int(spec.occupancy_array().sum()),
                            force=True)
            self.params.set("SIM_SCENE_HASH", 0 if spec is None else scene_hash(spec), force=True)
        self.vehicle = (vehicle_factory or _default_vehicle)(self.params, cfg)  # the scene builds meanwhile
        self.commander = Commander(self.params, self.vehicle, cfg.home, autopilot_hz=cfg.autopilot_hz)
        self.camera = Camera(self.vehicle, cfg.intrinsics, self.run_dir, render,
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
            raise UavsearchError(f"cannot open the MAVLink UDP ports ({e}); is another sitl running? "
                                 "Choose others with --api-local-port / --gcs-local-port") from None
        if cfg.lockstep:
            self.endpoint.lockstep = LockstepGate()
        self._stop = None
        self._ap_period_us = int(1e6 / cfg.autopilot_hz)
        self._io_period_us = int(1e6 / cfg.io_hz)
        self._next_ap_us = int(self.vehicle.time_us)
        self._next_io_us = int(self.vehicle.time_us)
        self._stream_period_us = int(1e6 / cfg.stream_hz)
        self._next_stream_us = int(self.vehicle.time_us)
        self._wall = time.monotonic()
        self._pace_wall0 = None
        self._pace_sim0 = 0

    @property
    def time_s(self) -> float:
        return self.vehicle.time_us * 1e-6

    def step(self) -> None:
        """One physics step, then the autopilot and I/O when due (simulation time)."""
        v = self.vehicle
        gate = self.endpoint.lockstep
        if gate is not None and v.time_us >= gate.until_us and not self._hold(gate):
            return
        now = v.time_us
        if now >= self._next_ap_us:
            self._next_ap_us = _next_tick(self._next_ap_us, self._ap_period_us, now)
            self.commander.update(self._wall)
        if now >= self._next_io_us:
            self._next_io_us = _next_tick(self._next_io_us, self._io_period_us, now)
            self._wall = time.monotonic()
            self.endpoint.poll(self._wall)
            if now >= self._next_stream_us:
                self._next_stream_us = _next_tick(self._next_stream_us, self._stream_period_us, now)
                self.endpoint.send_streams()
            self._pace()
        v.step()

    def _hold(self, gate: LockstepGate) -> bool:
        """Stand still, answering packets, until a client grants more time; False when asked to stop."""
        while self.vehicle.time_us >= gate.until_us:
            if self._stop is not None and self._stop():
                return False
            self._wall = time.monotonic()
            self.endpoint.hold(self._wall)
            if self.endpoint.wait_readable(0.005 if self.camera.busy else 0.2):  # an image may be on its way
                self._wall = time.monotonic()
                self.endpoint.poll(self._wall)
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
            if self.endpoint.wait_readable(remaining):
                self._wall = time.monotonic()
                self.endpoint.poll(self._wall)
        if time.monotonic() - target > 0.5:  # far behind (a slow machine): do not try to catch up in a burst
            self._pace_wall0, self._pace_sim0 = time.monotonic(), self.vehicle.time_us

    def run(self, duration_s: float | None = None, stop=None) -> None:
        end_us = None if duration_s is None else self.vehicle.time_us + int(duration_s * 1e6)
        self._stop = stop
        while (end_us is None or self.vehicle.time_us < end_us) and not (stop and stop()):
            self.step()

    def close(self) -> None:
        self.camera.close()  # the images in flight are written before the renderer goes
        self.endpoint.close()
        if self._close_render:
            self._close_render()
            self._close_render = None

    def banner(self) -> str:
        c = self.cfg
        speed = "max" if not math.isfinite(c.speed) else f"{c.speed:g}x real time"
        if c.lockstep:
            speed += ", lockstep (runs only as far as a client grants)"
        lines = [
            f"uavsearch sitl: sysid {int(self.params['MAV_SYS_ID'])}, seed {c.seed}, "
            f"scene {c.scene_seed if c.scene_seed is not None else 'none'}, speed {speed}",
            f"  home      lat {c.home.lat_deg:.7f}  lon {c.home.lon_deg:.7f}  alt {c.home.alt_m:.1f} m AMSL",
        ]
        for link in self.endpoint.links:
            hint = "MAVSDK: udpin://0.0.0.0:{p}" if link.cfg.name == "api" else "QGC / MAVProxy: udpin:0.0.0.0:{p}"
            lines.append(
                f"  {link.cfg.name.upper()} link  sends to udp {link.cfg.remote_host}:{link.cfg.remote_port} "
                f"from 127.0.0.1:{link.local_port}   ({hint.format(p=link.cfg.remote_port)})"
            )
        sign = "off" if c.signing_key is None else ("required on all links" if c.sign_api_strict
                                                    else "required on GCS link; API link signs, accepts unsigned")
        lines.append(f"  signing   {sign}")
        cam = c.intrinsics
        lines.append(f"  camera    {cam.width_px}x{cam.height_px} px, {cam.hfov_deg:g} deg horizontal FOV, nadir "
                     "(compid 100)")
        lines.append(f"  run dir   {self.run_dir}")
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
    p.add_argument("--api-local-port", type=int, default=14580, help="source port of the API link (0: any)")
    p.add_argument("--gcs-local-port", type=int, default=18570, help="source port of the GCS link (0: any)")
    p.add_argument("--param", type=_parse_param, action="append", default=[], metavar="NAME=VALUE",
                   help="set a parameter at start (repeatable)")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds of simulation time")


def config_from_args(args) -> SitlConfig:
    for port in (args.api_port, args.gcs_port, args.api_local_port, args.gcs_local_port):
        if not 0 <= port <= 65535:
            raise UavsearchError(f"UDP port {port} out of range")
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
        ep = sitl.endpoint
        print(
            f"\nstopped: {sim:.1f} s simulated in {wall:.1f} s wall ({sim / max(wall, 1e-9):.1f}x real time); "
            f"packets in {sum(l.rx_packets for l in ep.links)}, out {sum(l.tx_packets for l in ep.links)}, "
            f"dropped {ep.rx_dropped}; images {sitl.camera.image_count}",
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
