"""A policy trained outside uavsearch (PPO on the gymnasium env's "cells" observations) as a search-loop policy.

Stable-Baselines3's and CleanRL's PPO (examples/sb3_ppo.py, examples/cleanrl_ppo.py) train an MLP actor on the
flattened "cells" observation (`cells.flatten_cells`, what ``gymnasium.wrappers.FlattenObservation`` gives).
`ExternalPolicyNet` is that actor: Linear + tanh layers, then the action logits. It rebuilds the observation
from a `search_loop.PolicyInput` with the envs' own `cells.cells_observation`, so `run_search` (evaluation,
flight) shows it exactly what the env showed it in training, fused by the same fusion.

Its checkpoint is a search checkpoint (policy.save_search_model: the fusion it was trained with, the actor's
config and weights, the search config), named ``search_s<K>_<fusion>_external.pt``; `agents.build_agent`
loads it for the "external" policy, and ``uavsearch eval search`` scores it as the "PPO (external)" row.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import nn

from .cells import cells_observation, flatten_cells, observation_keys
from .config import SearchConfig, config_from_dict, config_to_dict
from .search_loop import PolicyInput, sample_actions

MASKED_LOGIT = -1e9  # masked viewpoints' logit: finite, so the entropy stays finite (sample_actions)


@dataclass(frozen=True)
class ExternalConfig:
    """The actor's architecture and the search task whose observations it reads; stored in the checkpoint."""

    obs_dim: int  # length of the flattened "cells" observation
    num_actions: int
    hidden: tuple[int, ...] = (64, 64)
    search: dict = field(default_factory=dict)  # config_to_dict of the SearchConfig it was trained on
    mask: bool = False  # logits of viewpoints outside the observation's action_mask are masked (time budget)
    trainer: str = ""  # who trained it ("sb3", "cleanrl"), for the record

    @property
    def search_config(self) -> SearchConfig:
        return config_from_dict(self.search)


class ExternalPolicyNet(nn.Module):
    """An MLP actor on the flattened "cells" observation (module docstring)."""

    KIND = "external"  # the checkpoint's policy kind (checkpoints.POLICY_NETS)

    def __init__(self, cfg: ExternalConfig):
        super().__init__()
        self.cfg = cfg
        layers, prev = [], cfg.obs_dim
        for h in cfg.hidden:
            layers += [nn.Linear(prev, h), nn.Tanh()]
            prev = h
        layers.append(nn.Linear(prev, cfg.num_actions))
        self.mlp = nn.Sequential(*layers)
        self._config = cfg.search_config if cfg.search else None
        if cfg.mask and (self._config is None or observation_keys(self._config)[0] != "action_mask"):
            raise ValueError("a masking actor needs a search config whose observation starts with action_mask")

    @classmethod
    def for_config(cls, config: SearchConfig, hidden=(64, 64), trainer: str = "") -> "ExternalPolicyNet":
        """A fresh actor for the "cells" observation of `config`."""
        B = 1
        P, N = config.lattice.num_positions, config.grid.num_cells
        z = torch.zeros(B, N)
        obs = cells_observation(config, z, z.bool(), z, z, torch.zeros(B, P), torch.zeros(B, dtype=torch.long),
                                torch.zeros(B, dtype=torch.long), torch.zeros(B), torch.ones(B, P, dtype=torch.bool))
        return cls(ExternalConfig(int(flatten_cells(obs).shape[1]), config.num_actions, tuple(int(h) for h in hidden),
                                  config_to_dict(config), config.budget_s is not None, trainer))

    def forward(self, flat_obs: torch.Tensor) -> torch.Tensor:
        """(B, obs_dim) flattened observations -> (B, num_actions) logits, those outside the observation's
        action_mask set to MASKED_LOGIT when the actor masks (its first num_actions entries: "action_mask" is
        the first of the sorted keys)."""
        logits = self.mlp(flat_obs)
        if self.cfg.mask:
            logits = torch.where(flat_obs[:, : self.cfg.num_actions] > 0, logits, MASKED_LOGIT)
        return logits

    def observation(self, inp: PolicyInput) -> dict:
        """The "cells" observation the env would give for this point of the episode."""
        config = self._config
        B, P = inp.lattice_idx.shape[0], config.lattice.num_positions
        visits = torch.nn.functional.one_hot(inp.view_positions, P).sum(1)
        return cells_observation(config, inp.view_probs[:, -1], inp.view_valid[:, -1], inp.fused,
                                 inp.view_valid.sum(1), visits, inp.lattice_idx,
                                 torch.full((B,), int(inp.step), dtype=torch.long, device=inp.lattice_idx.device),
                                 inp.time_left_s, inp.allowed)

    def logits(self, inp: PolicyInput) -> torch.Tensor:
        return self(torch.as_tensor(flatten_cells(self.observation(inp)), device=inp.fused.device))

    def act(self, inp: PolicyInput, generator: torch.Generator | None = None, greedy: bool = False):
        return sample_actions(self.logits(inp), generator, greedy)


__all__ = ["ExternalConfig", "ExternalPolicyNet", "MASKED_LOGIT"]
