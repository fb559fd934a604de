"""The learned wide-area policy: the search as a map, a score for every viewpoint.

The wide family lets a policy go anywhere next (config.move_set "any"), so the action space is the lattice
itself. `MapPolicyNet` reads the search as planes on the cell grid (MAP_PLANES: the fused p, its uncertainty,
how many views measured each cell from each altitude layer, the highest p any view gave, whether a
lowest-layer view has measured it, the current footprint, the cells any view has seen, and the budget left in
views and in seconds), runs a small fully-convolutional trunk over them (3x3 convolutions with growing
dilation, so a cell's features know its neighbourhood of a few footprints), and scores each viewpoint from
the mean of its footprint's cell features plus what is known of the viewpoint itself (VIEWPOINT_FEATURES:
the rule's descent score, the mean and the uncertainty of the fused p it would see, the flight time to it,
its altitude layer). One small head is shared by every viewpoint, so the net does not learn viewpoints by
index; visited and unaffordable viewpoints are masked (wide_policies.candidates).

Everything comes from search_loop.PolicyInput, so the net flies a vehicle (LiveViews, B = 1) exactly as it
runs on the view cache; train/map_policy.py trains it.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from uavsearch.errors import UavsearchError

from .checkpoints import wide_checkpoint
from .config import SearchConfig, config_from_dict
from .search_loop import PolicyInput, sample_actions
from .wide_policies import binary_entropy, candidates, footprints

MASKED = -1e9  # logit of a forbidden viewpoint: finite, so log p and the entropy stay finite
MAP_PLANES = ("fused", "uncertainty", "views_top", "views_low", "max_p", "low_measured", "here", "seen",
              "views_left", "seconds_left")
VIEWPOINT_FEATURES = ("descent_score", "mean_p", "entropy", "flight_time", "is_low", "is_top")
VIEWS_SCALE = 4.0  # a cell's view count enters as n / 4 (a 70 m lawnmower sees a cell up to ~10 times)
TIME_SCALE_S = 60.0  # flight times enter as seconds / 60
BUDGETS = ("8", "240")  # Table III's two conditions: T = 8 views, or the family's time budget (one net each)


@dataclass(frozen=True)
class MapPolicyConfig:
    """Architecture and the search it was trained for; stored in every checkpoint."""

    search: dict  # config_to_dict of the SearchConfig (lattice, grid, budgets)
    channels: int = 32
    conv_layers: int = 4
    cell_features: int = 16
    hidden: int = 64

    def search_config(self) -> SearchConfig:
        return config_from_dict(self.search)

    @property
    def num_actions(self) -> int:
        return self.search_config().num_actions


class MapPolicyNet(nn.Module):
    """Map planes -> conv trunk -> per-viewpoint logits (module docstring)."""

    KIND = "map"  # the checkpoint's policy kind (policy.save_search_model)

    def __init__(self, cfg: MapPolicyConfig):
        super().__init__()
        self.cfg = cfg
        config = cfg.search_config()
        if config.move_set != "any":
            raise UavsearchError("the map policy chooses viewpoints: it needs a search config with move_set 'any'")
        self.n = config.grid.n
        self.budget_T, self.budget_s = config.budget_T, config.budget_s
        foot = footprints(config).float()  # (P, N)
        self.register_buffer("foot", foot, persistent=False)
        self.register_buffer("foot_mean", foot.T / foot.sum(1).clamp(min=1.0), persistent=False)  # (N, P)
        alts = torch.tensor(config.lattice.positions_enu[:, 2], dtype=torch.float32)
        self.register_buffer("low", alts == alts.min(), persistent=False)
        self.register_buffer("top", alts == alts.max(), persistent=False)
        self.register_buffer("cost", config.lattice.flight_time_t.float() / TIME_SCALE_S, persistent=False)
        layers, c = [], len(MAP_PLANES)
        for i in range(cfg.conv_layers):
            d = 2 ** min(i, 2) if i < cfg.conv_layers - 1 else 1  # dilations 1, 2, 4, ..., 1
            layers += [nn.Conv2d(c, cfg.channels, 3, padding=d, dilation=d), nn.ReLU()]
            c = cfg.channels
        layers += [nn.Conv2d(c, cfg.cell_features, 1), nn.ReLU()]
        self.trunk = nn.Sequential(*layers)
        self.head = nn.Sequential(nn.Conv1d(cfg.cell_features + len(VIEWPOINT_FEATURES), cfg.hidden, 1), nn.ReLU(),
                                  nn.Conv1d(cfg.hidden, 1, 1))

    @torch.no_grad()
    def state(self, inp: PolicyInput) -> tuple[torch.Tensor, torch.Tensor]:
        """(planes (B, MAP_PLANES, n, n), viewpoint features (B, VIEWPOINT_FEATURES, P)) of one decision."""
        if inp.view_probs is None or inp.view_valid is None or inp.view_positions is None:
            raise UavsearchError("the map policy needs the episode's views in PolicyInput (run_search gives them)")
        p, v = inp.view_probs.float(), inp.view_valid.bool()
        low_view = self.low[inp.view_positions][..., None] & v  # (B, t+1, N)
        top_view = self.top[inp.view_positions][..., None] & v
        fused = inp.fused.float()
        ent = binary_entropy(fused)
        seen = v.any(1)
        B = fused.shape[0]
        views_left = 1.0 - (inp.step + 1) / max(self.budget_T, 1)
        if inp.time_left_s is not None and self.budget_s:
            secs = (inp.time_left_s.float() / float(self.budget_s))[:, None].expand_as(fused)
        else:
            secs = torch.ones_like(fused)
        planes = torch.stack([
            fused, 4 * fused * (1 - fused), top_view.sum(1) / VIEWS_SCALE, low_view.sum(1) / VIEWS_SCALE,
            torch.where(seen, torch.where(v, p, 0.0).amax(1), torch.zeros_like(fused)),
            low_view.any(1).float(), self.foot[inp.lattice_idx], seen.float(),
            torch.full_like(fused, views_left), secs], 1).reshape(B, len(MAP_PLANES), self.n, self.n)
        open_p = fused * (~low_view.any(1)).float()
        descent = (open_p[:, None, :] * self.foot[None]).amax(-1)  # (B, P) the rule's score
        vp = torch.stack([descent, fused @ self.foot_mean, ent @ self.foot_mean, self.cost[inp.lattice_idx],
                          self.low.float().expand(B, -1), self.top.float().expand(B, -1)], 1)
        return planes, vp

    @staticmethod
    def mask(inp: PolicyInput) -> torch.Tensor:
        """(B, P) bool: the viewpoints it may take (all, where none is left: the loop has ended that episode)."""
        m = candidates(inp)
        return torch.where(m.any(1, keepdim=True), m, torch.ones_like(m))

    def forward(self, planes: torch.Tensor, vp: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Masked logits (B, P) of a batch of states (what training on stored states calls)."""
        cells = self.trunk(planes).flatten(2)  # (B, C, N)
        pooled = cells @ self.foot_mean  # (B, C, P)
        return self.head(torch.cat([pooled, vp], 1))[:, 0].masked_fill(~mask, MASKED)

    def logits(self, inp: PolicyInput) -> torch.Tensor:
        planes, vp = self.state(inp)
        return self(planes, vp, self.mask(inp))

    def act(self, inp: PolicyInput, generator: torch.Generator | None = None, greedy: bool = False):
        return sample_actions(self.logits(inp), generator, greedy)


__all__ = ["BUDGETS", "MAP_PLANES", "VIEWPOINT_FEATURES", "MapPolicyConfig", "MapPolicyNet", "wide_checkpoint"]
