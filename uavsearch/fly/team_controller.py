"""A scene family's mission flown: `search.team.run_team` on N live vehicles (one for the learned wide-area policy).

The one mission controller (mission_controller.fly) starts the vehicles, takes off, lands and logs; this module
is what differs when a family's team method searches: there is no second team loop here either, `run_team` runs
with `LiveTeamViews` as its view source, the same event loop and planner as the teleport team, with the events
taken in the order of their predicted arrivals:

- every vehicle's next viewpoint is sent the moment the planner chooses it (`dispatch`), the capture taken when
  the vehicle has arrived and settled (`observe`), the mission time read from the vehicles' clock at each
  capture (`mission_time_s`). In lockstep any vehicle's grant runs all of them, so while the controller waits
  for one vehicle the others fly on and their telemetry is read on the same connection; the separation rule
  holds because the planner never gives two vehicles one viewpoint and the simulated vehicles refuse a goto
  within SIM_SEP_DIST of another vehicle;
- recording: one StepRecord per view with the system id that took it (`vehicle`), so replay draws every track;
- a team degrades, it does not stop: a vehicle that cannot go on (MavlinkVehicle.trouble: disarmed, a failsafe
  mode, battery critical; no progress to its goal; its link gone) is named with its reason in one line and leaves
  the search (run_team's VehicleOut): its viewpoint is free again, its views stay in the map, the others fly the
  rest of the mission. Its end state is what it did (end_text); a team of one ends as a one-vehicle flight does.
"""

from __future__ import annotations

import time

import numpy as np

from .errors import FlightError, StepFailed, VehicleDown, VehicleLost
from .vehicle import MavlinkVehicle


class LiveTeamViews:
    """run_team's view source for a flying team (B = 1): vehicle v flies, arrives, captures; perception runs."""

    per_vehicle = True

    def __init__(self, vehicles: list[MavlinkVehicle], perception, labels, config, say=None):
        self.vehicles, self.perception, self.config = vehicles, perception.eval(), config
        self.say = say  # callable(str): the line that names a vehicle leaving the search
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
        try:
            if veh.down is not None:  # it left when it was to be sent on (dispatch)
                raise VehicleDown(veh.down)
            if veh.goal_enu is None or not np.allclose(veh.goal_enu, target):  # not sent there yet: the start view
                veh.begin_goto(target)
            flight = veh.wait_arrived()
        except VehicleLost:  # the vehicle process is gone: every vehicle with it
            raise
        except FlightError as e:
            if len(self.vehicles) == 1:
                raise
            self._leave(veh, e)
        view = veh.capture_here(target, flight, wall0)
        o = observe_view(self.perception, view)
        self.last = (v, o)
        return o

    def _leave(self, veh: MavlinkVehicle, e: FlightError):
        """Vehicle `veh` leaves the search for `e`: one line naming it and why; run_team's VehicleOut."""
        from ..search.team import VehicleOut

        if veh.down is None:
            if isinstance(e, StepFailed):
                veh.down = f"no progress to its goal: {e}"
            else:  # no answer within the wall-clock backstop
                veh.down, veh.link_lost = f"lost link: {e}", True
        left = sum(v.down is None for v in self.vehicles)
        t = veh.sim_time_s
        when = "" if t is None or self._t0 is None else f" at mission time {t - self._t0:.1f} s"
        if self.say is not None:
            self.say(f"vehicle {veh.target_system} leaves the search{when}: {veh.down}; "
                     f"{left} vehicle{'s' if left != 1 else ''} fly on")
        raise VehicleOut(f"vehicle {veh.target_system}: {veh.down}")

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
        veh = self.vehicles[v]
        if n < 0 or len(self.vehicles) == 1:
            if n >= 0:
                veh.begin_goto(self._lattice[n])
            return
        why = veh.trouble()  # a goto would take it out of its failsafe: it is not sent (observe says why)
        if why is not None:
            veh.leave(why)
            return
        try:
            veh.begin_goto(self._lattice[n])
        except StepFailed as e:  # refused: observe says so when its view comes
            veh.down = f"no progress to its goal: {e}"


class TeamSearch:
    """How a scene family's mission searches (mission_controller.fly asks it): its team planner, or its learned
    wide-area policy on each vehicle, in run_team over LiveTeamViews; the log's team header and summary."""

    names_vehicles = True  # every step line and the end text say which system id
    view_noun = "view"  # what its progress lines call a view
    flown_plan = False  # a team's routes make no one QGroundControl plan (replay draws every track)
    sitl_params: tuple[str, ...] = ()  # the autopilot's defaults (PX4's descent: its landings as recorded)

    def __init__(self, mission, config):
        self.mission, self.config, self.n = mission, config, mission.vehicles
        self.max_views = mission.team.max_views if mission.team is not None else None
        self.method = self.perception = self.views = None

    def load(self, mission, progress) -> None:
        """The fusion and planner (Mission.team_method) and the perception; a line saying what they are."""
        from ..search.perception import load_perception

        self.mission, self.method = mission, mission.team_method(self.config)
        most = f", at most {self.max_views} views" if self.max_views else ""
        progress(f"models    {mission.perception_path.name}, {self.method.description}, mission time "
                 f"{self.config.budget_s:g} s{most}")
        self.perception = load_perception(mission.perception_path)[0].for_grid(self.config.grid.num_cells)

    def header(self) -> dict:
        from ..search.fusion import fusion_name

        c, n = self.config, self.n
        # what replay and its flag checks read: a learned aggregation by the spec that names its checkpoint
        named = str(self.mission.fusion)
        fusion = named if named.startswith("neighbour:") else fusion_name(self.method.fusion)
        return dict(config={"altitude_m": c.altitude_m, "altitudes_m": list(c.layers_m), "budget_s": c.budget_s,
                            "actions": ["viewpoint"]},
                    team={"vehicles": n, "planner": self.mission.policy, "mission_time_s": c.budget_s,
                          "max_views": self.max_views, "system_ids": list(range(1, n + 1))},
                    agent=self.method.description, fusion=fusion, policy=self.mission.policy)

    def at(self, views: int) -> str:
        """Where a failure ended the search, after `views` views."""
        return f"{self.view_noun} {views + 1}"

    def fly(self, vehicles: list[MavlinkVehicle], recorder) -> None:
        from ..search.team import run_team

        self.views = LiveTeamViews(vehicles, self.perception, recorder.labels, self.config, say=recorder.progress)
        run_team(self.views, self.method.fusion, self.method.planner, self.n, float(self.config.budget_s),
                 max_views=self.max_views, on_event=lambda *event: self._event(recorder, *event))
        if all(v.down is not None for v in vehicles):
            raise FlightError("every vehicle left the search: " + "; ".join(
                f"vehicle {v.target_system}: {v.down}" for v in vehicles))

    def _event(self, recorder, vehicle, idx, time_s, taken, fused, next_idx) -> None:
        """run_team's on_event: the view just taken, recorded before the vehicles fly on."""
        if not bool(taken[0]):
            return
        v, o = self.views.last
        veh = self.views.vehicles[v]
        cap, nxt = veh.last_capture, int(next_idx[0])
        rec = recorder.record(cap, fused[0], t=len(recorder.records), lattice_idx=int(idx[0]),
                              p_occ=o.log_probs[0, :, 1].exp().numpy(), valid=o.valid[0].numpy(),
                              cell_area_px=o.cell_area_px[0].numpy(), action=nxt if nxt >= 0 else None,
                              action_name=None if nxt < 0 else f"viewpoint {nxt}", vehicle=veh.target_system)
        e, n, u = cap.reported_position_enu
        then = f" -> viewpoint {nxt}" if nxt >= 0 else " -> done"
        recorder.progress(f"view {len(recorder.records):2d}  vehicle {veh.target_system} at E {e:6.1f} N {n:6.1f} "
                          f"U {u:5.1f} m  mission time {float(time_s[0]):5.1f} s  {recorder.found(rec)}  "
                          f"acc {rec.acc:.2f} F1 {rec.f1:.2f}{then}")

    def summary(self, records: list) -> dict:
        """The summary's own fields, each after the common field that names it; a team that lost a vehicle adds,
        after `end`, how many finished and each vehicle's end state (what it did)."""
        own = {"wall_phases_s": dict(
            mission_time_s=(records[-1].sim_time_s - records[0].sim_time_s) if records else None, vehicles=self.n,
            views_per_vehicle={str(i + 1): sum(r.vehicle == i + 1 for r in records) for i in range(self.n)})}
        vehicles = self.views.vehicles if self.views is not None else []
        if any(v.down is not None for v in vehicles):
            own["end"] = dict(vehicles_finished=sum(v.down is None for v in vehicles),
                              vehicle_ends={str(i + 1): v.end_state or v.down for i, v in enumerate(vehicles)})
        return own


__all__ = ["LiveTeamViews", "TeamSearch"]
