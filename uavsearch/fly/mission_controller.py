"""The mission controller: one flown search, by one vehicle or a team, on any scene family.

There is no second loop here. A mission's method searches with the teleport loop's own episode, given views that
fly:

- on the paper's settings, its agent (fusion + policy + checkpoints, built by agents.build_agent like every
  agent) in `search_loop.run_search` with `LiveViews(MavlinkVehicle, perception)` (`AgentSearch`, below);
- on a scene family with a team's task, its team planner (or its learned wide-area policy on each vehicle) in
  `search.team.run_team` with live views of N vehicles (team_controller.py).

This module is everything else a flight needs, once for every mission:

- the run directory and its flight log (logs/flight_log.py): mission.json, the header, one StepRecord per view
  written (flushed) before the vehicles fly on (`FlightRecorder`), the failures, the summary;
- the vehicles: by default `uavsearch sitl --vehicles N --one-api-port` as a SEPARATE process (real UDP,
  nothing shared but the run directory), every vehicle's API link on this controller's one free UDP port; one
  MavlinkConnection demultiplexes them by system id (I + 1) into N MavlinkVehicles. With `connect`, vehicles
  someone else started;
- their life cycle: connect, take off together, the search, then land / RTL together even when a step fails.

The only thing taken from outside MAVLink is the TRUE camera pose for the log: the simulated camera
writes it to captures.jsonl beside its images (the file:// URL of CAMERA_IMAGE_CAPTURED says where), and
the controller copies it into each step record (for evaluation and replay; the search never reads it).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import threading
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import MissionError
from ..flight.camera import SCENE_FILE
from ..flight.sitl_process import SitlProcess
from ..logs.flight_log import FlightLogWriter
from ..logs.step_record import StepRecord, TruePose
from ..paths import RUNS_DIR
from ..search.metrics import map_accuracy, map_f1, unseen_cells
from ..world.scene import load_scene
from .connection import MavlinkConnection
from .team_controller import TeamSearch
from .vehicle import FlightError, MavlinkVehicle, StepFailed, VehicleLost, climb_grant

if TYPE_CHECKING:
    from ..search.agents import LoadedAgent

# This module imports no torch (nor the search loop, which does) at import time: `fly` starts the vehicle
# process first and imports them while it starts (1-4 s, the longest part of a mission's start-up).

def _true_pose(camera_dir: Path, index: int) -> TruePose | None:
    """The simulated camera's own record of image `index` (true pose), when the camera keeps one beside its
    images: a vehicle this controller started, or a `uavsearch sitl` reached with --connect on this machine."""
    path = Path(camera_dir) / "captures.jsonl"
    if not path.is_file():
        return None
    with open(path) as f:
        for line in f:
            try:
                rec = json.loads(line)
            except ValueError:
                continue
            if rec.get("index") == index:
                return TruePose(rec.get("true_position_enu_m"), rec.get("true_rpy_rad"))
    return None


def capture_fields(cap, run_dir: Path) -> dict:
    """The StepRecord fields a capture (CaptureInfo) gives: times, waypoint, reported and true pose, image."""
    image = os.path.relpath(cap.image_path, run_dir) if Path(cap.image_path).is_absolute() else cap.image_path
    return dict(sim_time_s=cap.time_boot_s, wall_s=cap.wall_s, flight_time_s=cap.flight_time_s,
                waypoint_enu=cap.waypoint_enu, reported_position_enu=cap.reported_position_enu,
                reported_rpy_rad=cap.reported_rpy_rad, true_pose=_true_pose(cap.camera_dir, cap.index),
                image_index=cap.index, image=image)


@dataclass
class MissionResult:
    run_dir: Path
    status: str  # "completed" | "failed: ..." | "interrupted"
    fused: np.ndarray | None  # (N,) final fused p(occupied)
    labels: np.ndarray  # (N,) ground truth
    acc: float | None
    f1: float | None
    steps: int
    positions: list = field(default_factory=list)  # commanded waypoints (ENU)
    sim_time_s: float | None = None  # vehicle clock from connection to the end action done
    wall_s: float = 0.0  # whole command (incl. starting the vehicle)
    flight_wall_s: float = 0.0  # connection to the end action done
    end: str = ""
    phases: dict = field(default_factory=dict)  # wall seconds since the start at which each stage ended
    photos_asked: int = 0  # IMAGE_START_CAPTURE commands the camera accepted
    photos_received: int = 0  # good captures it answered with


class FlightRecorder:
    """The flight log's step lines: one StepRecord per view, scored against the ground truth and written (flushed)
    before the vehicles fly on; the mission's method gives its own fields and progress line."""

    def __init__(self, log: FlightLogWriter, labels, run_dir: Path, progress):
        self.log, self.run_dir, self.progress = log, run_dir, progress
        self.labels = np.asarray(labels, dtype=bool)
        self.records: list[StepRecord] = []
        self.seen = np.zeros(self.labels.shape, dtype=bool)  # cells some view measured; the others hold the prior

    def record(self, cap, fused, **fields) -> StepRecord:
        """Write the view of capture `cap` (a CaptureInfo) with `fused`, the (N,) map after it."""
        fused = np.asarray(fused.float(), dtype=float)
        rec = StepRecord(**capture_fields(cap, self.run_dir), fused=fused, acc=float(map_accuracy(fused, self.labels)),
                         f1=float(map_f1(fused, self.labels)), **fields)
        self.log.step(rec)
        self.records.append(rec)
        if rec.valid is not None:
            self.seen |= np.asarray(rec.valid, dtype=bool)
        return rec

    def found(self, rec: StepRecord) -> str:
        """The cells the map calls occupied, and the unseen ones with what acc and F1 count them as."""
        f = np.asarray(rec.fused) > 0.5
        unseen = unseen_cells(rec.fused, self.seen)
        return (f"cells found {int(f.sum())} ({int((f & self.labels).sum())} of {int(self.labels.sum())} true)"
                + (f", {unseen}" if unseen else ""))


# The vehicle this controller starts for an agent descends at this speed above MPC_LAND_ALT1 (PX4's
# MPC_Z_VEL_MAX_DN, default 1.5 m/s here, PX4 allows 0.5-4): a 70 m landing takes 29 instead of 59 simulated
# seconds. The search never descends, so its views are the same.
LAND_DESCENT_M_S = 3.0


class AgentSearch:
    """How a mission on one of the paper's settings searches (fly asks it): its agent in run_search over LiveViews,
    on one vehicle; the log's agent header and summary."""

    names_vehicles = False  # one vehicle: its lines and its end text need no system id
    view_noun = "step"  # what its progress lines call a view
    flown_plan = True  # the flown route as a QGroundControl plan (plan_files.write_flown_plan)
    sitl_params = (f"MPC_Z_VEL_MAX_DN={LAND_DESCENT_M_S:g}",)

    def __init__(self, mission, config):
        self.mission, self.config, self.loaded = mission, config, None

    def load(self, mission, progress) -> None:
        self.mission, self.loaded = mission, mission.agent(self.config)

    def header(self) -> dict:
        c = self.config
        return dict(config={"altitude_m": c.altitude_m, "step_m": c.step_m, "budget_T": c.budget_T,
                            "actions": list(c.actions)},
                    agent=self.loaded.description, fusion=self.mission.fusion, policy=self.mission.policy)

    def at(self, views: int) -> str:
        """Where a failure ended the search, after `views` views."""
        return f"{self.view_noun} {views + 1} of {self.config.budget_T}"

    def fly(self, vehicles: list[MavlinkVehicle], recorder: FlightRecorder) -> None:
        import torch

        from ..search.search_loop import LiveViews, run_search

        (vehicle,) = vehicles
        gen = torch.Generator().manual_seed(int(self.mission.policy_seed))
        run_search(LiveViews(vehicle, self.loaded.perception, recorder.labels), self.loaded.agent,
                   self.config.budget_T, generator=gen, on_step=lambda info: self._step(vehicle, info, recorder))

    def _step(self, vehicle: MavlinkVehicle, info, recorder: FlightRecorder) -> None:
        """run_search's on_step: view `info.t` (a search_loop.StepInfo of one episode) and the move after it."""
        cap, t, T = vehicle.last_capture, info.t, self.config.budget_T
        scores = info.scores
        if scores is None and self.loaded.scores_net is not None:  # logged for replay's re-fusion
            scores = self.loaded.scores_net(info.observation.cell_features)
        action = None if info.action is None else int(info.action[0])
        rec = recorder.record(
            cap, info.fused[0], t=t, lattice_idx=int(info.viewpoint[0]), p_occ=info.p[0].numpy(),
            scores=None if scores is None else scores.reshape(-1).numpy(), valid=info.valid[0].numpy(),
            cell_area_px=info.observation.cell_area_px[0].numpy(), action=action,
            action_name=self.config.actions[action] if action is not None else None, revisit=bool(info.revisit[0]),
            reward=None if info.reward is None else float(info.reward[0]))
        e, n, u = cap.reported_position_enu
        nxt = f" -> {rec.action_name}" if action is not None else ""
        recorder.progress(f"step {t + 1}/{T}  at E {e:6.1f} N {n:6.1f} U {u:5.1f} m  flew {cap.flight_time_s:5.1f} s  "
                          f"{recorder.found(rec)}  acc {rec.acc:.2f} F1 {rec.f1:.2f}{nxt}")

    def summary(self, records: list) -> dict:
        """The summary's own fields, each after the common field that names it."""
        return {"steps": {"budget_T": self.config.budget_T},
                "sim_time_s": {"first_view_sim_time_s": records[0].sim_time_s if records else None},
                "wall_phases_s": {"agent": self.loaded.description}}


class _Models:
    """The mission's models, loaded in a thread from fly's start: importing torch is most of a second, which the
    vehicle's start-up, link and arming hide. `result()` waits for them (and raises what their loading raised)."""

    def __init__(self, mission, method, torch_threads: int, progress, phases: dict, wall0: float):
        self._mission, self._error = mission, None
        self._thread = threading.Thread(target=self._load, args=(method, torch_threads, progress, phases, wall0),
                                        name="models", daemon=True)
        self._thread.start()

    def _load(self, method, torch_threads, progress, phases, wall0) -> None:
        try:
            import torch

            torch.set_num_threads(int(torch_threads))
            self._mission = self._mission.check_registry()  # its names, if read without the registry (REGISTRY)
            method.load(self._mission, progress)
            phases["agent_s"] = time.monotonic() - wall0
        except BaseException as e:  # noqa: BLE001 - raised in the flying thread by result()
            self._error = e

    def loaded(self) -> bool:
        self._thread.join()
        return self._error is None

    def result(self):
        """The mission checked against the registry, once its models are loaded."""
        self._thread.join()
        if self._error is not None:
            raise self._error
        return self._mission


def check_vehicle_scene(vehicle: MavlinkVehicle, spec, config, mission_uses_spec_file: bool = False) -> str:
    """What a vehicle we did not start simulates (SIM_SCENE_* parameters, CAMERA_INFORMATION) against the scene
    and camera we score against: a MissionError line on a mismatch, else a note of what was checked."""
    from ..flight.sitl import scene_hash  # lazy: only with --connect
    from ..world.scene import generate_scene

    seed, cells, digest = (vehicle.read_param(n) for n in ("SIM_SCENE_SEED", "SIM_SCENE_CELLS", "SIM_SCENE_HASH"))
    if seed is None:
        return "the vehicle does not report its scene (no SIM_SCENE_SEED): scores assume the mission's scene"
    if seed < 0:
        raise MissionError("the vehicle simulates no scene (started with --no-camera-scene): nothing to search")
    seed, cells, digest = int(seed), int(cells), int(digest)
    want = (spec.seed, int(spec.occupancy_array().sum()))
    mismatch = (seed, cells) != want
    if not mismatch and (digest != 0 or mission_uses_spec_file):
        # a spec file on either side may have been edited: compare the scenes themselves (0: the vehicle
        # generated its scene from seed and cells, as this client can)
        theirs = digest if digest != 0 else scene_hash(generate_scene(seed, cells))
        mismatch = theirs != scene_hash(spec)
        if mismatch:
            what = f"scene {seed} from another spec (hash {theirs}, the mission's {scene_hash(spec)})"
    if mismatch:
        what = what if (seed, cells) == want else f"scene {seed} with {cells} occupied cells"
        raise MissionError(f"the vehicle simulates {what}; the mission scores scene {want[0]} with {want[1]} "
                           "occupied cells: start it with the mission's scene, or fly with --scene")
    info = vehicle.camera_information()
    if info is not None:
        intr = config.intrinsics
        fx = info.focal_length * info.resolution_h / info.sensor_size_h if info.sensor_size_h > 0 else math.nan
        if (info.resolution_h, info.resolution_v) != (intr.width_px, intr.height_px) or not abs(fx - intr.fx) <= 0.01 * intr.fx:
            raise MissionError(f"the vehicle's camera is {info.resolution_h}x{info.resolution_v} px, fx {fx:.1f} px; "
                               f"the models were trained for {intr.width_px}x{intr.height_px} px, fx {intr.fx:.1f} px")
    return f"vehicle simulates scene {want[0]} ({want[1]} occupied cells), camera as trained"


def fly_search(vehicles: list[MavlinkVehicle], method, recorder: FlightRecorder, progress=print,
               phases: dict | None = None, wall0: float = 0.0, before_takeoff=None, arm_first: bool = False) -> str:
    """Connect, take off together, search with `method` (AgentSearch, TeamSearch), every view recorded; returns the
    status. `phases` gets the wall time (since `wall0`) at which the take-off and the search ended;
    `before_takeoff()` runs once the links are up (a MissionError from it ends the mission on the ground);
    `arm_first`: one vehicle is armed before it (fly's own vehicle, while the models finish loading: the same
    commands at the same simulated times as arming at take-off, since the vehicle runs in lockstep)."""
    phases = {} if phases is None else phases
    log, run_dir, lead = recorder.log, recorder.run_dir, vehicles[0]
    try:
        for v in vehicles:
            v.connect()
        if arm_first and len(vehicles) == 1:
            lead.arm()
        phases["armed_s"] = time.monotonic() - wall0
        if before_takeoff is not None:
            before_takeoff()
        phases["models_s"] = time.monotonic() - wall0
        import torch  # loaded by now (fly's models)

        _take_off(vehicles)
        phases["took_off_s"] = time.monotonic() - wall0
        with torch.no_grad():
            method.fly(vehicles, recorder)
        phases["searched_s"] = time.monotonic() - wall0
        return "completed"
    except VehicleLost as e:
        status = f"{VEHICLE_LOST} at {method.at(len(recorder.records))}: {e}"
        _log_failure(log, step=len(recorder.records), error=str(e), sim_time_s=lead.sim_time_s)
    except FlightError as e:  # a step that failed cleanly, or something the vehicle could not do
        full = disk_full(run_dir)
        status = f"failed: {full or e}"
        _log_failure(log, step=len(recorder.records), error=full or str(e), sim_time_s=lead.sim_time_s)
        if isinstance(e, StepFailed) and full is None:  # a full disk is said once, at the end
            progress(f"{method.view_noun} {len(recorder.records) + 1} failed: {e}")
    except OSError as e:  # the run directory's disk: the flight log cannot grow, the vehicles still fly
        full = disk_full(run_dir, e)
        if full is None:
            raise
        status = f"failed: {full}"
    except KeyboardInterrupt as e:  # Ctrl-C, or SIGTERM (errors.Terminated, when the command turns it into one)
        status, why = "interrupted", f"interrupted ({e or 'Ctrl-C'})"
        _log_failure(log, step=len(recorder.records), error=why, sim_time_s=lead.sim_time_s)
        progress(f"{why}: ending the mission")
    return status


def _all(vehicles: list[MavlinkVehicle], cond, what: str, sim_timeout_s: float, tick_s=None):
    """One wait until cond(), on the first vehicle's clock (in lockstep its grants run every vehicle)."""
    lead = vehicles[0]
    return lead.system.wait_until(cond, lead.settings.wall_timeout_s, what, sim_timeout_s=sim_timeout_s,
                                  tick_s=tick_s, say=lead._say)


def _take_off(vehicles: list[MavlinkVehicle]) -> None:
    """Every vehicle is sent up, then one wait until all are there (one vehicle: its own take-off and its lines)."""
    if len(vehicles) == 1:
        vehicles[0].take_off()
        return
    for v in vehicles:
        v.begin_take_off()
    _all(vehicles, lambda: all(v.took_off() for v in vehicles), "take-off of the team",
         vehicles[0].settings.takeoff_timeout_s, tick_s=lambda: climb_grant(vehicles))


def _land(vehicles: list[MavlinkVehicle]) -> list[str]:
    """Every vehicle's end action (land / RTL / none) at once, then one wait until all are disarmed: what each did
    (one vehicle: its own finish(), with its lines). A vehicle that refuses says so in its entry."""
    if len(vehicles) == 1:
        return [vehicles[0].finish()]
    ends = []
    for v in vehicles:
        try:
            ends.append(v.begin_finish())
        except VehicleLost:
            raise
        except FlightError as e:
            ends.append(f"end action failed: {e or type(e).__name__}")
    waiting = [v for v, end in zip(vehicles, ends) if end is None]
    if waiting:
        _all(waiting, lambda: all(v.done_flying() for v in waiting), "landing of the team", 300.0,
             tick_s=waiting[0].settings.land_tick_s)
    ends = [v.end_text() if end is None else end for v, end in zip(vehicles, ends)]
    for v, end in zip(vehicles, ends):
        v.end_state = end
    return ends


VEHICLE_LOST = "vehicle lost"
DISK_FULL_FREE_BYTES = 1 << 20  # less free space than this in the run directory: its disk is full


def disk_full(run_dir: Path, error: OSError | None = None) -> str | None:
    """'no space left on device ...' naming the path and its free space, when that is why things failed."""
    import errno

    if error is not None and error.errno != errno.ENOSPC:
        return None
    try:
        usage = shutil.disk_usage(run_dir)
    except OSError:
        usage = None
    if error is None and (usage is None or usage.free >= DISK_FULL_FREE_BYTES):
        return None
    where = getattr(error, "filename", None) or run_dir
    free = "" if usage is None else f" ({usage.free // 1024} KiB free of {usage.total // 1024} KiB)"
    return f"no space left on device writing {where}{free}"


def _log_failure(log: FlightLogWriter, **fields) -> None:
    """The failure record, unless the disk is too full to take it (the status line says why)."""
    import errno

    try:
        log.failure(**fields)
    except OSError as e:
        if e.errno != errno.ENOSPC:
            raise


def _watch(sitl: SitlProcess):
    """The watchdog a vehicle process gets: VehicleLost, naming how it ended and its log, once it is gone."""

    def check() -> None:
        why = sitl.exit_reason()
        if why is not None:
            raise VehicleLost(f"the vehicle process {why} (its log: {sitl.log_path})")

    return check


# --------------------------------------------------------------------------------------------------
# Starting the simulated vehicle as its own process


def _start_sitl(run_dir: Path, mission, sitl_params, api_port: int, gcs_port: int, progress=None) -> SitlProcess:
    """The simulated vehicles of `mission`, one process (`sitl --vehicles N`, every API link to `api_port`): their
    scene, noise seed, home, pacing and lockstep. Returns at once: they start while the controller loads its
    models (`wait_ready()` before flying)."""
    s, h, c, sc = mission.flight, mission.home, mission.camera, mission.scene
    if mission.spec_path is not None:
        scene = ["--scene-file", str(mission.spec_path)]
    elif sc.setting is not None and sc.occupied_cells is None:  # the family's scene, drawn with its render options
        scene = ["--setting", str(sc.setting), "--scene", str(sc.seed)]
    else:
        scene = ["--scene", str(sc.seed), "--cells", str(sc.k)]
    params = [arg for p in sitl_params for arg in ("--param", p)]
    return SitlProcess(run_dir, "--vehicles", str(mission.vehicles), "--one-api-port", *scene,
                       "--seed", str(s.vehicle_seed), "--home", f"{h.lat_deg},{h.lon_deg},{h.alt_m}", *params,
                       "--camera-hfov", f"{c.hfov_deg:g}", "--camera-size", f"{c.width_px}x{c.height_px}",
                       speed="max" if s.speed == "max" else f"{float(s.speed):g}", lockstep=s.lockstep,
                       api_port=api_port, gcs_port=gcs_port, wait=False, progress=progress)


def _scene_text(mission) -> str:
    if mission.spec_path is not None:
        return f"scene {mission.spec_path}"
    if mission.family is not None:
        return f"{mission.family} scene {mission.scene.seed}"
    return f"scene {mission.scene.seed}, {mission.scene.k} occupied cells"


def default_run_dir(mission) -> Path:
    stamp = datetime.now(timezone.utc).strftime("%Y%m%d-%H%M%S")
    return RUNS_DIR / f"fly__{mission.name}__{stamp}"


def fly(mission, connect: str | None = None, out=None, progress=print, gcs_port: int = 14550,
        torch_threads: int = 1, api_port: int = 0, on_scene=None) -> MissionResult:
    """Fly `mission` with its `mission.vehicles` vehicles: start them (unless `connect` names the link of vehicles
    someone else started), search with the mission's method, land, log; the result scores the one map.

    The vehicle process starts first, so its start-up (imports, physics; its camera's scene is generated
    and built during take-off) runs while this process loads the models. The scene's ground truth (the
    log's labels) is the one the vehicle generated (its scene.json); with `connect`, generated here.
    `torch_threads`: perception on one 224 px image gains nothing from more, and on a 2-core machine two
    threads fight the vehicle process for the cores. `on_scene(spec, labels)` is called once the scene and the
    models are known, before take-off (the CLI starts its end-of-flight comparison there, beside the flight).
    """
    wall0 = time.monotonic()
    phases = {"start_unix": time.time()}  # then: wall seconds since the start at which each stage ended
    config = mission.search_config()
    method = (AgentSearch if mission.family is None else TeamSearch)(mission, config)
    n = mission.vehicles
    run_dir = Path(out) if out else default_run_dir(mission)
    made_run_dir = not run_dir.exists()
    log = FlightLogWriter(run_dir)
    (run_dir / "mission.json").write_text(mission.model_dump_json(indent=2) + "\n")
    try:
        conn = MavlinkConnection(connect or f"udpin:127.0.0.1:{int(api_port)}", tlog=log.tlog)  # 0: any free port
    except FlightError:
        _discard(log, run_dir, made_run_dir)
        raise
    # one System of the link per vehicle: system id I + 1 (one vehicle: the autopilot that heartbeats), images
    # where `uavsearch sitl` keeps them (copied there from a vehicle someone else started)
    vehicles = [MavlinkVehicle(None, config, mission.origin(), mission.flight_settings(), tlog=log.tlog,
                               image_dir=(run_dir if n == 1 else run_dir / f"vehicle{i + 1}") / "images",
                               progress=progress, system_id=None if n == 1 else i + 1, connection=conn)
                for i in range(n)]
    sitl = None
    recorder, status, end, fwall0 = None, "not started", "", None
    try:
        if connect is None:
            port = conn.port.getsockname()[1]
            progress(f"starting uavsearch sitl ({_scene_text(mission)}, {n} vehicle{'s' if n > 1 else ''}, speed "
                     f"{mission.flight.speed}) -> API link udp 127.0.0.1:{port}")
            sitl = _start_sitl(run_dir, mission, method.sitl_params, port, gcs_port, progress)
            for v in vehicles:
                v.watch(_watch(sitl))
        progress(f"models    loading {mission.fusion} fusion + {mission.policy} policy (torch)"
                 + (" while the vehicle starts ..." if sitl is not None else " ..."))
        models = _Models(mission, method, torch_threads, progress, phases, wall0)
        if connect is not None:  # someone else's vehicle: nothing is asked of it before the models are known good
            mission = models.result()
        spec = mission.scene_spec() if sitl is None else load_scene(sitl.wait_file(SCENE_FILE))
        labels = np.asarray(spec.occupancy_array(), dtype=bool)
        phases["scene_s"] = time.monotonic() - wall0
        family = {} if mission.family is None else {"setting": mission.family}
        started = datetime.now(timezone.utc).isoformat()

        def header() -> dict:  # the method's fields once its models are loaded (none if they failed to load)
            return dict(mission=mission.model_dump(mode="json"), mission_file=mission.source, connect=connect,
                        scene={"seed": spec.seed, **family, "occupied_cells": int(labels.sum())},
                        labels=labels.astype(int), grid={"n": config.grid.n, "cell_m": config.grid.cell_m},
                        **(method.header() if models.loaded() else {}), home=mission.home.model_dump(),
                        started_utc=started, tlog_clock="simulated (vehicle time_boot_ms from the start's wall time)")

        log.header_later(header)
        if sitl is not None:
            sitl.wait_ready()
        phases["vehicle_ready_s"] = time.monotonic() - wall0
        fwall0 = time.monotonic()
        recorder = FlightRecorder(log, labels, run_dir, progress)

        def before_takeoff() -> None:  # the models (a MissionError ends the mission on the ground); a vehicle
            nonlocal mission  # someone else started: is it simulating this mission's scene?
            mission = models.result()
            log.write_header()  # before the flight's images take the run folder's disk
            if connect is not None:
                for v in vehicles:
                    progress(check_vehicle_scene(v, spec, config, mission.spec_path is not None))
            if on_scene is not None:  # after the models: their import is not slowed by it
                on_scene(spec, labels)

        try:
            status = fly_search(vehicles, method, recorder, progress, phases=phases, wall0=wall0,
                                before_takeoff=before_takeoff, arm_first=connect is None)
        except KeyboardInterrupt as e:
            status = "interrupted"
            _log_failure(log, step=None, error=f"interrupted ({e or 'Ctrl-C'})", sim_time_s=vehicles[0].sim_time_s)
        except FlightError as e:
            status = f"failed: {e}"
            _log_failure(log, step=None, error=str(e), sim_time_s=vehicles[0].sim_time_s)
        try:
            if status.startswith(VEHICLE_LOST):  # said once, by the caller
                end = f"not landed: {'the' if n == 1 else 'a'} vehicle is gone"
            else:
                ends = _land(vehicles)
                end = "; ".join(f"vehicle {v.target_system}: {e}" if method.names_vehicles else e
                                for v, e in zip(vehicles, ends))
                if any(e != "not flown" for e in ends):
                    progress(end)
        except VehicleLost as e:
            end = f"end action failed: {e}"
            status = status if status.startswith(VEHICLE_LOST) else f"{VEHICLE_LOST} while ending the mission: {e}"
        except FlightError as e:
            end = f"end action failed: {e or type(e).__name__}"
            progress(end)
        except KeyboardInterrupt as e:
            left = ("the vehicle is left as it is" if n == 1 else "the vehicles are left as they are") if connect \
                else "the vehicle process is stopped in the air"
            end = f"end action abandoned: {e or 'Ctrl-C'} again during the {mission.flight.end_action}; {left}"
            progress(end)
        phases["landed_s"] = time.monotonic() - wall0
    finally:
        for v in vehicles:
            v.close()
        conn.close()
        if sitl is not None:
            sitl.stop(wait=False)  # it closes its links and exits on its own; nothing here needs its exit
    if connect is not None and all(v.mode() is None for v in vehicles) and made_run_dir:
        # Nothing answered: no flight happened, so no flight log is left behind to be mistaken for one.
        _discard(log, run_dir, made_run_dir)
        if status == "interrupted":
            raise KeyboardInterrupt
        raise FlightError(f"{status.removeprefix('failed: ')}; nothing flown, no flight log kept "
                          f"(is a vehicle running and sending to {conn.link_text}?)")
    records = recorder.records
    fused = np.asarray(records[-1].fused) if records else None
    acc = None if fused is None else float(map_accuracy(fused, labels))
    f1 = None if fused is None else float(map_f1(fused, labels))
    sims = [v.sim_time_s - v.connected_sim_s for v in vehicles
            if v.sim_time_s is not None and v.connected_sim_s is not None]
    result = MissionResult(
        run_dir=run_dir, status=status, fused=fused, labels=labels, acc=acc, f1=f1, steps=len(records),
        positions=[r.waypoint_enu for r in records], sim_time_s=max(sims) if sims else None,
        wall_s=time.monotonic() - wall0, flight_wall_s=(time.monotonic() - fwall0) if fwall0 else 0.0, end=end,
        phases=phases, photos_asked=sum(v.photos_asked for v in vehicles),
        photos_received=sum(v.photos_received for v in vehicles))
    from .plan_files import write_flown_plan

    common = dict(status=status, end=end, steps=result.steps, acc=acc, f1=f1, fused=fused, labels=labels.astype(int),
                  positions=result.positions, sim_time_s=result.sim_time_s, wall_s=result.wall_s,
                  flight_wall_s=result.flight_wall_s, wall_phases_s=phases, scene_seed=spec.seed,
                  occupied_cells=int(labels.sum()), speed=mission.flight.speed, photos_asked=result.photos_asked,
                  photos_received=result.photos_received)
    own = method.summary(records)
    summary = {k: v for key, value in common.items() for k, v in ((key, value), *own.get(key, {}).items())}
    # the flown search, once the log is closed, as a QGroundControl plan
    return finish_log(log, run_dir, result, summary, after=(lambda: write_flown_plan(run_dir)) if method.flown_plan
                      else None)


def finish_log(log: FlightLogWriter, run_dir: Path, result: MissionResult, summary: dict, after=None) -> MissionResult:
    """Write the summary and close the log (then `after()`); a full disk becomes the result's status, not an
    error, and what was recorded stays."""
    try:
        log.summary(summary)
        log.close()
        if after is not None:
            after()
    except OSError as e:
        full = disk_full(run_dir, e)
        if full is None:
            raise
        if not result.status.startswith("failed: no space"):
            result.status = f"failed: {full}"
            try:  # the summary says so, and what was kept
                log.summary({**summary, "status": result.status})
            except OSError:
                pass
        log.close()
    return result


def _discard(log: FlightLogWriter, run_dir: Path, made: bool) -> None:
    """Close the log and remove the run directory this flight created (only that one)."""
    log.close()
    if made:
        shutil.rmtree(run_dir, ignore_errors=True)


def format_maps(fused, labels, n: int) -> str:
    """The found map beside the ground truth, as text: '#' occupied, '.' empty; in 'found', 'x' marks a miss
    (occupied but not found) and '!' a false alarm."""
    f = np.asarray(fused) > 0.5
    y = np.asarray(labels, dtype=bool)
    lines = [f"{'found':<{2 * n}}   {'truth':<{2 * n}}"]
    for r in range(n):
        a, b = [], []
        for c in range(n):
            i = r * n + c
            a.append("#" if f[i] and y[i] else "!" if f[i] else "x" if y[i] else ".")
            b.append("#" if y[i] else ".")
        lines.append(" ".join(a) + "    " + " ".join(b))
    lines.append("(# occupied, . empty; in 'found': x missed, ! false alarm; north up, row 0 = north)")
    return "\n".join(lines)


__all__ = ["AgentSearch", "FlightRecorder", "LoadedAgent", "MissionResult", "SitlProcess", "fly", "fly_search",
           "format_maps"]
