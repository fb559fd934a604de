"""Teams: N vehicles searching one area together, sharing one fused map, on one clock of simulated flight.

`run_team(source, fusion, planner, vehicles, budget_s)` is the team's episode, batched over B episodes like
`run_search`, and the flying team (fly --vehicles N) asks the same planner. It is event-driven on simulated
time, because vehicles fly at once and arrive when their flights end, not in turns:

- every vehicle starts above the lattice start (their homes lie a few metres apart at the centre); vehicle 0
  takes the start view at time 0 (free, as in run_search), the others take theirs where the planner sends them;
- the next event of an episode is the vehicle that arrives first (ties: the lower vehicle); it takes its view,
  the view is fused into the episode's one map, and the planner gives that vehicle its next viewpoint from the
  map, the viewpoints any vehicle has taken or is flying to (never two vehicles on one viewpoint: the
  separation rule), and the seconds of mission time left;
- a vehicle whose planner has nothing it can reach before `budget_s` (or says -1) stops; the episode ends
  when every vehicle has. `max_views` caps the team's views in all;
- a vehicle that cannot go on (a flying source's `observe` raises `VehicleOut`: it fell, a failsafe took it, its
  link is gone) stops there without a view: its viewpoint is no longer claimed, so the others may take it, and
  its views so far stay in the map.

A flying team's source (fly/team_controller.py) has `per_vehicle = True`: `observe(idx, vehicle)` waits for
that vehicle to arrive and captures, and `dispatch(vehicle, next_idx)` sends it on as soon as it is chosen,
so the vehicles fly at once while events are taken in the order of their predicted arrivals; its
`mission_time_s(vehicle)` is the capture's time on the vehicles' own (lockstepped) clock since the start view,
so a flown mission counts its budget in the seconds the vehicles really flew (the lattice's flight times only
predict which viewpoints are still reachable).

Planners (`TeamPlanner.choose(inp, vehicle, generator) -> (B,) viewpoint or -1`) read a PolicyInput whose
`allowed` already excludes taken, claimed and unreachable viewpoints and whose `lattice_idx` is the deciding
vehicle's viewpoint; its `step` is the team's views so far minus one (the largest over the batch), so a
planner must not count its own steps from it:

- `TeamRule` (the wide family's rule for a team): while survey viewpoints are free, the nearest of them; then
  the rule's descent score (wide_policies.DescendRule), optionally per second of flight from here;
- `Partition`: a fixed split of the lattice, each vehicle flying the lowest layer's lawnmower over its strip
  of columns;
- `TeamEntropy`: entropy per second of flight, where the cells another vehicle is about to see count less;
- `EachVehicle(policy)`: any one-vehicle wide policy (entropy per second, random), asked for each vehicle.
"""

from __future__ import annotations

from typing import NamedTuple, Protocol

import torch

from uavsearch.devices import follow
from uavsearch.errors import UavsearchError

from .config import SearchConfig
from .fusion import Fusion
from .episode import PolicyInput, SearchState, ViewSource
from .wide_policies import SURVEY_OUTER_M, DescendRule, argmax_allowed, viewpoints_at


class VehicleOut(UavsearchError):
    """A flying source's vehicle cannot take the view it flew to, nor any later one (the message says why)."""


class TeamPlanner(Protocol):
    def reset(self, batch: int, vehicles: int) -> None: ...

    def choose(self, inp: PolicyInput, vehicle: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
        """(B,) the next viewpoint of `vehicle` (B,) in each episode, or -1: it stops."""


class TeamEpisode(NamedTuple):
    """B episodes of E events (an event: a vehicle reached its viewpoint; it took a view where `taken`)."""

    vehicle: torch.Tensor  # (B, E) long
    lattice_idx: torch.Tensor  # (B, E) viewpoint of the event
    time_s: torch.Tensor  # (B, E) mission time of the event (simulated seconds since the start view)
    taken: torch.Tensor  # (B, E) bool: a view was taken (False: no view, or the episode had ended)
    maps: torch.Tensor  # (B, E, N) fused p after the event
    labels: torch.Tensor | None  # (B, N)
    vehicles: int

    def map_at(self, time_s: float) -> torch.Tensor:
        """(B, N) the fused map of each episode after every view taken by `time_s` (the prior before any)."""
        ok = self.taken & (self.time_s <= time_s + 1e-9)
        last = torch.where(ok, torch.arange(ok.shape[1], device=ok.device), -1).amax(1)  # (B,)
        maps = self.maps[torch.arange(len(last), device=ok.device), last.clamp(min=0)]
        return torch.where((last >= 0)[:, None], maps, torch.zeros_like(maps))

    def views(self) -> torch.Tensor:
        """(B,) views taken."""
        return self.taken.sum(1)


def run_team(source: ViewSource, fusion: Fusion, planner: TeamPlanner, vehicles: int, budget_s: float,
             max_views: int | None = None, generator: torch.Generator | None = None, on_event=None) -> TeamEpisode:
    """B episodes of a team of `vehicles` under a mission time of `budget_s` simulated seconds (module docstring),
    on the episode engine (episode.SearchState).

    `on_event(vehicle, idx, time_s, taken, fused, next_idx)` hears each event once its next viewpoint is
    chosen (a flight log writes it there). Evaluation only: no gradients are kept."""
    config: SearchConfig = source.config
    if vehicles < 1:
        raise UavsearchError(f"a team needs at least one vehicle, got {vehicles}")
    B = source.batch_size
    st = SearchState(config, fusion, B, int(vehicles), max_views=max_views, budget_s=budget_s, labels=source.labels,
                     team=True, device=getattr(source, "device", None),
                     view_features=bool(getattr(planner, "reads_view_features", False)))
    st.fused = torch.zeros_like(st.fused)  # the map before any view (every event 0 takes one)
    ar = st._ar
    planner.reset(B, st.V)
    ev_v, ev_idx, ev_t, ev_taken, ev_maps = [], [], [], [], []
    clock = getattr(source, "mission_time_s", None)  # a flying team: the time the vehicle's own clock says
    with torch.no_grad():
        while bool(st.active.any()):
            v, live, now = st.next_vehicle()
            idx = st.pos[ar, v]
            cap = st.capture[ar, v] & live
            if max_views is not None:
                cap &= st.views < max_views
            if bool(cap.any()):
                try:
                    st.take(source, v, cap)
                except VehicleOut:  # it leaves the team here: no view, its viewpoint free again
                    st.capture[ar, v] = False
                    st.stop(v, cap)
                    ev_v.append(v)
                    ev_idx.append(idx)
                    ev_t.append(now)
                    ev_taken.append(torch.zeros_like(cap))
                    ev_maps.append(st.fused.clone())
                    continue
                if clock is not None:
                    now = torch.where(cap, clock(v).to(now.dtype), now)
            st.capture[ar, v] = False
            visited = st.visited(v)  # the deciding vehicle's choices: nothing taken, claimed, or out of reach
            allowed = st.choices(visited, idx, now)
            nxt = planner.choose(st.policy_input(idx, visited, now, allowed, st.view_scores()), v, generator)
            ok = (nxt >= 0) & live
            ok &= allowed[ar, nxt.clamp(min=0)]
            ev_v.append(v)
            ev_idx.append(idx)
            ev_t.append(now)
            ev_taken.append(cap)
            ev_maps.append(st.fused.clone())
            if on_event is not None:
                on_event(v, idx, now, cap, ev_maps[-1], torch.where(ok, nxt, -1))
            if hasattr(source, "dispatch"):  # a flying team: the vehicle sets off now, the others fly on
                source.dispatch(v, torch.where(ok, nxt, -1))
            st.stop(v, live & ~ok)
            st.fly(v, nxt, ok, now)
    return TeamEpisode(torch.stack(ev_v, 1), torch.stack(ev_idx, 1), torch.stack(ev_t, 1).float(),
                       torch.stack(ev_taken, 1), torch.stack(ev_maps, 1), source.labels, st.V)


# --------------------------------------------------------------------------------------------------
# Planners


class TeamRule:
    """The rule for a team: the survey's free viewpoints first (the nearest), then the descent over the highest
    fused p (DescendRule's score); `per_second`: that score per second of flight from here."""

    def __init__(self, config: SearchConfig, per_second: bool = False, survey_xy_m=SURVEY_OUTER_M):
        self.rule = DescendRule(config, survey_xy_m, per_second_overhead_s=0.0 if per_second else None)
        self.survey = torch.as_tensor(viewpoints_at(config, survey_xy_m, config.layers_m[0]))
        self.cost = config.lattice.flight_time_t.float()

    def reset(self, batch: int, vehicles: int) -> None:
        pass

    def choose(self, inp: PolicyInput, vehicle: torch.Tensor, generator=None) -> torch.Tensor:
        follow(self, inp.allowed.device)
        allowed = inp.allowed
        cost = self.cost[inp.lattice_idx]  # (B, P)
        in_survey = torch.zeros_like(allowed)
        in_survey[:, self.survey] = True
        survey_free = allowed & in_survey
        nearest = argmax_allowed(-cost, survey_free)
        score, pick = self.rule.descend_scores(inp)
        descend = argmax_allowed(self.rule.per_second(score, inp), pick)
        out = torch.where(survey_free.any(1), nearest, descend)
        return torch.where(allowed.any(1), out, -1)


class Partition:
    """A fixed split: vehicle v flies the lowest layer's lawnmower over columns [v L / N, (v + 1) L / N)."""

    def __init__(self, config: SearchConfig):
        self.config = config
        self.routes: list[list[int]] = []
        self.done = None

    def reset(self, batch: int, vehicles: int) -> None:
        lat = self.config.lattice
        L = lat.size
        layer = lat.altitudes_m.index(min(lat.altitudes_m))
        self.routes = []
        for v in range(vehicles):
            cols = list(range(v * L // vehicles, (v + 1) * L // vehicles))
            self.routes.append([layer * L * L + r * L + c for r in range(L)
                                for c in (cols if r % 2 == 0 else cols[::-1])])
        width = max(len(r) for r in self.routes)
        self.table = torch.tensor([r + [-1] * (width - len(r)) for r in self.routes])  # (V, W)
        self.step = torch.zeros(batch, vehicles, dtype=torch.long)

    def choose(self, inp: PolicyInput, vehicle: torch.Tensor, generator=None) -> torch.Tensor:
        follow(self, vehicle.device)
        B = len(vehicle)
        ar = torch.arange(B, device=vehicle.device)
        out = torch.full((B,), -1, dtype=torch.long, device=vehicle.device)
        for _ in range(self.table.shape[1]):  # the next viewpoint of its strip it may still take
            k = self.step[ar, vehicle]
            cand = torch.where(k < self.table.shape[1], self.table[vehicle, k.clamp(max=self.table.shape[1] - 1)], -1)
            ok = (cand >= 0) & inp.allowed[ar, cand.clamp(min=0)]
            out = torch.where((out < 0) & ok, cand, out)
            move_on = (out < 0) & (k < self.table.shape[1])
            if not bool(move_on.any()):
                break
            self.step[ar[move_on], vehicle[move_on]] += 1
        done = out >= 0
        self.step[ar[done], vehicle[done]] += 1
        return out


class TeamEntropy:
    """Entropy per second of flight for a team: each vehicle takes the viewpoint with the most fused-map entropy
    in its footprint per second of flight from here, where a cell inside the footprint of a viewpoint another
    vehicle is flying to counts `1 - shared` as much (it is about to be seen). With one vehicle it is
    wide_policies.EntropyPerSecond."""

    def __init__(self, config: SearchConfig, shared: float = 0.8):
        from .wide_policies import binary_entropy, footprints

        self.entropy = binary_entropy
        self.foot = footprints(config).float()  # (P, N)
        self.cost = torch.as_tensor(config.lattice.flight_time_s, dtype=torch.float32)
        self.shared = float(shared)

    def reset(self, batch: int, vehicles: int) -> None:
        pass

    def choose(self, inp: PolicyInput, vehicle: torch.Tensor, generator=None) -> torch.Tensor:
        follow(self, inp.visited.device)
        taken = torch.zeros_like(inp.visited)
        taken.scatter_(1, inp.view_positions, inp.view_valid.any(-1))  # viewpoints a view measured from
        claimed = inp.visited & ~taken  # where the other vehicles are flying
        soon = (claimed.float() @ self.foot).clamp(max=1.0)  # (B, N) cells about to be seen
        gain = (self.entropy(inp.fused) * (1.0 - self.shared * soon)) @ self.foot.T  # (B, P)
        score = gain / self.cost[inp.lattice_idx].clamp(min=1.0)
        return torch.where(inp.allowed.any(1), argmax_allowed(score, inp.allowed), -1)


class EachVehicle:
    """Any one-vehicle wide policy, asked for whichever vehicle decides."""

    def __init__(self, policy):
        self.policy = policy

    def reset(self, batch: int, vehicles: int) -> None:
        pass

    def choose(self, inp: PolicyInput, vehicle: torch.Tensor, generator=None) -> torch.Tensor:
        a, _, _ = self.policy.act(inp, generator)
        return torch.where(inp.allowed.any(1), a, -1)


__all__ = ["EachVehicle", "Partition", "TeamEntropy", "TeamEpisode", "TeamPlanner", "TeamRule", "VehicleOut",
           "run_team"]
