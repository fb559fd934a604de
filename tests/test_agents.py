"""The agent registry: one place names every fusion method and policy; every user builds agents through it."""

import argparse
from dataclasses import dataclass

import numpy as np
import pytest
import torch

from uavsearch.testing.synthetic_views import synthetic_cache
from uavsearch.cli_args import add_dataclass_args, dataclass_from_args, opt
from uavsearch.errors import MissionError, UavsearchError
from uavsearch.replay.replay import _fuse_all
from uavsearch.fly.missions import mission_from_dict
from uavsearch.search import fusion
from uavsearch.search.agents import POLICIES, build_agent, checkpoint_path, new_agent, trained_fusion
from uavsearch.search.config import SearchConfig, config_to_dict, setting_config, wide_budgets
from uavsearch.search.external_policy import ExternalPolicyNet
from uavsearch.search.fusion import BY_NAME, FUSIONS, Fusion
from uavsearch.search.map_policy import MapPolicyConfig, MapPolicyNet
from uavsearch.search.policy import save_search_model
from uavsearch.search.reactive import ReactivePolicyNet
from uavsearch.search.search_loop import CachedViews, run_search


def _ship(models, setting=2, cell_dim=6, global_dim=16):
    torch.manual_seed(0)
    for f in BY_NAME:
        a = new_agent(f, SearchConfig(), global_dim, cell_dim)
        save_search_model(checkpoint_path(setting, f, models), a.fusion, a.policy)
        save_search_model(checkpoint_path(setting, f, models, policy="reactive"), a.fusion, ReactivePolicyNet())
        save_search_model(checkpoint_path(setting, f, models, policy="external"), a.fusion,
                          ExternalPolicyNet.for_config(SearchConfig()), {"search_config": config_to_dict(SearchConfig())})
        wide = wide_budgets(setting_config("wide"))["240 s"]
        save_search_model(checkpoint_path(setting, f, models, policy="map"), a.fusion,
                          MapPolicyNet(MapPolicyConfig(config_to_dict(wide))), {"search_config": config_to_dict(wide)})


@pytest.mark.parametrize("policy", list(POLICIES))
@pytest.mark.parametrize("fusion", BY_NAME)
def test_every_registered_pair_builds_and_runs(tmp_path, fusion, policy):
    _ship(tmp_path)
    config = setting_config("wide") if POLICIES[policy].move_set == "any" else SearchConfig()
    if policy == "map":  # a map net is trained for one budget: the time budget's here
        config = wide_budgets(config)["240 s"]
    loaded = build_agent(fusion, policy, config, checkpoint=checkpoint_path(2, fusion, tmp_path, policy=policy),
                         confidence_checkpoint=checkpoint_path(2, "learned", tmp_path), scores_net=True)
    assert loaded.agent.fusion_name == fusion and loaded.agent.fusion.trainable == trained_fusion(fusion)
    assert loaded.scores_net is not None  # the learned checkpoint's net, for logging scores
    assert loaded.description == f"{fusion} fusion + {policy} policy"
    with torch.no_grad():
        ep = run_search(CachedViews(synthetic_cache(2, config=config), [0, 1]), loaded.agent,
                        generator=torch.Generator().manual_seed(0))
    assert ep.maps.shape[::2] == (2, config.grid.num_cells) and torch.isfinite(ep.maps).all()
    assert ep.maps.shape[1] == config.budget_T or ep.taken is not None


def test_unknown_names_and_mismatched_checkpoints_are_one_line_errors(tmp_path):
    _ship(tmp_path)
    config = SearchConfig()
    with pytest.raises(UavsearchError, match="unknown fusion method 'median'"):
        build_agent("median", "random", config)
    with pytest.raises(UavsearchError, match="unknown policy 'psychic'"):
        build_agent("average", "psychic", config)
    with pytest.raises(MissionError, match="^mission x: checkpoint .* trained with 'bayes' fusion, not 'average'"):
        build_agent("average", "learned", config, checkpoint=checkpoint_path(2, "bayes", tmp_path),
                    error=MissionError, where="mission x: ")
    with pytest.raises(UavsearchError, match="needs a confidence network"):
        build_agent("learned", "random", config)
    with pytest.raises(MissionError, match="fusion: unknown fusion method 'median'"):
        mission_from_dict({"fusion": "median"}, "x.yaml")


def test_a_new_fusion_method_is_one_class_and_one_registry_entry(monkeypatch):
    """Registered in fusion.py's FUSIONS only, a method runs in the loop, in replay and validates in missions."""
    def _max(p, v, prior, area_px):  # max p over the valid views (takes area_px only to show a need)
        return torch.where(v, p, torch.zeros_like(p)).amax(-2)

    class MaxFusion(Fusion):
        name, needs, kernel = "max", ("area_px",), staticmethod(_max)

    monkeypatch.setitem(FUSIONS, "max", MaxFusion)
    assert fusion.FUSIONS["max"].needs == ("area_px",)
    agent = build_agent("max", "random", SearchConfig()).agent
    with torch.no_grad():
        ep = run_search(CachedViews(synthetic_cache(2), [0, 1]), agent, generator=torch.Generator().manual_seed(0))
    assert torch.isfinite(ep.maps).all()
    p = np.random.default_rng(0).random((3, 100))
    maps = _fuse_all("max", p, np.ones((3, 100), bool), area=np.ones((3, 100)))
    np.testing.assert_allclose(maps[-1], p.max(0))
    assert mission_from_dict({"fusion": "max", "policy": "random"}, "x.yaml").fusion == "max"


@dataclass
class _Args:
    steps: int = opt(3, "optimiser steps")
    out: str | None = opt(None, "where to", required=True)
    augment: bool = opt(True, "flip images")
    views: int = opt(2, "views per scene", flag="--v")
    layers: tuple = opt(factory=lambda: (1, 2), cli=False)


def test_cli_args_turns_a_dataclass_into_flags():
    p = add_dataclass_args(argparse.ArgumentParser(), _Args)
    assert dataclass_from_args(_Args, p.parse_args(["--out", "x"])) == _Args(out="x")
    a = dataclass_from_args(_Args, p.parse_args(["--out", "x", "--steps", "7", "--no-augment", "--v", "4"]))
    assert (a.steps, a.augment, a.views, a.layers) == (7, False, 4, (1, 2))
    assert dataclass_from_args(_Args, p.parse_args(["--out", "x", "--augment", "false"])).augment is False
    assert dataclass_from_args(_Args, p.parse_args(["--out", "x", "--augment"])).augment is True
    assert "optimiser steps (default 3)" in " ".join(p.format_help().split())
    with pytest.raises(SystemExit):
        p.parse_args([])  # --out is required
    with pytest.raises(SystemExit):
        p.parse_args(["--out", "x", "--augment", "maybe"])
