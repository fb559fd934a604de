"""One search loop, two vehicles: observe -> fuse -> choose the next view, for T views.

`run_search(source, agent, T, generator)` is the whole episode of the paper's method (Fig. 2) and of
every baseline, one vehicle on the episode engine (episode.SearchState, which the team and the envs step
too). It is batched over B episodes and differentiable where it must be (the confidence
scores through learned fusion, the policy's log-probabilities), so stage-2 training, the Table II
evaluation and the flying mission controller all run this same function:

- training / evaluation: `CachedViews(view_cache, scene_rows)` looks up the frozen perception's
  outputs per (scene, lattice position); nothing is rendered;
- one live episode (B = 1): `LiveViews(vehicle, perception)` asks any `views.Vehicle` (teleport, or
  the MAVLink vehicle that flies) to capture at the lattice position and runs perception on the image
  against the REPORTED pose's cell labels.

The move rule is the config's `lattice.moves` (search/lattice.py; the gymnasium env steps through it
too): a move that would leave the lattice keeps the camera where it is, the view is re-taken and counts
as a revisit.

A time budget (config.budget_s, simulated seconds of flight, `lattice.flight_time_s` per move; the start
view is free) ends an episode early: after view t it ends when no unvisited viewpoint is affordable in the
time left, or when its policy picks a move it cannot afford. An ended episode takes no more views (its
fused map stays as it was; `Episode.taken` says which views exist) and the batch stops once every episode
has ended. Policies see the time left and the affordable, unvisited viewpoints (PolicyInput.time_left_s,
.allowed). Without budget_s nothing of this runs: the paper's episodes are what they always were.
"""

from __future__ import annotations

from typing import NamedTuple, Protocol

import numpy as np
import torch

from uavsearch.devices import device_of
from uavsearch.errors import UavsearchError

from .config import SearchConfig
from .episode import SLACK_S, Observation, PolicyInput, SearchState, ViewSource, fusion_view
from .fusion import Fusion, FusionViews
from .perception import perceive


# The rewards of Eq. 13-15 (stage 2 trains with these; the env and the flight log report them)
R_TP = 1.0  # per true positive cell of the final map (Eq. 14)
R_FP = -1.0  # per false positive cell of the final map (Eq. 14)
R_RE = -0.5  # per revisit (Eq. 15; the paper leaves its value open, -0.5 trains best here)


def classification_reward(final_map, labels, r_tp: float = R_TP, r_fp: float = R_FP):
    """R_cls of Eq. 14: N_tp R_tp + N_fp R_fp of the map thresholded at 0.5 ((B, N) -> (B,), or (N,) -> ())."""
    pred = final_map > 0.5
    return r_tp * (pred & labels).sum(-1) + r_fp * (pred & ~labels).sum(-1)


def step_rewards(maps, labels, revisit, r_tp: float = R_TP, r_fp: float = R_FP, r_re: float = R_RE,
                 shaped: bool = False):
    """The reward of each view (Eq. 13-15), (B, T): r_re where view t is a revisit, plus R_cls of the last map
    at the last view; their sum is the episode's R_cls + R_re. The one reward of training, the env and the log.

    maps (B, T, N) fused after each view, labels (B, N) bool, revisit (B, T) bool. `shaped`: R_cls is paid
    as it accrues instead, R_cls(map t) - R_cls(map t-1) at view t (the same sum, a denser signal). Without
    `maps` (the env: the map belongs to the learner) only the revisit part; `revisit` may then be a bool.
    """
    r = r_re * revisit + 0.0  # + 0.0: no -0.0 where r_re * False
    if maps is None:
        return r
    if shaped:
        cls = classification_reward(maps, labels[:, None, :], r_tp, r_fp).float()
        return r + torch.diff(cls, dim=1, prepend=torch.zeros_like(cls[:, :1]))
    r[:, -1] += classification_reward(maps[:, -1], labels, r_tp, r_fp).float()
    return r


# --------------------------------------------------------------------------------------------------
# Views in, per-view perception outputs out


class CachedViews:
    """B episodes over cached scenes: `scene_rows[b]` is episode b's row in the view cache.

    With `confidence` (a net whose scores need no gradient: evaluation, rollouts) the scores of each
    (scene, position) are computed once, when an episode of the batch first sees it, instead of once per
    episode and step (and never for positions no episode visits). Cell features come from the cache
    (ViewCache.features_at: from its feature store when it keeps them on disk); with `features` every
    Observation carries them, scores or not.
    """

    def __init__(self, cache, scene_rows, config: SearchConfig | None = None, confidence=None, features: bool = False):
        """`config` defaults to the one the cache was made for (a cache records it)."""
        self.cache, self.features = cache, features
        self.device = cache.occupancy.device  # the cache's: every tensor of its episodes lives there
        rows = scene_rows if isinstance(scene_rows, torch.Tensor) else np.asarray(scene_rows)
        self.rows = torch.as_tensor(rows, dtype=torch.long, device=self.device).reshape(-1)
        self.config = config if config is not None else getattr(cache, "config", None)
        if self.config is None:
            raise UavsearchError("the view cache records no search config; pass the one it was made for")
        self.batch_size = int(self.rows.numel())
        self.labels = cache.occupancy[self.rows]
        if cache.num_positions != self.config.lattice.num_positions:
            raise UavsearchError(f"view cache has {cache.num_positions} positions, the config's lattice "
                                 f"{self.config.lattice.num_positions}")
        self.confidence = confidence
        if confidence is not None:
            uniq, inv = torch.unique(self.rows, return_inverse=True)
            self._rows_u, self._key0 = uniq, inv * cache.num_positions  # score table row of (episode, position 0)
            self._scores = torch.empty(len(uniq) * cache.num_positions, cache.occupancy.shape[-1], device=self.device)
            self._have = torch.zeros(len(self._scores), dtype=torch.bool, device=self.device)

    def _scores_at(self, lattice_idx: torch.Tensor) -> torch.Tensor:
        key = self._key0 + lattice_idx
        new = torch.unique(key[~self._have[key]])
        if len(new):
            P = self.cache.num_positions
            with torch.no_grad():
                self._scores[new] = self.confidence(self.cache.features_at(self._rows_u[new // P], new % P).float())
            self._have[new] = True
        return self._scores[key]

    def observe(self, lattice_idx: torch.Tensor) -> Observation:
        r, p = self.rows, lattice_idx
        c = self.cache
        if self.confidence is not None:
            return Observation(c.log_probs[r, p], c.features_at(r, p).float() if self.features else None,
                               c.global_feature[r, p], c.cell_area_px[r, p], c.valid[r, p], self._scores_at(p))
        f = c.features_at(r, p) if self.features else c.cell_features[r, p]
        return Observation(c.log_probs[r, p], f.float(), c.global_feature[r, p],
                           c.cell_area_px[r, p], c.valid[r, p])


    def fusion_views(self, lattice_idx: torch.Tensor) -> FusionViews:
        """The views at (B, T) lattice positions as one fusion batch (a trainer's loss re-fuses them); the cell
        features of each distinct (scene, position) once, indexed by feature_rows."""
        c, P = self.cache, self.cache.num_positions
        r = self.rows[:, None].expand_as(lattice_idx)
        uniq, inv = torch.unique(r * P + lattice_idx, return_inverse=True)
        feats = c.features_at(uniq // P, uniq % P).float()  # (U, N, D)
        return FusionViews(c.log_probs[r, lattice_idx][..., 1].exp(), c.valid[r, lattice_idx],
                           c.cell_area_px[r, lattice_idx], feats, None, lattice_idx, self.labels, inv)


class LiveViews:
    """One episode on a vehicle: capture at the lattice position, run perception on the image (B = 1).

    The cell labels come from the pose the vehicle REPORTS, so pose error becomes projection error.
    `views` keeps every captured View (the flight log records them).
    """

    def __init__(self, vehicle, perception, labels=None):
        self.vehicle, self.perception = vehicle, perception.eval()
        self.config: SearchConfig = vehicle.config
        self.batch_size = 1
        self.device = device_of(perception)  # the net's: its outputs, and so the episode, live there
        self.labels = None if labels is None else \
            torch.as_tensor(np.asarray(labels), device=self.device).bool().reshape(1, -1)
        self._lattice = self.config.lattice.positions_enu
        self.views: list = []

    @torch.no_grad()
    def observe(self, lattice_idx: torch.Tensor) -> Observation:
        view = self.vehicle.capture(self._lattice[int(lattice_idx.reshape(-1)[0])])
        self.views.append(view)
        return observe_view(self.perception, view)


@torch.no_grad()
def observe_view(perception, view) -> Observation:
    """Perception on one captured View (B = 1), against the cell labels of the pose it REPORTS."""
    o, valid, area = perceive(perception, [view])
    return Observation(o.log_probs, o.cell_features, o.global_feature, area, valid)


# --------------------------------------------------------------------------------------------------
# The loop


class Policy(Protocol):
    def act(self, inp: PolicyInput, generator: torch.Generator | None) -> tuple[torch.Tensor, torch.Tensor | None,
                                                                                 torch.Tensor | None]:
        """(actions (B,) long, log p(a) (B,) or None, entropy (B,) or None)."""


def sample_actions(logits: torch.Tensor, generator: torch.Generator | None = None, greedy: bool = False):
    """What a learned policy's act() returns from its (B, A) logits: (actions, log p(a), entropy).

    Sampled from the softmax with the caller's generator, or its argmax with `greedy`; masked moves carry a
    large finite negative logit (never -inf, so the entropy stays finite).
    """
    logp_all = torch.log_softmax(logits, dim=-1)
    if greedy:
        a = logits.argmax(-1)
    else:
        a = torch.multinomial(logp_all.exp().detach(), 1, generator=generator).squeeze(-1)
    logp = logp_all.gather(-1, a.unsqueeze(-1)).squeeze(-1)
    entropy = -(logp_all.exp() * logp_all).sum(-1)
    return a, logp, entropy


class Agent(NamedTuple):
    """A row of Table II: a fusion method (a fusion.Fusion, holding its learned part if any) and a policy."""

    fusion: Fusion
    policy: Policy

    @property
    def fusion_name(self) -> str:
        return self.fusion.name


class StepInfo(NamedTuple):
    """What `run_search` reports after view t to its `on_step` hook, before the vehicle moves on."""

    t: int
    viewpoint: torch.Tensor  # (B,) lattice index of view t
    p: torch.Tensor  # (B, N) the view's p(y=1)
    scores: torch.Tensor | None  # (B, N) its confidence scores (learned fusion only)
    valid: torch.Tensor  # (B, N) bool, the view measured the cell
    fused: torch.Tensor  # (B, N) M-bar^t, the map after view t (detached)
    action: torch.Tensor | None  # (B,) the move chosen after view t; None after the last view
    revisit: torch.Tensor  # (B,) bool, view t re-visits a position
    reward: torch.Tensor | None  # (B,) view t's step_rewards; None when the source knows no ground truth
    observation: Observation  # everything else perception said about the view (cell areas, features)


def _step_info(t: int, last: bool, idx, o: Observation, score, fused, action, revisit, labels) -> StepInfo:
    reward = None if labels is None else step_rewards(fused[:, None] if last else None, labels, revisit[:, None])[:, 0]
    return StepInfo(t, idx, o.log_probs[..., 1].exp(), None if score is None else score.detach(), o.valid,
                    fused.detach(), action, revisit, reward, o)


class Episode(NamedTuple):
    """B episodes of T views."""

    lattice_idx: torch.Tensor  # (B, T) position of each view
    actions: torch.Tensor  # (B, T-1)
    log_prob: torch.Tensor | None  # (B, T-1) log p(a^t | s^t), with grad, for learned policies
    entropy: torch.Tensor | None  # (B, T-1)
    revisit: torch.Tensor  # (B, T) bool, view t re-visits a position (False for t = 0)
    maps: torch.Tensor  # (B, T, N) fused p(y=1) after views 0..t; [:, -1] carries grad for learned fusion
    labels: torch.Tensor | None  # (B, N) bool ground truth when the source knows it
    taken: torch.Tensor | None = None  # (B, T) bool, view t was taken (None: every view was; a time budget ends
    # episodes early, and an ended episode's later columns repeat its last position and map)
    flight_s: torch.Tensor | None = None  # (B,) simulated seconds flown (with a time budget)


def _last(view_scores: torch.Tensor | None) -> torch.Tensor | None:
    """The latest view's scores of (B, t+1, N) per-view scores."""
    return None if view_scores is None else view_scores[:, -1]


def run_search(source: ViewSource, agent: Agent, budget_T: int | None = None,
               generator: torch.Generator | None = None, start_idx: int | None = None, on_step=None) -> Episode:
    """Run B episodes of `budget_T` views (default config.budget_T) from the lattice centre: one vehicle on the
    episode engine (episode.SearchState).

    Gradients flow where autograd is enabled: the last fused map w.r.t. the confidence net and the
    log-probabilities w.r.t. a learned policy. Wrap in torch.no_grad() to evaluate.
    `on_step(StepInfo)` is called once the move after view t is chosen and before the next view is taken,
    so a flight log can be written before the vehicle flies on; without it nothing extra is computed.
    """
    config = source.config
    T = int(budget_T or config.budget_T)
    B = source.batch_size
    st = SearchState(config, agent.fusion, B, max_views=T, labels=source.labels, start_idx=start_idx,
                     device=getattr(source, "device", None),
                     view_features=bool(getattr(agent.policy, "reads_view_features", False)))
    timed = st.timed
    lead = torch.zeros(B, dtype=torch.long, device=st.device)  # the one vehicle
    actions, logps, ents, revisits, maps, takens = [], [], [], [], [], []
    for t in range(T):
        live = st.active[:, 0].clone()
        o, revisit = st.take(source, mask=live if timed else None)  # an ended episode's view measures nothing
        revisits.append(revisit)
        maps.append(st.fused)
        takens.append(live)
        view_scores = st.view_scores()
        idx, now, visited = st.positions[-1], st.clock_s[:, 0].clone(), st.visited()
        allowed = None
        if timed:
            allowed = st.choices(visited, idx, now)
            st.stop(lead, ~allowed.any(1))
        if t == T - 1 or not bool(st.active.any()):
            if on_step is not None:
                on_step(_step_info(t, True, idx, o, _last(view_scores), st.fused, None, revisit, source.labels))
            break
        a, lp, ent = agent.policy.act(st.policy_input(idx, visited, now, allowed, view_scores), generator)
        if on_step is not None:
            on_step(_step_info(t, False, idx, o, _last(view_scores), st.fused, a, revisit, source.labels))
        actions.append(a)
        if lp is not None:
            logps.append(lp)
            ents.append(ent)
        nxt = st.moves[idx, a]
        go = st.active[:, 0]
        if timed:  # a move it cannot afford ends the episode where it is
            go = go & (st.cost_s[idx, nxt] <= st.time_left_s(now) + SLACK_S)
            st.stop(lead, ~go)
        st.fly(lead, nxt, go, now)
    empty = torch.zeros(B, 0, device=st.device)
    return Episode(
        lattice_idx=torch.stack(st.positions, 1),
        actions=torch.stack(actions, 1) if actions else empty.long(),
        log_prob=torch.stack(logps, 1) if logps else None,
        entropy=torch.stack(ents, 1) if ents else None,
        revisit=torch.stack(revisits, 1),
        maps=torch.stack(maps, 1),
        labels=source.labels,
        taken=torch.stack(takens, 1) if timed else None,
        flight_s=st.clock_s[:, 0].float() if timed else None,
    )


__all__ = ["Agent", "CachedViews", "Episode", "LiveViews", "Observation", "Policy", "PolicyInput", "ViewSource",
           "R_FP", "R_RE", "R_TP", "classification_reward", "fusion_view", "run_search", "sample_actions"]
__all__ += ["StepInfo", "observe_view", "step_rewards"]
