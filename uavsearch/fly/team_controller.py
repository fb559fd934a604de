"""Flying a team: a scene family's mission (missions/wide_team.yaml) on N simulated vehicles sharing one map.

There is no second team loop here either: `search.team.run_team` runs with `LiveTeamViews` as its view source,
the same event loop and planner as the teleport team, with the events taken in the order of their predicted
arrivals. What a flight adds:

- the vehicles: `uavsearch sitl --vehicles N --one-api-port` as its own process, every vehicle's API link on
  this controller's one UDP port; one MavlinkConnection demultiplexes them by system id into N
  MavlinkVehicles (system id I + 1). In lockstep any vehicle's grant runs all of them, so while the
  controller waits for one vehicle the others fly on and their telemetry is read on the same connection;
- take-off together (every vehicle is sent up, then one wait for all), each next viewpoint sent the moment
  the planner chooses it (`dispatch`), the capture when the vehicle has arrived and settled (`observe`),
  the mission time read from the vehicles' clock at each capture (`mission_time_s`), landing together; the
  separation rule holds because the planner never gives two vehicles one viewpoint and the simulated vehicles
  refuse a goto within SIM_SEP_DIST of another vehicle;
- recording: one StepRecord per view with the system id that took it (`vehicle`), so replay draws every track.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ..errors import MissionError
from ..flight.camera import SCENE_FILE
from ..flight.sitl_process import SitlProcess
from ..geometry import import_rotation_in_background
from ..logs.flight_log import FlightLogWriter
from ..logs.step_record import StepRecord
from ..search.metrics import map_accuracy, map_f1
from ..world.scene import load_scene
from .connection import MavlinkConnection
from .errors import FlightError, StepFailed, VehicleLost
from .mission_controller import (VEHICLE_LOST, MissionResult, _discard, _log_failure, _watch, capture_fields,
                                  default_run_dir, disk_full, finish_log)
from .vehicle import MavlinkVehicle, climb_grant


class LiveTeamViews:
    """run_team's view source for a flying team (B = 1): vehicle v flies, arrives, captures; perception runs."""

    per_vehicle = True

    def __init__(self, vehicles: list[MavlinkVehicle], perception, labels, config):
        self.vehicles, self.perception, self.config = vehicles, perception.eval(), config
        self.batch_size = 1
        import torch

        self.labels = torch.as_tensor(np.asarray(labels)).bool().reshape(1, -1)
        self._lattice = config.lattice.positions_enu
        self.last = None  # (vehicle index, Observation) of the last capture
        self._t0 = None  # the start view's capture time (vehicle clock)

    def observe(self, lattice_idx, vehicle):
        from ..search.search_loop import observe_view

        v, idx = int(vehicle.reshape(-1)[0]), int(lattice_idx.reshape(-1)[0])
        veh, target = self.vehicles[v], self._lattice[idx]
        wall0 = time.monotonic()
        if veh.goal_enu is None or not np.allclose(veh.goal_enu, target):  # not sent there yet: the start view
            veh.begin_goto(target)
        flight = veh.wait_arrived()
        view = veh.capture_here(target, flight, wall0)
        o = observe_view(self.perception, view)
        self.last = (v, o)
        return o

    def mission_time_s(self, vehicle):
        """(1,) seconds since the start view on the vehicles' shared simulated clock, at the capture just taken
        (the time run_team counts the budget in)."""
        import torch

        t = self.vehicles[int(vehicle.reshape(-1)[0])].last_capture.time_boot_s
        if self._t0 is None:  # the start view
            self._t0 = t
        return torch.tensor([t - self._t0], dtype=torch.float64)

    def dispatch(self, vehicle, next_idx) -> None:
        v, n = int(vehicle.reshape(-1)[0]), int(next_idx.reshape(-1)[0])
        if n >= 0:
            self.vehicles[v].begin_goto(self._lattice[n])


class TeamRecorder:
    """One StepRecord per view of the team (run_team's on_event hook), written before the vehicles fly on."""

    def __init__(self, log, views: LiveTeamViews, labels, run_dir: Path, progress):
        self.log, self.views, self.run_dir, self.progress = log, views, run_dir, progress
        self.labels = np.asarray(labels, dtype=bool)
        self.records: list[StepRecord] = []

    def event(self, vehicle, idx, time_s, taken, fused, next_idx) -> None:
        if not bool(taken[0]):
            return
        v, o = self.views.last
        veh = self.views.vehicles[v]
        cap = veh.last_capture
        f = np.asarray(fused[0].float(), dtype=float)
        nxt = int(next_idx[0])
        acc, f1 = float(map_accuracy(f, self.labels)), float(map_f1(f, self.labels))
        rec = StepRecord(
            t=len(self.records), lattice_idx=int(idx[0]), **capture_fields(cap, self.run_dir),
            p_occ=o.log_probs[0, :, 1].exp().numpy(), valid=o.valid[0].numpy(), cell_area_px=o.cell_area_px[0].numpy(), fused=f, action=nxt if nxt >= 0 else None,
            action_name=None if nxt < 0 else f"viewpoint {nxt}", acc=acc, f1=f1, vehicle=veh.target_system)
        self.log.step(rec)
        self.records.append(rec)
        e, n, u = cap.reported_position_enu
        found, hits = int((f > 0.5).sum()), int(((f > 0.5) & self.labels).sum())
        then = f" -> viewpoint {nxt}" if nxt >= 0 else " -> done"
        self.progress(f"view {len(self.records):2d}  vehicle {veh.target_system} at E {e:6.1f} N {n:6.1f} U {u:5.1f} m"
                      f"  mission time {float(time_s[0]):5.1f} s  cells found {found} ({hits} of "
                      f"{int(self.labels.sum())} true)  F1 {f1:.2f}{then}")


def _start_team_sitl(run_dir: Path, mission, api_port: int, gcs_port: int, progress=None) -> SitlProcess:
    s, h, c = mission.flight, mission.home, mission.camera
    return SitlProcess(run_dir, "--vehicles", str(mission.vehicles), "--one-api-port", "--setting", mission.family,
                       "--scene", str(mission.scene.seed), "--seed", str(s.vehicle_seed),
                       "--home", f"{h.lat_deg},{h.lon_deg},{h.alt_m}",
                       "--camera-hfov", f"{c.hfov_deg:g}", "--camera-size", f"{c.width_px}x{c.height_px}",
                       speed="max" if s.speed == "max" else f"{float(s.speed):g}", lockstep=s.lockstep,
                       api_port=api_port, gcs_port=gcs_port, wait=False, progress=progress)


def _all(vehicles: list[MavlinkVehicle], cond, what: str, sim_timeout_s: float, tick_s: float | None = None,
         status=None):
    """One wait (on the first vehicle's clock: in lockstep its grants run every vehicle) until cond()."""
    lead = vehicles[0]
    return lead.system.wait_until(cond, lead.settings.wall_timeout_s, what, sim_timeout_s=sim_timeout_s,
                                  tick_s=tick_s, status=status, say=lead._say)


def fly_team(mission, connect: str | None = None, out=None, progress=print, gcs_port: int = 14550,
             torch_threads: int = 1) -> MissionResult:
    """Fly a scene family's mission with `mission.vehicles` vehicles (module docstring); the result scores the
    team's one map. The vehicle process starts first; torch and the perception load while it starts."""
    wall0 = time.monotonic()
    phases = {"start_unix": time.time()}
    if mission.family is None:
        raise MissionError("a team flies a scene family's mission (scene.setting: wide)")
    if connect is not None:
        raise MissionError("a scene family's mission starts its own vehicles, one per team member: no --connect")
    n = mission.vehicles
    run_dir = Path(out) if out else default_run_dir(mission)
    made_run_dir = not run_dir.exists()
    log = FlightLogWriter(run_dir)
    (run_dir / "mission.json").write_text(mission.model_dump_json(indent=2) + "\n")
    try:
        conn = MavlinkConnection("udpin:127.0.0.1:0", tlog=log.tlog)
    except FlightError:
        _discard(log, run_dir, made_run_dir)
        raise
    port = conn.port.getsockname()[1]
    progress(f"starting uavsearch sitl: {n} vehicle{'s' if n > 1 else ''}, {mission.family} scene {mission.scene.seed}"
             f", speed {mission.flight.speed} -> API links udp 127.0.0.1:{port}")
    sitl = _start_team_sitl(run_dir, mission, port, gcs_port, progress)
    vehicles: list[MavlinkVehicle] = []
    records, status, ends, fwall0, fused = [], "not started", [], None, None
    labels = None
    try:
        import torch

        from ..search.fusion import fusion_name
        from ..search.perception import load_perception
        from ..search.team import run_team

        torch.set_num_threads(int(torch_threads))
        mission = mission.check_registry()
        config = mission.search_config()
        method = mission.team_method(config)
        max_views = mission.team.max_views if mission.team is not None else None
        progress(f"models    {mission.perception_path.name}, {method.description}, mission time {config.budget_s:g} s"
                 f"{f', at most {max_views} views' if max_views else ''}")
        perception, _ = load_perception(mission.perception_path)
        import_rotation_in_background()  # the first view's pose needs it; the vehicle's start and take-off hide it
        phases["agent_s"] = time.monotonic() - wall0
        vehicles = [MavlinkVehicle(None, config, mission.origin(), mission.flight_settings(), tlog=log.tlog,
                                   progress=progress, system_id=i + 1, connection=conn) for i in range(n)]
        for v in vehicles:
            v.watch(_watch(sitl))
        spec = load_scene(sitl.wait_file(SCENE_FILE))
        labels = np.asarray(spec.occupancy_array(), dtype=bool)
        phases["scene_s"] = time.monotonic() - wall0
        log.header(mission=mission.model_dump(mode="json"), mission_file=mission.source, connect=None,
                   scene={"seed": spec.seed, "setting": mission.family, "occupied_cells": int(labels.sum())},
                   labels=labels.astype(int), grid={"n": config.grid.n, "cell_m": config.grid.cell_m},
                   config={"altitude_m": config.altitude_m, "altitudes_m": list(config.layers_m),
                           "budget_s": config.budget_s, "actions": ["viewpoint"]},
                   team={"vehicles": n, "planner": mission.policy, "mission_time_s": config.budget_s,
                         "max_views": max_views, "system_ids": list(range(1, n + 1))},
                   agent=method.description, fusion=fusion_name(method.fusion),
                   policy=mission.policy, home=mission.home.model_dump(), tlog_clock="simulated")
        sitl.wait_ready()
        phases["vehicle_ready_s"] = time.monotonic() - wall0
        fwall0 = time.monotonic()
        views = LiveTeamViews(vehicles, perception, labels, config)
        rec = TeamRecorder(log, views, labels, run_dir, progress)
        records = rec.records
        try:
            for v in vehicles:
                v.connect()
            for v in vehicles:
                v.begin_take_off()
            _all(vehicles, lambda: all(v.took_off() for v in vehicles), "take-off of the team",
                 vehicles[0].settings.takeoff_timeout_s, tick_s=lambda: climb_grant(vehicles))
            phases["took_off_s"] = time.monotonic() - wall0
            with torch.no_grad():
                run_team(views, method.fusion, method.planner, n, float(config.budget_s), max_views=max_views,
                         on_event=rec.event)
            phases["searched_s"] = time.monotonic() - wall0
            status = "completed"
        except VehicleLost as e:
            status = f"{VEHICLE_LOST} at view {len(records) + 1}: {e}"
            _log_failure(log, step=len(records), error=str(e), sim_time_s=vehicles[0].sim_time_s)
        except (StepFailed, FlightError) as e:
            full = disk_full(run_dir)
            status = f"failed: {full or e}"
            _log_failure(log, step=len(records), error=full or str(e), sim_time_s=vehicles[0].sim_time_s)
        except KeyboardInterrupt:
            status = "interrupted"
            _log_failure(log, step=len(records), error="interrupted (Ctrl-C)", sim_time_s=vehicles[0].sim_time_s)
            progress("interrupted (Ctrl-C): landing the team")
        if not status.startswith(VEHICLE_LOST):
            ends = _land_all(vehicles, progress)
        phases["landed_s"] = time.monotonic() - wall0
    finally:
        for v in vehicles:
            v.close()
        conn.close()
        sitl.stop(wait=False)
    fused = np.asarray(records[-1].fused) if records else None
    lab = labels if labels is not None else np.zeros(0, dtype=bool)
    acc = None if fused is None else float(map_accuracy(fused, lab))
    f1 = None if fused is None else float(map_f1(fused, lab))
    end = "; ".join(ends) if ends else ("not landed: a vehicle is gone" if status.startswith(VEHICLE_LOST) else "")
    sims = [v.sim_time_s - v.connected_sim_s for v in vehicles if v.sim_time_s is not None
            and v.connected_sim_s is not None]
    result = MissionResult(run_dir=run_dir, status=status, fused=fused, labels=lab, acc=acc, f1=f1, steps=len(records),
                           positions=[r.waypoint_enu for r in records], sim_time_s=max(sims) if sims else None,
                           wall_s=time.monotonic() - wall0,
                           flight_wall_s=(time.monotonic() - fwall0) if fwall0 else 0.0, end=end, phases=phases,
                           photos_asked=sum(v.photos_asked for v in vehicles),
                           photos_received=sum(v.photos_received for v in vehicles))
    summary = dict(status=status, end=end, steps=result.steps, acc=acc, f1=f1, fused=fused,
                   labels=lab.astype(int), positions=result.positions, sim_time_s=result.sim_time_s,
                   wall_s=result.wall_s, flight_wall_s=result.flight_wall_s, wall_phases_s=phases,
                   mission_time_s=(records[-1].sim_time_s - records[0].sim_time_s) if records else None,
                   vehicles=n, views_per_vehicle={str(i + 1): sum(r.vehicle == i + 1 for r in records)
                                                  for i in range(n)},
                   scene_seed=mission.scene.seed, occupied_cells=int(lab.sum()), speed=mission.flight.speed,
                   photos_asked=result.photos_asked, photos_received=result.photos_received)
    return finish_log(log, run_dir, result, summary)


def _land_all(vehicles: list[MavlinkVehicle], progress) -> list[str]:
    """Every vehicle's end action at once, then one wait until all are disarmed; what each did."""
    ends, waiting = [], []
    for v in vehicles:
        try:
            done = v.begin_finish()
        except FlightError as e:
            ends.append(f"vehicle {v.target_system}: end action failed: {e}")
            continue
        if done is None:
            waiting.append(v)
        else:
            ends.append(f"vehicle {v.target_system}: {done}")
    if waiting:
        try:
            _all(waiting, lambda: not any(v.armed for v in waiting), "landing of the team", 300.0,
                 tick_s=waiting[0].settings.land_tick_s)
            ends += [f"vehicle {v.target_system}: {v.end_text()}" for v in waiting]
        except FlightError as e:
            ends.append(f"end action failed: {e}")
    progress("; ".join(ends))
    return ends


__all__ = ["LiveTeamViews", "TeamRecorder", "fly_team"]
