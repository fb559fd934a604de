"""View selection policies (paper Eq. 8-9) and the non-learned routes they are compared with.

- `PolicyNet`: the paper's policy. s^t = F_state(F_embedding(O^t) ⊕ c^t ⊕ M-bar^t ⊕ extras), p(a | s^t) =
  F_action(s^t). F_embedding is perception.ImageEmbedding (frozen backbone's global feature -> 512-d,
  trained here); F_state two FC + ReLU; F_action FC + ReLU + FC + softmax. `extras` (on by default)
  adds the camera's lattice position (one-hot), the positions visited so far and the step (one-hot):
  the paper feeds "the current observation and position"; with only T = 5 views and a revisit penalty,
  knowing where you are, where you have been and how many views are left is what makes a plan possible.
- `RandomPolicy`: uniform over the action set (the paper's random baseline).
- `CoverageRoute`: a fixed route that covers the area best by geometry alone (a lawnmower for T views):
  every cell seen as close to straight down as the budget allows.
- `GreedyUncertainty`: moves toward the most uncertain cells: to the neighbouring position nearest to
  them (ground distance weighted by the entropy of M-bar), never back to a visited position while a new
  one is reachable.

All share `act(PolicyInput, generator) -> (actions, log_prob | None, entropy | None)` (search_loop.Policy).
"""

from __future__ import annotations

import itertools
import json
from typing import NamedTuple
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from uavsearch.devices import follow, resolve_device
from uavsearch.errors import UavsearchError

from .checkpoints import policy_net
from .config import SearchConfig
from . import neighbour_fusion  # noqa: F401  registers the learned aggregations a checkpoint may carry
from .fusion import Fusion, load_fusion
from .perception import EMBED_DIM, ImageEmbedding
from .search_loop import PolicyInput, sample_actions


@dataclass(frozen=True)
class PolicyConfig:
    """Architecture; stored in every checkpoint."""

    global_dim: int  # the perception's global feature size (F_embedding's input)
    num_cells: int = 100
    num_positions: int = 25
    num_actions: int = 4
    budget_T: int = 5
    embed_dim: int = EMBED_DIM
    state_hidden: int = 128
    action_hidden: int = 64
    extras: bool = True  # position one-hot ⊕ visited mask ⊕ step one-hot in the state

    @property
    def state_in(self) -> int:
        extra = (2 * self.num_positions + self.budget_T) if self.extras else 0
        return self.embed_dim + 2 * self.num_cells + extra


class PolicyNet(nn.Module):
    """Eq. 8-9 (see the module docstring)."""

    KIND = "paper"  # the checkpoint's policy kind (save_search_model)

    def __init__(self, cfg: PolicyConfig):
        super().__init__()
        self.cfg = cfg
        self.embedding = ImageEmbedding(cfg.global_dim, cfg.embed_dim)
        self.state = nn.Sequential(nn.Linear(cfg.state_in, cfg.state_hidden), nn.ReLU(),
                                   nn.Linear(cfg.state_hidden, cfg.state_hidden), nn.ReLU())
        self.action = nn.Sequential(nn.Linear(cfg.state_hidden, cfg.action_hidden), nn.ReLU(),
                                    nn.Linear(cfg.action_hidden, cfg.num_actions))

    def logits(self, inp: PolicyInput) -> torch.Tensor:
        parts = [self.embedding(inp.global_feature), inp.cells_in_view, inp.fused]
        if self.cfg.extras:
            B = inp.fused.shape[0]
            pos = torch.nn.functional.one_hot(inp.lattice_idx, self.cfg.num_positions).float()
            step = torch.zeros(B, self.cfg.budget_T, device=inp.fused.device)
            step[:, min(inp.step, self.cfg.budget_T - 1)] = 1.0
            parts += [pos, inp.visited.float(), step]
        return self.action(self.state(torch.cat(parts, dim=-1)))

    def act(self, inp: PolicyInput, generator: torch.Generator | None = None, greedy: bool = False):
        return sample_actions(self.logits(inp), generator, greedy)


class ArgmaxPolicy:
    """Evaluate a learned policy net (PolicyNet, ReactivePolicyNet) with its most likely action instead of sampling."""

    def __init__(self, net: nn.Module):
        self.net = net

    def act(self, inp: PolicyInput, generator=None):
        return self.net.act(inp, generator, greedy=True)


class RandomPolicy:
    """Uniform over the action set, from the caller's generator."""

    def __init__(self, num_actions: int = 4):
        self.num_actions = num_actions

    def act(self, inp: PolicyInput, generator: torch.Generator | None = None):
        B = inp.lattice_idx.shape[0]
        return torch.randint(self.num_actions, (B,), generator=generator, device=inp.lattice_idx.device), None, None


def coverage_route(config: SearchConfig, budget_T: int | None = None) -> tuple[int, ...]:
    """The move sequence from the centre that covers the grid best, by geometry alone.

    Among all routes of T - 1 moves that never revisit a position, the one minimising the sum over cells
    of the ground distance to the nearest of its views (every cell seen once as close to nadir as
    possible; nadir views of flat ground give every cell the same pixel area, so area cannot tell routes
    apart), ties to the first in action order. A lawnmower for a budget too short to mow.
    """
    T = int(budget_T or config.budget_T)
    moves, dist = config.lattice.moves, config.lattice.cell_distances
    best, best_score = None, -np.inf
    for seq in itertools.product(range(moves.shape[1]), repeat=T - 1):
        pos = [config.lattice.start_index]
        for a in seq:
            pos.append(int(moves[pos[-1], a]))
        if len(set(pos)) < len(pos):
            continue
        score = -float(dist[pos].amin(0).sum())
        if score > best_score + 1e-9:
            best, best_score = seq, score
    if best is None:
        raise UavsearchError(f"no route of {T} views without revisits on this lattice")
    return best


class CoverageRoute:
    """A fixed route (coverage_route), the same for every scene."""

    def __init__(self, config: SearchConfig, budget_T: int | None = None):
        self.route = coverage_route(config, budget_T)

    def act(self, inp: PolicyInput, generator=None):
        B = inp.lattice_idx.shape[0]
        return torch.full((B,), self.route[min(inp.step, len(self.route) - 1)], dtype=torch.long,
                          device=inp.lattice_idx.device), None, None


class GreedyUncertainty:
    """Next view = the neighbour nearest to the most uncertain cells; unvisited neighbours first."""

    def __init__(self, config: SearchConfig):
        self.moves = config.lattice.moves
        self.weight = -config.lattice.cell_distances  # (P, N): nearer is better

    def act(self, inp: PolicyInput, generator=None):
        follow(self, inp.fused.device)
        p = inp.fused.clamp(1e-6, 1 - 1e-6)
        H = -(p * p.log() + (1 - p) * (1 - p).log())  # (B, N) binary entropy of M-bar
        nxt = self.moves[inp.lattice_idx]  # (B, A)
        score = torch.einsum("bn,ban->ba", H, self.weight[nxt])
        seen = inp.visited.gather(1, nxt)
        score = torch.where(seen, score - 1e6, score)  # any new position beats every revisit
        return score.argmax(-1), None, None


# --------------------------------------------------------------------------------------------------
# Checkpoints: one file per (setting, fusion, policy) holds the policy and the fusion it was trained with; each
# saves itself ({name / kind, config, state_dict}) and is rebuilt from that


FORMAT = "uavsearch-search-model/2"
FORMAT_V1 = "uavsearch-search-model/1"  # fusion as a name, learned fusion's confidence net by layer sizes


class SearchModel(NamedTuple):
    fusion: Fusion  # the fusion the policy was trained with (its weights too, for a trainable one)
    policy: nn.Module  # PolicyNet or ReactivePolicyNet (its KIND says which), in eval mode
    extra: dict  # metadata (args, best validation, perception_tag)


def _half(sd: dict) -> dict:
    """float16 storage halves the shipped files; loading casts back to float32 (what evaluation then uses)."""
    return {k: (v.detach().cpu().half() if v.is_floating_point() else v.detach().cpu()).clone() for k, v in sd.items()}


def save_search_model(path, fusion: Fusion, policy: nn.Module, extra: dict | None = None) -> Path:
    """The policy net (its KIND, config and weights) and the fusion it was trained with, in one file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fused = fusion.save_dict()
    torch.save({"format": FORMAT, "fusion": {**fused, "state_dict": _half(fused["state_dict"])},
                "policy_kind": policy.KIND, "policy_config": asdict(policy.cfg),
                "policy_state": _half(policy.state_dict()), "extra": json.loads(json.dumps(extra or {}, default=str))},
               path)
    return path


def _fusion_v1(ck: dict) -> dict:
    """The fusion entry of a checkpoint in the first layout: a name, and learned fusion's net by layer sizes."""
    c = ck["confidence"]
    if c is None:
        return {"name": ck["fusion"], "config": {}, "state_dict": {}}
    return {"name": ck["fusion"], "config": {"in_dim": c["in_dim"], "hidden": c["hidden"], "dropout": c["dropout"]},
            "state_dict": {f"net.{k}": v for k, v in c["state_dict"].items()}}


def load_search_model(path, device="cpu") -> SearchModel:
    """The policy and fusion of a search checkpoint (either layout), in eval mode, on `device` (a torch.device or
    devices.resolve_device's names)."""
    path = Path(path)
    if not path.is_file():
        raise UavsearchError(f"search model {path} not found (train one: uavsearch train policy)")
    try:
        device = resolve_device(device)
        ck = torch.load(path, map_location=device, weights_only=True)
        if ck.get("format") not in (FORMAT, FORMAT_V1):
            raise KeyError("format")
        net_cls, cfg_cls = policy_net(ck.get("policy_kind", PolicyNet.KIND))  # its module imported now
        policy = net_cls(cfg_cls(**ck["policy_config"]))
        policy.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in ck["policy_state"].items()})
        fusion = load_fusion(ck["fusion"] if ck["format"] == FORMAT else _fusion_v1(ck))
    except UavsearchError:
        raise
    except Exception as e:  # noqa: BLE001 - any corrupt file is one clear line
        raise UavsearchError(f"{path} is not a uavsearch search model ({type(e).__name__}: {e})") from None
    policy.eval().to(device)
    if isinstance(fusion, nn.Module):
        fusion.to(device)
    return SearchModel(fusion, policy, ck.get("extra", {}))


def round_trip_half(module: nn.Module) -> nn.Module:
    """Round the weights through float16 in place, so a net in memory equals its shipped file."""
    with torch.no_grad():
        for p in module.parameters():
            p.copy_(p.half().float())
    return module


__all__ = ["SearchModel", "ArgmaxPolicy", "CoverageRoute", "GreedyUncertainty", "PolicyConfig", "PolicyNet",
           "RandomPolicy", "coverage_route", "load_search_model", "round_trip_half", "save_search_model"]
