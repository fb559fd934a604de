"""THE registry of fusion methods, policies and team planners, and the one `build_agent(...)` every user goes
through.

Evaluation (the rows of Table II, Table III, the team table), flying (a mission's method, one vehicle or a team),
replay (re-running perception + fusion on a log), the envs and training all look names up here, so a fusion
method, a policy or a team planner is named in one place (where its checkpoint lives: checkpoints.py):

- fusion methods: `FUSIONS` in fusion.py (name -> Fusion class). A `trainable` one (learned fusion) comes
  with its weights from a search checkpoint, which saves the fusion object whole.
- policies: `POLICIES` below. "learned" (the paper's PolicyNet) loads its net from a search checkpoint
  (search_s<K>_<fusion>.pt, trained with that fusion), "reactive" (reactive.ReactivePolicyNet) from
  search_s<K>_<fusion>_reactive.pt, "external" (external_policy.ExternalPolicyNet, a PPO actor trained on the
  gymnasium env) from search_s<K>_<fusion>_external.pt, "map" (map_policy.MapPolicyNet, the wide-area
  search's) from the checkpoint a wide mission or Table III names; the others are built from the search config.
- fusion specs: `make_fusion(spec)` builds every fusion a user names: "name" or "name:prior" (bayes:0.02),
  "calibrated:GAMMA" fitted on training views, and (given a setting) a trained one from its shipped checkpoint.
- team planners: `PLANNERS` below (search/team.py's), "name" or "name:VALUE" for a planner with a parameter.

Adding a fusion method is one class and one entry in fusion.py's FUSIONS; adding a policy or a team planner is
one entry here.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Callable, NamedTuple

from torch import nn

from uavsearch.errors import UavsearchError
from uavsearch.paths import display_path
from uavsearch.world.settings import setting_params

from .checkpoints import checkpoint_path
from .config import SearchConfig, config_from_dict
from .fusion import FUSIONS, Fusion, calibrated_candidates, calibrated_gamma, check_buildable, fusion_from_spec
from .neighbour_fusion import neighbour_from_spec
from .perception import load_perception
from .policy import (ArgmaxPolicy, CoverageRoute, GreedyUncertainty, PolicyConfig, PolicyNet, RandomPolicy,
                     load_search_model)
from .search_loop import Agent, Policy
from .team import EachVehicle, Partition, TeamEntropy, TeamPlanner, TeamRule
from .wide_policies import (SURVEY_INNER_M, SURVEY_OUTER_M, DescendRule, EntropyPerSecond, MaskedRandom, RoutePolicy,
                            lawnmower, survey_then_lawnmower)
from .perception import perception_tag


class PolicyKind(NamedTuple):
    """How a policy is made: from the config, or (build None) loaded from a search checkpoint whose net is of
    kind `net` (checkpoints.POLICY_NETS)."""

    build: Callable[[SearchConfig], Policy] | None
    description: str
    net: str | None = None
    move_set: str | None = None  # the config.move_set it needs (None: either)


POLICIES: dict[str, PolicyKind] = {
    "learned": PolicyKind(None, "the REINFORCE view-selection net of a search checkpoint", "paper"),
    "reactive": PolicyKind(None, "a conv net on the map of what each view said (DAgger + REINFORCE; beyond the "
                                 "paper)", "reactive"),
    "external": PolicyKind(None, "a PPO actor trained outside on the gymnasium env's cells observations "
                                 "(examples/sb3_ppo.py, examples/cleanrl_ppo.py; beyond the paper)", "external"),
    "map": PolicyKind(None, "the wide-area search's learned policy: a conv net on the map scores every viewpoint "
                            "(DAgger + REINFORCE)", "map", move_set="any"),
    "random": PolicyKind(lambda config: RandomPolicy(len(config.actions)) if config.move_set == "steps"
                         else MaskedRandom(config), "uniform random moves (any viewpoint: uniform over the allowed)"),
    "coverage": PolicyKind(CoverageRoute, "a fixed geometric route (beyond the paper)"),
    "greedy": PolicyKind(GreedyUncertainty, "toward the most uncertain cells (beyond the paper)"),
    # the wide-area search's (move_set "any"; wide_policies.py)
    "lawnmower_high": PolicyKind(lambda c: RoutePolicy(lawnmower(c, c.layers_m[0])),
                                 "boustrophedon over the start altitude's layer", move_set="any"),
    "lawnmower_low": PolicyKind(lambda c: RoutePolicy(lawnmower(c, min(c.layers_m))),
                                "boustrophedon over the lowest layer", move_set="any"),
    "survey_inner": PolicyKind(lambda c: RoutePolicy(survey_then_lawnmower(c, SURVEY_INNER_M)),
                               "the 4 inner start-altitude viewpoints, then the lowest layer's boustrophedon", move_set="any"),
    "survey_outer": PolicyKind(lambda c: RoutePolicy(survey_then_lawnmower(c, SURVEY_OUTER_M)),
                               "4 start-altitude viewpoints covering the area, then the lowest layer's boustrophedon", move_set="any"),
    "descend_rule": PolicyKind(DescendRule, "survey high, then descend over the highest fused p (the rule)", move_set="any"),
    "entropy_per_s": PolicyKind(EntropyPerSecond, "most fused-map entropy in the footprint per second of flight", move_set="any"),
}


class PlannerKind(NamedTuple):
    """How a team planner is made from the search config and the VALUE of "name:VALUE" ("" without one)."""

    build: Callable[[SearchConfig, str], TeamPlanner]
    description: str
    parameter: str | None = None  # what VALUE sets (None: the planner takes none)


def _team_entropy(config: SearchConfig, value: str) -> TeamPlanner:
    try:
        shared = float(value) if value else 0.8
    except ValueError:
        shared = float("nan")
    if not 0.0 <= shared <= 1.0:
        raise UavsearchError(f"team planner team_entropy:{value}: the discount must be a number in [0, 1]")
    return TeamEntropy(config, shared)


PLANNERS: dict[str, PlannerKind] = {
    "rule": PlannerKind(lambda c, _: TeamRule(c), "the rule for a team (nearest free survey viewpoint, then the "
                                                  "descent score)"),
    "rule_per_s": PlannerKind(lambda c, _: TeamRule(c, per_second=True),
                              "the rule for a team, descent score per second of flight"),
    "partition": PlannerKind(lambda c, _: Partition(c), "fixed partition (each vehicle the 40 m lawnmower of its "
                                                        "strip)"),
    "entropy_per_s": PlannerKind(lambda c, _: EachVehicle(EntropyPerSecond(c)), "entropy per second, each vehicle "
                                                                                "in turn"),
    "team_entropy": PlannerKind(_team_entropy, "entropy per second, cells others are about to see discounted",
                                "SHARED"),
}


def make_planner(spec: str, config: SearchConfig) -> TeamPlanner:
    """A team planner from its name, or name:VALUE for one with a parameter (team_entropy:0.8)."""
    key, _, value = str(spec).partition(":")
    if key not in PLANNERS or (value and PLANNERS[key].parameter is None):
        with_value = ", ".join(f"{k}:{p.parameter}" for k, p in PLANNERS.items() if p.parameter)
        raise UavsearchError(f"unknown team planner {spec!r}; valid: {', '.join(PLANNERS)} ({with_value})")
    return PLANNERS[key].build(config, value)


def make_fusion(spec: str, train=None, *, setting=None, models_dir=None, device="cpu") -> Fusion:
    """The fusion a name or spec says. Without `setting`: fusion.fusion_from_spec's ("name" or "name:prior" of a
    fusion without weights or labels), or "calibrated[:GAMMA]" fitted on the training view cache `train` (Table
    III's --wide-fusion, a wide mission's fusion, the map policy's). With `setting` (an env's): any method of
    FUSIONS by name, a trained one with the weights of the setting's shipped checkpoint (its net on `device`)."""
    neighbour = neighbour_from_spec(spec)  # "neighbour:PATH.pt": a trained checkpoint of its own
    if neighbour is not None:
        return neighbour
    if setting is None:
        gamma = calibrated_gamma(spec)
        if gamma is not None and train is not None:
            return calibrated_candidates(train, (gamma,))[0]
        return fusion_from_spec(spec, "--wide-fusion")
    check_buildable(spec)
    if not FUSIONS[spec].trainable:
        return FUSIONS[spec]()
    family = setting_params(setting)
    if family.task.mission != "moves":  # a lattice task's policies are map policies, saved per budget, not per fusion
        raise UavsearchError(f"{spec} fusion has no shipped checkpoint for scene family {family.name!r}; choose bayes")
    return load_search_model(checkpoint_path(setting, spec, models_dir), device).fusion  # eval mode; saves whole


def trained_fusion(fusion: str) -> bool:
    """Whether the fusion method has trained weights (loaded from a search checkpoint)."""
    return FUSIONS[fusion].trainable


def check_names(fusion: str | None = None, policy: str | None = None) -> None:
    """A one-line error for a fusion method or policy the registry does not know."""
    if fusion is not None:
        check_buildable(fusion)
    if policy is not None and policy not in POLICIES:
        raise UavsearchError(f"unknown policy {policy!r}; choose one of {', '.join(POLICIES)}")


def loads_checkpoint(policy: str) -> bool:
    """Whether the policy's net comes from a search checkpoint (it is trained) rather than the config."""
    return POLICIES[policy].build is None


def same_lattice(a: SearchConfig, b: SearchConfig) -> bool:
    """Whether a policy trained on config `a` reads config `b`: the same viewpoints, actions and move set."""
    pa, pb = a.lattice.positions_enu, b.lattice.positions_enu
    return (pa.shape == pb.shape and bool((abs(pa - pb) < 1e-6).all()) and a.actions == b.actions
            and a.move_set == b.move_set)


def _lattice_text(c: SearchConfig) -> str:
    alts = "/".join(f"{a:g}" for a in c.layers_m)
    return f"{c.lattice.num_positions} viewpoints at {alts} m, {c.step_m:g} m apart, moves {', '.join(c.actions)}"


class LoadedAgent(NamedTuple):
    agent: Agent
    perception: nn.Module | None  # the frozen perception net, when asked for
    scores_net: nn.Module | None  # per-view scores for logging (a trained fusion's scorer, when one was found)
    description: str


def _warn_tag(extra, perception, path) -> None:
    """A policy / confidence net trained on another perception net's outputs reads them wrongly: say so."""
    tag = extra.get("perception_tag") if isinstance(extra, dict) else None
    if tag and tag != perception_tag(perception):
        print(f"uavsearch: warning: {path} was trained with perception {tag}, the given perception is "
              f"{perception_tag(perception)}", file=sys.stderr)


def build_agent(fusion: str, policy: str, config: SearchConfig, *, checkpoint=None, confidence_checkpoint=None,
                greedy: bool = False, perception=None, scores_net: bool = False,
                error: type[UavsearchError] = UavsearchError, where: str = "", device="cpu") -> LoadedAgent:
    """The agent named by (fusion, policy).

    checkpoint: the learned policy's search checkpoint (its fusion must be `fusion`).
    confidence_checkpoint: where a trained fusion comes from when the policy's checkpoint has none (learned
        fusion with another policy; or, with `scores_net`, any fusion, to log scores for replay's re-fusion).
    greedy: a learned policy takes its most likely move instead of sampling.
    perception: a checkpoint path (or a loaded net) to load with the agent; the policy checkpoint's
        perception tag is checked against it.
    error, where: the error class and message prefix (a mission says which file is wrong).
    device: where the nets it loads live (the episodes it acts in must live there too).
    """
    try:
        check_names(fusion, policy)
    except UavsearchError as e:
        raise error(f"{where}{e}") from None
    net = None
    if perception is not None and not isinstance(perception, nn.Module):
        perception, _ = load_perception(perception, device)
        perception = perception.for_grid(config.grid.num_cells)  # a detector knows no grid until told
    trained: Fusion | None = None  # a fusion with weights, from a checkpoint
    kind = POLICIES[policy]
    if kind.build is None:
        if checkpoint is None:
            raise error(f"{where}the {policy!r} policy needs a checkpoint")
        trained, net, extra = load_search_model(checkpoint, device)
        if perception is not None:
            _warn_tag(extra, perception, checkpoint)
        if trained.name != fusion:
            raise error(f"{where}checkpoint {checkpoint} holds a policy trained with {trained.name!r} fusion, "
                        f"not {fusion!r}")
        if net.KIND != kind.net:
            raise error(f"{where}checkpoint {checkpoint} holds a {net.KIND!r} policy net, not the {policy!r} "
                        f"policy's {kind.net!r}")
        recorded = extra.get("search_config") if isinstance(extra, dict) else None
        if recorded is not None and not same_lattice(config_from_dict(recorded), config):
            raise error(f"{where}checkpoint {checkpoint} was trained on another viewpoint lattice "
                        f"({_lattice_text(config_from_dict(recorded))}) than this search's ({_lattice_text(config)})")
        if net.cfg.num_actions != config.num_actions:
            raise error(f"{where}checkpoint has {net.cfg.num_actions} actions, the search has "
                        f"{config.num_actions}")
        pol = ArgmaxPolicy(net) if greedy else net
    else:
        if kind.move_set is not None and kind.move_set != config.move_set:
            raise error(f"{where}the {policy!r} policy needs move_set {kind.move_set!r}, the search has "
                        f"{config.move_set!r}")
        pol = kind.build(config)
    needed = trained_fusion(fusion)
    if trained is not None and not trained.trainable:
        trained = None
    if trained is None and confidence_checkpoint is not None and \
            (needed or (scores_net and Path(confidence_checkpoint).is_file())):
        try:
            trained = load_search_model(confidence_checkpoint, device).fusion
        except UavsearchError:
            if needed:
                raise
        if trained is not None and not trained.trainable:
            trained = None
        if needed and (trained is None or trained.name != fusion):
            raise error(f"{where}{confidence_checkpoint} has no confidence network for {fusion} fusion")
    if needed and trained is None:
        raise error(f"{where}{fusion} fusion needs a confidence network (a checkpoint trained with it)")
    agent = Agent(trained if needed else FUSIONS[fusion](), pol)
    return LoadedAgent(agent, perception, trained.scorer if scores_net and trained is not None else None,
                       f"{fusion} fusion + {policy} policy")


def load_wide_agent(path, config: SearchConfig, error: type[UavsearchError] = UavsearchError,
                    where: str = "", device="cpu") -> Agent | None:
    """The learned wide-area policy of a checkpoint (map_policy.MapPolicyNet) as an agent: its most likely
    viewpoint, with the fusion it was trained with (saved beside it). None where the file is missing; a
    checkpoint of another kind, or one trained for another lattice, grid or budget than `config`, is a one-line
    error (Table III and a wide mission both load it here)."""
    if not Path(path).is_file():
        return None
    fusion, net, _ = load_search_model(path, device)
    if net.KIND != "map":
        raise error(f"{where}{display_path(path)} holds a {net.KIND!r} policy, not the wide family's map policy")
    trained = net.cfg.search_config()
    if not same_lattice(trained, config) or trained.grid != config.grid:
        raise error(f"{where}{display_path(path)} was trained for another viewpoint lattice or grid than this search's")
    if trained.budget_s != config.budget_s or (trained.budget_s is None and trained.budget_T != config.budget_T):
        raise error(f"{where}{display_path(path)} was trained for {budget_text(trained)}, this search has "
                    f"{budget_text(config)}")
    return Agent(fusion, ArgmaxPolicy(net))


def budget_text(config: SearchConfig) -> str:
    """'T = 8 views' or '240 s of flight': the budget a wide-area policy was trained for."""
    return f"T = {config.budget_T} views" if config.budget_s is None else f"{config.budget_s:g} s of flight"


def new_agent(fusion: str, config: SearchConfig, global_dim: int, cell_dim: int, extras: bool = True) -> Agent:
    """A fresh agent for stage 2 to train: a policy net and a fresh fusion (its weights untrained)."""
    check_names(fusion)
    policy = PolicyNet(PolicyConfig(global_dim=global_dim, num_cells=config.grid.num_cells,
                                    num_positions=config.lattice.num_positions, num_actions=config.num_actions,
                                    budget_T=config.budget_T, extras=extras))
    return Agent(FUSIONS[fusion].new(cell_dim), policy)


__all__ = ["FUSIONS", "POLICIES", "LoadedAgent", "PolicyKind", "budget_text", "build_agent", "check_names",
           "checkpoint_path", "load_wide_agent", "loads_checkpoint", "new_agent", "same_lattice", "trained_fusion"]
