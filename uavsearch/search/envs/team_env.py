"""The team search as a PettingZoo environment: the vehicles of one team are its agents, on one shared map.

``uavsearch.envs.team_parallel_env(...)`` builds a `TeamSearchEnv` (a ``pettingzoo.ParallelEnv``) and
``uavsearch.envs.team_aec_env(...)`` its AEC form through PettingZoo's own ``parallel_to_aec``; the manual is the
class docstring.

**Which PettingZoo convention, and why.** Vehicles fly at once and each decides when it reaches its viewpoint,
so at any moment one vehicle decides and the others are in flight. Two conventions could say that: only the
deciding agent in the step's dicts, or every live agent in every dict with an action mask. This env takes the
second: a vehicle in flight is alive (it will decide again and its flight still counts), the Parallel API and
its ``parallel_api_test`` expect every live agent in every dict (agents absent for a step read as dead), and
``parallel_to_aec`` then gives each agent its turn as usual. So every step every live vehicle gets an
observation whose ``action_mask`` allows only KEEP_GOING (the last action) while it flies, and the one vehicle
that has just arrived gets the viewpoints it may take (and KEEP_GOING, which for it means: stop here).

**One step is one event** of the episode engine (episode.SearchState, ``team=True``): the vehicle that arrives
first (ties: the lower vehicle) takes its view, the view is fused into the one map, and it chooses its next
viewpoint while the others fly on. Two vehicles arriving at the same second still decide one after the other,
as in `team.run_team`, because the first one's choice is claimed before the second chooses (no two vehicles on
one viewpoint). Stepping the env with a team planner's choices is run_team with that planner, view for view
(tests/test_team_env.py).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from gymnasium.utils import seeding

from ...devices import resolve_device
from ...errors import UavsearchError

try:
    from pettingzoo import ParallelEnv
except ModuleNotFoundError:  # an optional extra
    raise UavsearchError("the team env needs PettingZoo: pip install 'uavsearch[pettingzoo]'") from None
from ..agents import make_fusion
from ..cells import TableSource, cells_observation
from ..config import SearchConfig, setting_config
from ..episode import PolicyInput, SearchState
from ..metrics import map_accuracy, map_f1
from ..search_loop import R_FP, R_TP, step_rewards
from .search_env import SceneViews, cells_space, check_buffered_fusion

# The team task `uavsearch eval team` reports and missions/wide_team.yaml flies: three vehicles for 80 s of
# flight on the wide family. The env fuses by default with the hand-made fusion chosen on validation for that
# task (Bayes, prior 0.5: results/team_wide/hand_made), fast and for any perception; the mission flies the one
# chosen among hand-made and learned, the shipped learned stack's aggregation (TEAM_LEARNED_FUSION:
# results/team_wide), which the env takes too (it reads each view's cell features: several times the cost).
TEAM_SETTING, TEAM_VEHICLES, TEAM_MISSION_TIME_S, TEAM_FUSION = "wide", 3, 80.0, "bayes:0.5"
TEAM_LEARNED_FUSION = "neighbour:models/search_wide_240s_map.pt"
REWARDS = ("shaped", "terminal", "f1")
CREDITS = ("team", "own")


def team_config(setting=TEAM_SETTING, mission_time_s: float = TEAM_MISSION_TIME_S) -> SearchConfig:
    """The family's task as a team searches it: views bounded only by the mission time (eval team's config)."""
    config = setting_config(setting)
    return dataclasses.replace(config, budget_T=config.lattice.num_positions, budget_s=float(mission_time_s))


class TeamSearchEnv(ParallelEnv):
    """A team of vehicles searching one scene of a family on one shared map, in teleport mode (PettingZoo Parallel).

    **Agents.** ``vehicle_0`` ... ``vehicle_{V-1}`` (system ids 1..V when flown). All start above the lattice
    start; vehicle 0 takes the start view at time 0 (free) and decides first, the others decide at time 0 after
    it, in order. A vehicle is terminated when it stops: it chose KEEP_GOING on arrival, chose a viewpoint it may
    not take (taken, claimed by another vehicle, out of reach in the mission time left: run_team's rule), or has
    nothing left it can reach (then it stops on its own). The episode ends when every vehicle has stopped;
    nothing is truncated.

    **Actions.** ``Discrete(P + 1)``: 0..P-1 the next viewpoint (lattice.py order; P = 73 for the wide family),
    P = KEEP_GOING. Only the deciding vehicle's action counts; the others' are ignored (their mask allows only
    KEEP_GOING).

    **Observation** (per agent, ``Dict``, float32 but the mask): the single env's "cells" observation
    (search_env.ActiveSearchEnv, ``obs="cells"``) for this vehicle, (N, N) maps row 0 north:

    - ``fused`` the team's one map; ``cell_views`` views that measured each cell; ``visits`` (P,) views at each
      viewpoint; ``step`` (P,) one-hot of the team's views so far minus one;
    - ``p_view`` / ``in_view`` this vehicle's latest view; ``position`` (P,) one-hot of its viewpoint (where it
      is flying to while it flies); ``time_left_s`` (1,) the mission time left when it gets there;
    - ``action_mask`` (P + 1,) int8: the deciding vehicle's choices (unvisited, unclaimed, reachable in the time
      left) and KEEP_GOING; a vehicle in flight: KEEP_GOING only;

    and where the others are and are going, listed from the next vehicle on (vehicle v sees v+1, v+2, ... mod V,
    so one network serves every vehicle): ``others_at`` (V-1, P) one-hot of the viewpoint each left from (or
    stands at), ``others_to`` (V-1, P) one-hot of the viewpoint each is flying to (zeros once it stopped),
    ``others_eta_s`` (V-1,) seconds until it arrives there.

    **Reward** (per step, per agent), from `search_loop.step_rewards` (R_tp, R_fp = ``r_tp``, ``r_fp``):
    ``reward="shaped"`` (default) the change of N_tp R_tp + N_fp R_fp of the fused map (threshold 0.5) the step's
    views made (the first step also pays the start view's); ``"terminal"`` that of the final map at the last
    step; ``"f1"`` the change of the fused map's F1 the step's views made (the episode's sum: the final F1, the
    metric the team table reports). ``credit="team"`` (default): every live agent gets the team's reward;
    ``"own"`` (shaped or f1): each view's change goes to the vehicle that took it. An agent's return counts the steps it was alive for.

    **Info** (per agent): ``occupancy`` (N*N,) int8 ground truth, ``f1`` / ``acc`` of the fused map
    (search/metrics.py), ``time_s`` the mission time of this event, ``views`` the team's views so far,
    ``deciding`` whether this agent decides now, ``lattice_index`` its viewpoint, ``scene_seed``.

    **Scenes** come from the family's view caches (``setting`` / ``split`` / ``part`` / ``limit``, as
    WideSearchEnv's; ``cache`` a ViewCache in memory instead); ``reset(seed=s)`` draws a scene from the env's
    RNG, ``options={"scene_seed": S}`` names one of the caches (other keys are ignored).

    **Arguments.** ``vehicles`` (3), ``mission_time_s`` (80): the team task of missions/wide_team.yaml and
    results/team_wide; ``fusion`` (``"bayes:0.5"``, the hand-made one chosen for that task; the mission's is the
    learned stack's aggregation, TEAM_LEARNED_FUSION); ``max_views`` caps the team's views (None); ``part``
    ("train": learn there, evaluate on "val" or "test"); ``device`` where the episode's tensors live.
    """

    metadata = {"name": "uavsearch_team_v0", "render_modes": [], "is_parallelizable": True}

    def __init__(self, setting=TEAM_SETTING, vehicles: int = TEAM_VEHICLES,
                 mission_time_s: float = TEAM_MISSION_TIME_S, fusion: str = TEAM_FUSION, split: str | None = None,
                 part: str = "train", limit: int | None = None, max_views: int | None = None,
                 reward: str = "shaped", credit: str = "team", r_tp: float = R_TP, r_fp: float = R_FP,
                 perception=None, cache_dir=None, cache=None, progress: bool = True, workers: int = 1,
                 device="cpu", render_mode: str | None = None):
        from ...world import settings

        if int(vehicles) < 1 or int(vehicles) > 16:
            raise UavsearchError(f"a team has 1 to 16 vehicles, not {vehicles}")
        if not mission_time_s > 0:
            raise UavsearchError(f"mission_time_s must be positive, not {mission_time_s}")
        if reward not in REWARDS or credit not in CREDITS:
            raise UavsearchError(f"reward must be one of {', '.join(REWARDS)} and credit one of {', '.join(CREDITS)}")
        if reward == "terminal" and credit == "own":
            raise UavsearchError("credit='own' needs a per-view reward, shaped or f1 (a terminal one is the team's)")
        if settings.setting_params(setting).task.mission != "team":
            raise UavsearchError(f"the team env searches a scene family (wide, wide-uniform), not setting {setting!r}")
        self.config = team_config(setting, mission_time_s)
        if cache is not None and getattr(cache, "config", None) is not None:
            self.config = dataclasses.replace(cache.config, budget_T=self.config.budget_T,
                                              budget_s=self.config.budget_s)
        self.setting, self.V, self.mission_time_s = setting, int(vehicles), float(mission_time_s)
        self.max_views = max_views
        self.reward_mode, self.credit, self.r = reward, credit, {"r_tp": float(r_tp), "r_fp": float(r_fp)}
        self.render_mode = render_mode
        self.device = resolve_device(device)
        self.fusion = make_fusion(fusion)
        check_buffered_fusion(self.fusion)
        split = split or settings.setting_params(setting).split
        settings.scene_seeds(setting, split, part)  # a bad split / part is a one-line error now
        self.scenes = SceneViews(setting, split, part, self.config, self.fusion, perception, limit, cache_dir, cache,
                                 progress, workers, self.device)
        self.P, self.N = self.config.lattice.num_positions, self.config.grid.num_cells
        self.KEEP_GOING = self.P
        self.possible_agents = [f"vehicle_{v}" for v in range(self.V)]
        self.agents: list[str] = []
        self._index = {a: v for v, a in enumerate(self.possible_agents)}
        base = dict(cells_space(self.config).spaces)
        base["action_mask"] = spaces.Box(0, 1, (self.P + 1,), np.int8)
        k = self.V - 1
        base["others_at"] = spaces.Box(0.0, 1.0, (k, self.P), np.float32)
        base["others_to"] = spaces.Box(0.0, 1.0, (k, self.P), np.float32)
        base["others_eta_s"] = spaces.Box(0.0, self.mission_time_s, (k,), np.float32)
        self._obs_space = spaces.Dict(base)
        self._act_space = spaces.Discrete(self.P + 1)
        self.np_random, _ = seeding.np_random(None)
        self._st: SearchState | None = None

    # the spaces: one object per agent, every call (PettingZoo's contract)
    @functools.lru_cache(maxsize=None)
    def observation_space(self, agent):
        return self._obs_space

    @functools.lru_cache(maxsize=None)
    def action_space(self, agent):
        return self._act_space

    # ----------------------------------------------------------------------------------------------
    def reset(self, seed: int | None = None, options: dict | None = None):
        if seed is not None:
            self.np_random, _ = seeding.np_random(seed)
        tables = self.scenes.tables
        options = options or {}
        if "scene_seed" in options:
            s = int(options["scene_seed"])
            if s not in self.scenes.seeds:
                raise UavsearchError(f"scene {s} is not in the team env's view caches ({len(self.scenes.seeds)} "
                                     f"scenes of {self.setting} {self.scenes.split}/{self.scenes.part})")
            row = self.scenes.seeds.index(s)
        else:
            row = int(self.np_random.integers(len(self.scenes.seeds)))
        self._row = row
        self._source = TableSource(tables, 1)
        self._source.rows[0] = row
        labels = tables.labels[row][None]
        st = self._st = SearchState(self.config, self.fusion, 1, self.V, max_views=self.max_views,
                                    budget_s=self.mission_time_s, labels=labels, team=True, device=self.device)
        st.fused = torch.zeros_like(st.fused)  # the map before any view, as run_team's
        dev = self.device
        self._from = st.pos[0].clone()  # (V,) the viewpoint each vehicle left from (or stands at)
        self._p_last = torch.zeros(self.V, self.N, device=dev)
        self._valid_last = torch.zeros(self.V, self.N, dtype=torch.bool, device=dev)
        self._cell_views = torch.zeros(self.N, device=dev)
        self._pending = torch.zeros(self.V, dtype=torch.float64)  # rewards earned since the last step
        self._stopped: set[int] = set()
        self._f1 = 0.0  # the F1 of the map before any view (reward="f1")
        self.agents = self.possible_agents[:]
        self._advance()
        return self._observations(self.agents), self._infos(self.agents)

    def step(self, actions: dict):
        if self._st is None or not self.agents:
            raise UavsearchError("call reset() before step(): the episode has ended" if self._st is not None
                                 else "call reset() before step()")
        st, ar = self._st, self._st._ar
        live = list(self.agents)
        agent = self.possible_agents[self._v]
        if agent not in actions:
            raise UavsearchError(f"{agent} decides now (it reached its viewpoint) and was given no action")
        a = int(actions[agent])
        if not 0 <= a <= self.P:
            raise UavsearchError(f"{agent}'s action {a} is not in Discrete({self.P + 1})")
        v = torch.tensor([self._v], device=self.device)
        nxt = torch.tensor([a if a < self.P else -1], device=self.device)
        ok = (nxt >= 0) & self._allowed[ar, nxt.clamp(min=0)]
        st.stop(v, ~ok)
        st.fly(v, nxt, ok, self._now)
        if bool(ok[0]):
            self._from[self._v] = self._idx[0]
        else:
            self._stopped.add(self._v)
        self._advance()
        done = not bool(st.active.any())
        if self.reward_mode == "terminal":
            team = float(step_rewards(st.fused[:, None], st.labels, torch.zeros(1, 1, dtype=torch.bool),
                                      **self.r)[0, 0]) if done else 0.0
            rew = {a: team for a in live}
        elif self.credit == "team":
            team = float(self._pending.sum())
            rew = {a: team for a in live}
        else:
            rew = {a: float(self._pending[self._index[a]]) for a in live}
        self._pending.zero_()
        term = {a: self._index[a] in self._stopped for a in live}
        trunc = {a: False for a in live}
        obs, infos = self._observations(live), self._infos(live)
        self.agents = [a for a in live if not term[a]]
        return obs, rew, term, trunc, infos

    # ----------------------------------------------------------------------------------------------
    def _advance(self) -> None:
        """Run the engine to the next vehicle that has a choice to make (run_team's event loop): vehicles
        arriving take their view; one with nothing left it can reach stops there."""
        st = self._st
        ar = st._ar
        with torch.no_grad():
            while bool(st.active.any()):
                v, live, now = st.next_vehicle()
                idx = st.pos[ar, v]
                cap = st.capture[ar, v] & live
                if self.max_views is not None:
                    cap &= st.views < self.max_views
                if bool(cap.any()):
                    prev = st.fused.clone()
                    o, _ = st.take(self._source, v, cap)
                    vi = int(v[0])
                    self._p_last[vi], self._valid_last[vi] = o.prob()[0], o.valid[0]
                    self._cell_views += o.valid[0]
                    if self.reward_mode == "f1":
                        f1 = float(map_f1(st.fused.cpu().numpy(), st.labels.cpu().numpy())[0])
                        gain, self._f1 = f1 - self._f1, f1
                    else:
                        gain = float(step_rewards(torch.stack([prev, st.fused], 1), st.labels,
                                                  torch.zeros(1, 2, dtype=torch.bool, device=self.device),
                                                  shaped=True, **self.r)[0, 1])
                    self._pending[vi] += gain
                st.capture[ar, v] = False
                visited = st.visited(v)
                allowed = st.choices(visited, idx, now)
                self._v, self._idx, self._now, self._visited, self._allowed = int(v[0]), idx, now, visited, allowed
                if bool(allowed.any()):
                    return
                st.stop(v, live)
                self._stopped.add(int(v[0]))

    @property
    def deciding_agent(self) -> str | None:
        """The agent whose action counts in the next step (None once the episode has ended)."""
        return self.possible_agents[self._v] if self.agents else None

    def planner_input(self) -> tuple[torch.Tensor, PolicyInput]:
        """(vehicle (1,), PolicyInput) of the deciding vehicle: what run_team gives a team planner here, so a
        planner (agents.make_planner) can act in the env: ``action = nxt if nxt >= 0 else KEEP_GOING``."""
        st = self._st
        return (torch.tensor([self._v], device=self.device),
                st.policy_input(self._idx, self._visited, self._now, self._allowed, st.view_scores()))

    # ----------------------------------------------------------------------------------------------
    def _observations(self, agents) -> dict[str, dict[str, np.ndarray]]:
        st, V, P = self._st, self.V, self.P
        pos, clock = st.pos[0], st.clock_s[0]
        deciding = bool(st.active[0, self._v])
        mask = np.zeros((V, P + 1), np.int8)
        mask[:, P] = 1
        if deciding:
            mask[self._v, :P] = self._allowed[0].cpu().numpy()
        allowed = torch.as_tensor(mask[:, :P], device=self.device).bool()
        step = torch.full((V,), max(int(st.views[0]) - 1, 0), dtype=torch.long)
        cells = cells_observation(self.config, self._p_last, self._valid_last, st.fused.expand(V, -1),
                                  self._cell_views.expand(V, -1), st.visits.expand(V, -1), pos, step,
                                  (self.mission_time_s - clock).clamp(min=0.0), allowed)
        now = float(self._now[0])
        flying = st.active[0].clone()
        if deciding:
            flying[self._v] = False
        at = np.eye(P, dtype=np.float32)[self._from.cpu().numpy()]  # (V, P)
        to = np.where(flying.cpu().numpy()[:, None], np.eye(P, dtype=np.float32)[pos.cpu().numpy()], 0.0)
        eta = np.where(flying.cpu().numpy(), (clock - now).clamp(min=0.0).cpu().numpy(), 0.0).astype(np.float32)
        out = {}
        for a in agents:
            v = self._index[a]
            others = [(v + k) % V for k in range(1, V)]
            o = {k: x[v] for k, x in cells.items()}
            o["action_mask"] = mask[v]
            o["others_at"], o["others_to"], o["others_eta_s"] = at[others], to[others].astype(np.float32), eta[others]
            out[a] = o
        return out

    def _infos(self, agents) -> dict[str, dict[str, Any]]:
        st = self._st
        fused, labels = st.fused.cpu().numpy(), st.labels.cpu().numpy()
        base = {"occupancy": labels[0].astype(np.int8), "f1": float(map_f1(fused, labels)[0]),
                "acc": float(map_accuracy(fused, labels)[0]), "time_s": float(self._now[0]),
                "views": int(st.views[0]), "scene_seed": int(self.scenes.seeds[self._row])}
        deciding = self.deciding_agent if bool(st.active.any()) else None
        pos = st.pos[0].cpu().numpy()
        return {a: {**base, "occupancy": base["occupancy"].copy(), "deciding": a == deciding,
                    "lattice_index": int(pos[self._index[a]])} for a in agents}

    def render(self):
        return None

    def close(self):
        self._st = None


__all__ = ["CREDITS", "REWARDS", "TEAM_FUSION", "TEAM_MISSION_TIME_S", "TEAM_SETTING", "TEAM_VEHICLES",
           "TeamSearchEnv", "team_config"]
