"""The one episode engine: B search episodes x N vehicles, stepped together in array operations.

Every search steps a `SearchState`: the teleport loop (`search_loop.run_search`, one vehicle), the team
(`team.run_team`), the envs (`cells.SearchBatch`, the state of search/envs/) and flight (the same loops with
views that fly). It keeps

- per vehicle its viewpoint and its clock (the mission time at which it arrives there, simulated seconds since
  the start view): the next vehicle to arrive acts (`next_vehicle`; ties: the lower vehicle); a vehicle that
  stops never acts again;
- per episode the views taken at each viewpoint (a view where one was taken is a revisit), the views so far,
  the fused map of the episode's one `Fusion` (search/fusion.py);
- the budgets: views (`max_views`) and seconds of flight (`budget_s`; `lattice.flight_time_s` a move, the
  start view free): `choices` are the viewpoints a vehicle may still take;
- the policy's input: `policy_input` gives the deciding vehicle's `PolicyInput`, the one object every policy
  and team planner reads.

The map is kept one of two ways. The loops step their episodes in lockstep and keep the fusion's running
state (`Fusion.update`; differentiable, stage 2 trains through it). The envs start and end episodes one by
one (`buffered`): each view goes into fixed (B, T, N) float64 buffers and the fusion re-fuses an episode's
views when it takes one, so the map rounds to the same float32 whatever the batch (a vector env equals its
single envs bit for bit). A buffered state lives on the host as numpy arrays, whatever the run's device, and
fuses with `Fusion.fuse_host`: an env step is many small ops, which numpy runs in the calling thread, where
torch would hand each to its intra-op thread pool, whose threads wait for a core whenever another process
keeps one busy (an env beside a learner ran 10-100x slower at torch's default thread count).

A team (`team=True`) keeps viewpoints apart: a vehicle's choices exclude every viewpoint taken or claimed by
another vehicle's flight, and the views the pending flights will take count against `max_views`. One
vehicle alone may choose a viewpoint again (a revisit).
"""

from __future__ import annotations

from typing import NamedTuple, Protocol

import numpy as np
import torch

from .config import SearchConfig
from .fusion import Fusion, FusionViews


class Observation(NamedTuple):
    """What the frozen perception says about one view, batched over episodes."""

    log_probs: torch.Tensor | None  # (B, N, 2); None where the source keeps p only (`p`)
    cell_features: torch.Tensor | None  # (B, N, D) the confidence network's input (None when scores are given)
    global_feature: torch.Tensor | None  # (B, G) the image embedding's input
    cell_area_px: torch.Tensor  # (B, N) F_size
    valid: torch.Tensor  # (B, N) bool: the view measured the cell (c^t)
    scores: torch.Tensor | None = None  # (B, N) confidence scores s_i, if the source precomputed them
    p: torch.Tensor | None = None  # (B, N) p(y=1), where the source keeps it (the envs' cell tables)

    def prob(self) -> torch.Tensor:
        """(B, N) the view's p(y=1)."""
        return self.p if self.p is not None else self.log_probs[..., 1].exp()


class ViewSource(Protocol):
    """Where an episode's views come from: cached perception outputs, or a vehicle plus a perception net.

    `observe(lattice_idx)` gives the view of every episode at its viewpoint (B,). A source whose vehicles fly
    (fly/team_controller.py) says `per_vehicle = True` and is asked `observe(lattice_idx, vehicle)`; it may
    have `mission_time_s(vehicle)` (the capture's time on the vehicles' own clock, which then replaces the
    predicted one) and `dispatch(vehicle, next_idx)` (send the vehicle on as soon as its next viewpoint is
    chosen; -1: it stops).
    """

    config: SearchConfig
    batch_size: int
    labels: torch.Tensor | None  # (B, N) bool ground truth if known (oracle fusion and scoring only)

    def observe(self, lattice_idx: torch.Tensor) -> Observation: ...


class PolicyInput(NamedTuple):
    """Everything a policy may look at before choosing the move after view t (Eq. 9's s^t, unencoded).

    `SearchState.policy_input` builds it; in a team it is the deciding vehicle's."""

    global_feature: torch.Tensor  # (B, G) of the current view
    cells_in_view: torch.Tensor  # (B, N) float c^t
    fused: torch.Tensor  # (B, N) M-bar^t, fused p(y=1) over views 0..t (detached)
    lattice_idx: torch.Tensor  # (B,) current position
    visited: torch.Tensor  # (B, P) bool, positions visited so far (in a team: or claimed by another vehicle)
    step: int  # t, 0 for the start view (in a team: the views so far minus one, the largest over the batch)
    budget_T: int
    # the episode so far, view by view (a policy that reacts to what each view said reads them, e.g.
    # reactive.ReactivePolicyNet)
    view_positions: torch.Tensor | None = None  # (B, t+1) long lattice index of views 0..t
    view_probs: torch.Tensor | None = None  # (B, t+1, N) each view's p(y=1)
    view_valid: torch.Tensor | None = None  # (B, t+1, N) bool, the view measured the cell
    view_scores: torch.Tensor | None = None  # (B, t+1, N) confidence scores (detached), None without learned fusion
    # with a time budget (else None)
    time_left_s: torch.Tensor | None = None  # (B,) simulated seconds of flight left
    allowed: torch.Tensor | None = None  # (B, P) bool: unvisited viewpoints affordable in the time left
    # per-view cell features (B, t+1, N, D), only for a policy that says it reads them (`reads_view_features`)
    # and a source that serves them (CachedViews(features=True), live views); else None
    view_features: torch.Tensor | None = None


def fusion_view(o: Observation, lattice_idx: torch.Tensor, labels: torch.Tensor | None) -> FusionViews:
    """One observed view as a fusion batch of T = 1."""
    def one(x):
        return None if x is None else x.unsqueeze(1)

    return FusionViews(o.prob()[:, None], o.valid[:, None], o.cell_area_px[:, None],
                       one(o.cell_features), one(o.scores), lattice_idx[:, None], labels)


SLACK_S = 1e-9  # a flight that fits the time left to this many seconds is affordable


def host(x) -> np.ndarray:
    """A tensor (on any device) or array-like as a numpy array on the host (a CPU tensor's memory is shared)."""
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def host_observation(o: Observation) -> Observation:
    """What a buffered state keeps of an observation, as numpy arrays: p, valid, pixel areas, scores (and the
    cell features a source gives, which a fusion that reads them sums, `SearchState._buffer`)."""
    f = o.cell_features if o.cell_features is not None and o.cell_features.shape[-1] > 0 else None
    return Observation(None, None if f is None else host(f), None, host(o.cell_area_px), host(o.valid).astype(bool),
                       None if o.scores is None else host(o.scores), host(o.prob()))


class SearchState:
    """B episodes x `vehicles` vehicles of one search (module docstring).

    `max_views` (default config.budget_T) and `budget_s` (None: no time budget; default config.budget_s) are the
    budgets; `labels` (B, N) the ground truth where known (the oracle fusion reads it); `start_idx` the
    viewpoint every vehicle starts above (default the lattice's start); vehicle 0 takes the start view.
    """

    def __init__(self, config: SearchConfig, fusion: Fusion, batch_size: int, vehicles: int = 1, *,
                 max_views: int | None = None, budget_s: float | None = ..., labels: torch.Tensor | None = None,
                 start_idx: int | None = None, team: bool = False, buffered: bool = False, device=None,
                 view_features: bool = False):
        lat = config.lattice
        self.config, self.fusion, self.team, self.buffered = config, fusion, bool(team), bool(buffered)
        self.B, self.V, self.P, self.N = int(batch_size), int(vehicles), lat.num_positions, config.grid.num_cells
        self.max_views = max_views if team else int(max_views or config.budget_T)
        self.budget_s = config.budget_s if budget_s is ... else budget_s
        self.timed = self.budget_s is not None
        self.start_idx = lat.start_index if start_idx is None else int(start_idx)
        B, V, P, N = self.B, self.V, self.P, self.N
        self.device = dev = torch.device("cpu") if device is None else torch.device(device)
        self.last: Observation | None = None  # the latest observation (lockstep)
        if buffered:
            self._init_host(lat, fusion)
            return
        self.cost_s, self.moves = lat.flight_time_t.to(dev), lat.moves.to(dev)  # (P, P) float64 seconds, (P, A)
        self._ar = torch.arange(B, device=dev)
        self.labels = labels if not buffered else torch.zeros(B, N, dtype=torch.bool, device=dev)
        self.pos = torch.full((B, V), self.start_idx, dtype=torch.long, device=dev)
        self.clock_s = torch.zeros(B, V, dtype=torch.float64, device=dev)
        self.capture = torch.zeros(B, V, dtype=torch.bool, device=dev)
        self.capture[:, 0] = True
        self.active = torch.ones(B, V, dtype=torch.bool, device=dev)
        self.visits = torch.zeros(B, P, dtype=torch.long, device=dev)
        self.views = torch.zeros(B, dtype=torch.long, device=dev)
        self.allowed = torch.ones(B, P, dtype=torch.bool, device=dev)
        self.fused = torch.full((B, N), float(fusion.prior), device=dev)
        self.state = fusion.init_state(B, N)
        self.positions: list[torch.Tensor] = []  # per lockstep view: (B,) viewpoint, (B, N) p, (B, N) valid
        self.probs: list[torch.Tensor] = []
        self.valids: list[torch.Tensor] = []
        # kept only when asked: stacking every view's (B, N, D) features costs time nobody else needs
        self.features: list[torch.Tensor] | None = [] if view_features else None

    def _init_host(self, lat, fusion: Fusion) -> None:
        """A buffered state's arrays: the lockstep ones' dtypes, in numpy on the host (module docstring)."""
        B, V, P, N, T = self.B, self.V, self.P, self.N, self.max_views
        self.cost_s, self.moves = host(lat.flight_time_t), host(lat.moves)
        self._ar = np.arange(B)
        self.labels = np.zeros((B, N), dtype=bool)
        self.pos = np.full((B, V), self.start_idx, dtype=np.int64)
        self.clock_s = np.zeros((B, V), dtype=np.float64)
        self.capture = np.zeros((B, V), dtype=bool)
        self.capture[:, 0] = True
        self.active = np.ones((B, V), dtype=bool)
        self.visits = np.zeros((B, P), dtype=np.int64)
        self.views = np.zeros(B, dtype=np.int64)
        self.allowed = np.ones((B, P), dtype=bool)
        self.fused = np.full((B, N), fusion.prior, dtype=np.float32)
        self.hist_p = np.zeros((B, T, N), dtype=np.float64)
        self.hist_valid = np.zeros((B, T, N), dtype=bool)
        self.hist_area = np.zeros((B, T, N), dtype=np.float64)
        self.hist_scores = np.zeros((B, T, N), dtype=np.float64)
        self.hist_viewpoint = np.zeros((B, T), dtype=np.int64)  # where each view was taken (a fusion may read it)
        # a fusion reading cell features: its running summary of them (Fusion.feature_summary, made at the first
        # view), not every view's (B x views x N x D numbers)
        self.feature_summary: list[np.ndarray] | None = None

    # -- the clocks --------------------------------------------------------------------------------

    def next_vehicle(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(vehicle (B,), live (B,), now (B,) float64): the vehicle of each episode that arrives first, whether
        any vehicle is still flying, and the time it arrives (0 where none is)."""
        t_ev = torch.where(self.active, self.clock_s, torch.full_like(self.clock_s, float("inf")))
        v = t_ev.argmin(1)
        live = self.active.any(1)
        return v, live, torch.where(live, t_ev[self._ar, v], torch.zeros(self.B, dtype=torch.float64, device=self.device))

    def time_left_s(self, now: torch.Tensor) -> torch.Tensor:
        """(B,) float64 seconds of the time budget left at mission time `now`."""
        return self.budget_s - now

    # -- views -------------------------------------------------------------------------------------

    def take(self, source, vehicle: torch.Tensor | None = None, mask: torch.Tensor | None = None):
        """The episodes in `mask` (default all) take a view where `vehicle` (B,) (default 0) is and fuse it:
        (the observation, (B,) bool revisit). A lockstep state observes every episode and masks the others
        out; a buffered one re-fuses only the masked episodes."""
        if self.buffered:
            return self._take_host(source, mask)
        idx = self.pos[:, 0].clone() if vehicle is None else self.pos[self._ar, vehicle]
        if "cell_features" in self.fusion.needs and getattr(source, "features", None) is False:
            source.features = True  # a fusion that reads cell features has a cached source serve them
        if vehicle is not None and getattr(source, "per_vehicle", False):
            o = source.observe(idx, vehicle)
        else:
            o = source.observe(idx)
        every = mask is None or bool(mask.all())
        m = torch.ones(self.B, dtype=torch.bool, device=self.device) if mask is None else mask
        if not every:
            o = o._replace(valid=o.valid & m[:, None])
        revisit = (self.visits[self._ar, idx] > 0) & m
        self.state, new = self.fusion.update(self.state, fusion_view(o, idx, self.labels))
        self.fused = new if every else torch.where(m[:, None], new, self.fused)
        self.positions.append(idx)
        self.probs.append(o.prob())
        self.valids.append(o.valid)
        if self.features is not None and o.cell_features is not None and o.cell_features.shape[-1] > 0:
            self.features.append(o.cell_features)
        self.visits[self._ar[m], idx[m]] += 1
        self.views += m.long()
        self.last = o
        return o, revisit

    def _take_host(self, source, mask) -> tuple[Observation, np.ndarray]:
        """`take` of a buffered state (numpy; a source with `observe_host` serves numpy arrays itself)."""
        idx = self.pos[:, 0].copy()
        m = np.ones(self.B, dtype=bool) if mask is None else host(mask).astype(bool)
        observe = getattr(source, "observe_host", None)
        o = observe(idx) if observe is not None else host_observation(source.observe(torch.as_tensor(idx)))
        revisit = (self.visits[self._ar, idx] > 0) & m
        envs = np.flatnonzero(m)
        self._buffer(envs, o, idx)
        self.visits[envs, idx[envs]] += 1
        self.views += m
        self.last = o
        return o, revisit

    def _buffer(self, envs: np.ndarray, o: Observation, idx: np.ndarray) -> None:
        """Episodes `envs` write their view into the buffers at their own index and re-fuse their views (only
        the slots up to the latest view: a later one holds no view, and fusing it changes no bit)."""
        if not len(envs):
            return
        t = self.views[envs]
        self.hist_p[envs, t], self.hist_valid[envs, t] = o.p[envs], o.valid[envs]
        self.hist_area[envs, t] = o.cell_area_px[envs]
        self.hist_viewpoint[envs, t] = idx[envs]
        if o.scores is not None:
            self.hist_scores[envs, t] = o.scores[envs]
        summary = self._sum_features(envs, o, idx) if "cell_features" in self.fusion.needs else None
        k, sel = int(t.max()) + 1, slice(None) if len(envs) == self.B else envs
        views = FusionViews(self.hist_p[sel, :k], self.hist_valid[sel, :k], self.hist_area[sel, :k],
                            scores=self.hist_scores[sel, :k] if o.scores is not None else None,
                            viewpoints=self.hist_viewpoint[sel, :k], labels=self.labels[sel],
                            feature_summary=None if summary is None else tuple(x[sel] for x in summary))
        self.fused[envs] = self.fusion.fuse_host(views)

    def _sum_features(self, envs: np.ndarray, o: Observation, idx: np.ndarray) -> list[np.ndarray] | None:
        """Add the view's summary of cell features (Fusion.feature_summary) to episodes `envs`' running ones;
        without features from the source the fusion's own one-line error says what is missing."""
        if o.cell_features is None:
            return None
        f = torch.as_tensor(o.cell_features[envs][:, None])
        one = FusionViews(torch.as_tensor(o.p[envs][:, None]), torch.as_tensor(o.valid[envs][:, None]),
                          cell_features=f, viewpoints=torch.as_tensor(idx[envs][:, None]))
        parts = [host(x) for x in self.fusion.feature_summary(one)]
        if self.feature_summary is None:
            self.feature_summary = [np.zeros((self.B, *x.shape[1:]), x.dtype) for x in parts]
        for acc, x in zip(self.feature_summary, parts):
            acc[envs] += x
        return self.feature_summary

    def view_scores(self) -> torch.Tensor | None:
        """(B, t+1, N) the confidence scores of the views so far (detached), or None (lockstep)."""
        s = self.fusion.view_scores(self.state)
        return None if s is None else s.detach()

    # -- choices and moves -------------------------------------------------------------------------

    def visited(self, vehicle: torch.Tensor | None = None) -> torch.Tensor:
        """(B, P) bool: viewpoints taken, and in a team those another vehicle is flying to."""
        seen = self.visits > 0
        if not self.team:
            return seen
        claimed = torch.zeros_like(seen)
        for u in range(self.V):
            other = self.active[:, u] & self.capture[:, u] & (u != vehicle)
            claimed[self._ar[other], self.pos[other, u]] = True
        return seen | claimed

    def choices(self, visited: torch.Tensor, idx: torch.Tensor, now: torch.Tensor) -> torch.Tensor:
        """(B, P) bool: the viewpoints not in `visited` that a vehicle at `idx` can reach in the time left (and in a
        team, while views are left once the pending flights have taken theirs)."""
        allowed = ~visited
        if self.timed:
            allowed = allowed & (self.cost_s[idx] <= self.time_left_s(now)[:, None] + SLACK_S)
        if self.team and self.max_views is not None:
            pending = (self.active & self.capture).sum(1)
            allowed &= (self.views + pending < self.max_views)[:, None]
        return allowed

    def policy_input(self, idx: torch.Tensor, visited: torch.Tensor, now: torch.Tensor | None = None,
                     allowed: torch.Tensor | None = None, view_scores=None) -> PolicyInput:
        """The deciding vehicle's input (lockstep): it stands at `idx` (B,); `now` its time (with a time budget)."""
        o, B, N = self.last, self.B, self.N
        have = bool(self.positions)
        return PolicyInput(
            global_feature=o.global_feature if o is not None else None,
            cells_in_view=o.valid.float() if o is not None else torch.zeros(B, N, device=self.device),
            fused=self.fused.detach().float(),
            lattice_idx=idx,
            visited=visited,
            step=max(int(self.views.max()) - 1, 0),
            budget_T=int(self.max_views or self.P),
            view_positions=torch.stack(self.positions, 1) if have else idx[:, None],
            view_probs=torch.stack(self.probs, 1) if have else None,
            view_valid=torch.stack(self.valids, 1) if have else torch.zeros(B, 1, N, dtype=torch.bool, device=self.device),
            view_scores=view_scores,
            time_left_s=self.time_left_s(now).float() if self.timed else None,
            allowed=allowed,
            view_features=torch.stack(self.features, 1) if getattr(self, "features", None) else None,
        )

    def fly(self, vehicle: torch.Tensor, nxt: torch.Tensor, go: torch.Tensor, now: torch.Tensor) -> None:
        """Vehicle `vehicle` (B,) of the episodes in `go` flies to `nxt` (B,), leaving at `now` (B,) float64 and
        arriving a flight time later; it takes a view there."""
        ar, idx = self._ar, self.pos[self._ar, vehicle]
        self.pos[ar[go], vehicle[go]] = nxt[go]
        self.clock_s[ar[go], vehicle[go]] = now[go] + self.cost_s[idx[go], nxt[go]]
        self.capture[ar[go], vehicle[go]] = True

    def stop(self, vehicle: torch.Tensor, mask: torch.Tensor) -> None:
        """Vehicle `vehicle` (B,) of the episodes in `mask` stops: it never acts again in this episode."""
        self.active[self._ar[mask], vehicle[mask]] = False

    # -- episodes that start on their own (buffered) -----------------------------------------------

    def restart(self, envs: np.ndarray, labels: np.ndarray) -> None:
        """Start episodes `envs` (k,) afresh with ground truth `labels` (k, N) bool (a buffered state: numpy)."""
        self.pos[envs] = self.start_idx
        self.clock_s[envs] = 0.0
        self.active[envs] = True
        self.capture[envs] = False
        self.capture[envs, 0] = True
        self.views[envs] = 0
        for buf in (self.visits, self.hist_p, self.hist_valid, self.hist_area, self.hist_scores, self.hist_viewpoint,
                    *(self.feature_summary or ())):
            buf[envs] = 0
        self.labels[envs] = labels

    def ended(self):
        """(B,) bool, after a view (one vehicle): the views are spent, or (time budget) no unvisited viewpoint
        is affordable; sets `allowed` to the affordable unvisited viewpoints."""
        end = self.views >= self.max_views
        if self.timed:
            self.allowed = self.choices(self.visits > 0, self.pos[:, 0], self.clock_s[:, 0])
            end = end | ~self.allowed.any(1)
        return end


__all__ = ["Observation", "PolicyInput", "SLACK_S", "SearchState", "ViewSource", "fusion_view"]
