"""A view-selection policy that reacts to what each view said, and the label-peeking teacher it imitates.

The paper's policy (policy.PolicyNet) sees the fused map as a flat vector and learns to fly one fixed
route. `ReactivePolicyNet` sees the search as a MAP: a stack of planes on the cell grid (fused p, the
highest and lowest p any view gave, how many views measured the cell, their mean confidence score, how
far each cell is from the camera, from the nearest view taken and from each move's target, the step), a
small conv net over it and a small FC head -> logits over the moves. So "the cells the views disagree on
lie to the east" is something a 3x3 filter sees, wherever on the grid it happens.

Moves it may not make are masked: one that would leave the lattice (it would re-take the same view), and
one back to a visited position while a new one is reachable. Everything it reads comes from
search_loop.PolicyInput (run_search fills the episode's history), so it flies a vehicle (LiveViews, B = 1)
exactly as it runs on the view cache.

`LabelGreedyTeacher` peeks at the labels: for each move it fuses the views so far plus the candidate view
(learned fusion, from the view cache) and takes the move whose map scores the most N_tp - N_fp. It is what
train_reactive.py imitates first (DAgger), and an upper bound row for the evaluation (it knows the truth).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from uavsearch.errors import UavsearchError

from .config import SearchConfig, config_from_dict
from .fusion import fuse
from .search_loop import PolicyInput, classification_reward, sample_actions
from .symmetry import index_permutation, mirror_symmetry, square_symmetry

MASKED = -1e9  # logit of a forbidden move: finite, so log p and the entropy stay finite
PLANES = ("fused", "uncertainty", "max_p", "min_p", "views", "score", "last_p", "last_valid", "dist_camera",
          "dist_visited", "dist_move_0", "dist_move_1", "dist_move_2", "dist_move_3", "step")


@dataclass(frozen=True)
class ReactiveConfig:
    """Architecture and the lattice it was trained on; stored in every checkpoint."""

    grid_size: int = 10  # cells per side: the state is a grid_size x grid_size map
    num_positions: int = 25
    num_actions: int = 4
    budget_T: int = 5
    step_m: float = 10.0  # lattice step (the distance planes are in metres)
    channels: int = 32
    conv_layers: int = 3
    hidden: int = 64
    distance_scale_m: float = 50.0  # distances enter as d / scale
    score_scale: float = 4.0  # confidence scores (a few units either side of 0) enter as s / scale
    search: dict | None = None  # config_to_dict of the SearchConfig (None: a checkpoint older than the record)

    def search_config(self) -> SearchConfig:
        """The search config whose lattice the net reads: the recorded one, or the paper's with this step and T."""
        if self.search is not None:
            return config_from_dict(self.search)
        return SearchConfig(step_m=self.step_m, budget_T=self.budget_T)

    @property
    def num_cells(self) -> int:
        return self.grid_size * self.grid_size

    @property
    def in_planes(self) -> int:
        return 10 + self.num_actions + 1


def action_mask(inp: PolicyInput, moves: torch.Tensor) -> torch.Tensor:
    """(B, A) bool, the moves allowed: inside the lattice, and to a new position whenever one is reachable."""
    targets = moves[inp.lattice_idx]
    inside = targets != inp.lattice_idx[:, None]
    new = inside & ~inp.visited.gather(1, targets)
    return torch.where(new.any(1, keepdim=True), new, inside)


class ReactivePolicyNet(nn.Module):
    """Map-shaped state -> conv net -> logits over the moves (see the module docstring)."""

    KIND = "reactive"  # the checkpoint's policy kind (policy.save_search_model)

    def __init__(self, cfg: ReactiveConfig | None = None):
        super().__init__()
        self.cfg = cfg = cfg or ReactiveConfig()
        config = cfg.search_config()
        moves, dist = config.lattice.moves, config.lattice.cell_distances
        if moves.shape != (cfg.num_positions, cfg.num_actions) or dist.shape[1] != cfg.num_cells:
            raise UavsearchError(f"reactive policy config {cfg} does not match the search lattice "
                                 f"({moves.shape[0]} positions, {moves.shape[1]} moves, {dist.shape[1]} cells)")
        self.register_buffer("moves", moves.clone(), persistent=False)
        self.register_buffer("dist", dist.clone() / cfg.distance_scale_m, persistent=False)
        layers, c = [], cfg.in_planes
        for _ in range(cfg.conv_layers):
            layers += [nn.Conv2d(c, cfg.channels, 3, padding=1), nn.ReLU()]
            c = cfg.channels
        self.conv = nn.Sequential(*layers)
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(c * cfg.num_cells, cfg.hidden), nn.ReLU(),
                                  nn.Linear(cfg.hidden, cfg.num_actions))

    @torch.no_grad()
    def state(self, inp: PolicyInput) -> torch.Tensor:
        """(B, in_planes, grid, grid) float: the map the net looks at (PLANES, in order)."""
        if inp.view_probs is None or inp.view_valid is None or inp.view_positions is None:
            raise UavsearchError("the reactive policy needs the episode's views in PolicyInput (run_search gives them)")
        cfg = self.cfg
        p, v = inp.view_probs.float(), inp.view_valid.bool()
        n = v.sum(1)
        seen = n > 0
        zero = torch.zeros_like(inp.fused)
        p_max = torch.where(seen, torch.where(v, p, -1.0).amax(1), zero)
        p_min = torch.where(seen, torch.where(v, p, 2.0).amin(1), zero)
        if inp.view_scores is None:
            score = zero
        else:
            score = torch.where(v, inp.view_scores.float(), 0.0).sum(1) / n.clamp(min=1) / cfg.score_scale
        fused = inp.fused.float()
        planes = [fused, 4 * fused * (1 - fused), p_max, p_min, n.float() / cfg.budget_T, score,
                  torch.where(v[:, -1], p[:, -1], zero), v[:, -1].float(), self.dist[inp.lattice_idx],
                  self.dist[inp.view_positions].amin(1)]
        planes += list(self.dist[self.moves[inp.lattice_idx]].unbind(1))  # (B, N) per move's target
        planes.append(torch.full_like(zero, inp.step / max(cfg.budget_T - 1, 1)))
        return torch.stack(planes, 1).reshape(-1, cfg.in_planes, cfg.grid_size, cfg.grid_size)

    def mask(self, inp: PolicyInput) -> torch.Tensor:
        return action_mask(inp, self.moves)

    def forward(self, state: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Masked logits (B, A) of a batch of states (what training on stored states calls)."""
        return self.head(self.conv(state)).masked_fill(~mask, MASKED)

    def logits(self, inp: PolicyInput) -> torch.Tensor:
        return self(self.state(inp), self.mask(inp))

    def act(self, inp: PolicyInput, generator: torch.Generator | None = None, greedy: bool = False):
        return sample_actions(self.logits(inp), generator, greedy)


def mirror_actions(config: SearchConfig, east_west: bool, north_south: bool, device=None) -> torch.Tensor | None:
    """(A,) long: the move each move becomes when the grid is mirrored (None: the action set is not closed)."""
    perm = index_permutation(config.action_vectors(), mirror_symmetry(east_west, north_south))
    return perm if perm is None or device is None else perm.to(device)


def mirror_states(state: torch.Tensor, mask: torch.Tensor, actions: torch.Tensor, config: SearchConfig,
                  east_west: bool, north_south: bool):
    """A batch of (state, mask, move) as seen in the mirrored world: training data 4x over for free.

    Mirroring the search area east-west (north-south) mirrors every plane and swaps the moves alike (and
    the per-move distance planes with them); a nadir camera over the grid has that symmetry. Returns the
    inputs unchanged when the action set is not closed under the mirror.
    """
    perm = mirror_actions(config, east_west, north_south, state.device)
    if perm is None or not (east_west or north_south):
        return state, mask, actions
    inv = torch.argsort(perm)  # new move b was old move inv[b]
    first = PLANES.index("dist_move_0")
    chans = torch.arange(state.shape[1], device=state.device)
    chans[first:first + len(perm)] = first + inv
    return square_symmetry(state, mirror_symmetry(east_west, north_south))[:, chans], mask[:, inv], perm[actions]


# --------------------------------------------------------------------------------------------------
# The teacher


@torch.no_grad()
def score_table(cache, confidence: nn.Module, chunk: int = 64) -> torch.Tensor:
    """(S, P, N) the confidence net's scores of every (scene, position, cell) of a view cache, in eval mode."""
    was = confidence.training
    confidence.eval()
    out = torch.cat([confidence(cache.cell_features[i:i + chunk]) for i in range(0, cache.num_scenes, chunk)])
    confidence.train(was)
    return out


class LabelGreedyTeacher:
    """One-step lookahead on the labels: the move whose learned-fusion map scores the most N_tp - N_fp.

    `scene_rows[b]` is episode b's row of `cache` (as for search_loop.CachedViews over the same rows);
    `scores`, if given, is score_table(cache, confidence) (computed once for many teachers). Masked like
    ReactivePolicyNet; ties go to a new position, then to the lower action index.
    """

    def __init__(self, cache, scene_rows, confidence: nn.Module, config: SearchConfig | None = None,
                 scores: torch.Tensor | None = None):
        config = config or SearchConfig()
        dev = cache.occupancy.device
        rows = scene_rows if isinstance(scene_rows, torch.Tensor) else np.asarray(scene_rows)
        self.rows = torch.as_tensor(rows, dtype=torch.long, device=dev).reshape(-1)
        uniq, self._inv = torch.unique(self.rows, return_inverse=True)
        self.p = cache.log_probs[uniq][..., 1].exp()  # (U, P, N)
        self.valid = cache.valid[uniq]
        self.scores = scores[uniq] if scores is not None else score_table(cache.subset(uniq.cpu().numpy()), confidence)
        self.labels = cache.occupancy[self.rows]
        self.moves = config.lattice.moves.to(dev)
        A = self.moves.shape[1]
        # tie-breaks below the smallest reward difference (1, N_tp - N_fp is an integer)
        self._tie = 0.01 * torch.arange(A, 0, -1, dtype=torch.float32, device=dev)

    @torch.no_grad()
    def rewards(self, inp: PolicyInput) -> torch.Tensor:
        """(B, A) N_tp - N_fp of the map after each move's view."""
        if inp.view_positions is None:
            raise UavsearchError("the teacher needs the episode's view positions in PolicyInput")
        if inp.view_positions.shape[0] != len(self.rows):
            raise UavsearchError(f"teacher built for {len(self.rows)} episodes, got {inp.view_positions.shape[0]}")
        targets = self.moves[inp.lattice_idx]  # (B, A)
        B, A = targets.shape
        pos = torch.cat([inp.view_positions[:, None, :].expand(B, A, -1), targets[:, :, None]], -1)
        u = self._inv[:, None, None]
        fused = fuse("learned", self.p[u, pos], self.valid[u, pos], scores=self.scores[u, pos])
        return classification_reward(fused, self.labels[:, None, :]).float()

    @torch.no_grad()
    def act(self, inp: PolicyInput, generator: torch.Generator | None = None, greedy: bool = True):
        targets = self.moves[inp.lattice_idx]
        new = ~inp.visited.gather(1, targets)
        key = self.rewards(inp) + 0.5 * new + self._tie
        key = key.masked_fill(~action_mask(inp, self.moves), -np.inf)
        return key.argmax(-1), None, None


__all__ = ["LabelGreedyTeacher", "PLANES", "ReactiveConfig", "ReactivePolicyNet", "action_mask", "mirror_actions",
           "mirror_states", "score_table"]
