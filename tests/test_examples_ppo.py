"""The PPO examples train for a few hundred steps and write a checkpoint that the registry's "external" policy
loads and run_search flies (setting 2's first training scene; its cache is built on first use)."""

import sys

import pytest
import torch

from uavsearch.paths import REPO_ROOT
from uavsearch.search.agents import build_agent
from uavsearch.search.config import SearchConfig
from uavsearch.search.search_loop import CachedViews, run_search
from uavsearch.testing.synthetic_views import synthetic_cache

sys.path.insert(0, str(REPO_ROOT / "examples"))


def _flies(ckpt):
    agent = build_agent("learned", "external", SearchConfig(), checkpoint=ckpt, greedy=True).agent
    cache = synthetic_cache(2, cell_dim=agent.fusion.net.in_dim)
    with torch.no_grad():
        ep = run_search(CachedViews(cache, [0, 1], confidence=agent.fusion.scorer), agent)
    assert ep.lattice_idx.shape == (2, 5) and torch.isfinite(ep.maps).all()


def test_cleanrl_ppo_trains_and_its_checkpoint_flies(tmp_path):
    import cleanrl_ppo

    out = cleanrl_ppo.train(cleanrl_ppo.Args(total_timesteps=256, num_envs=8, num_steps=16, limit=1,
                                             runs_dir=str(tmp_path)))
    assert out["steps"] == 256 and (out["run_dir"] / "metrics.csv").read_text().count("\n") == 3
    _flies(out["checkpoint"])


def test_sb3_ppo_trains_and_its_checkpoint_flies(tmp_path):
    pytest.importorskip("stable_baselines3")
    import sb3_ppo

    out = sb3_ppo.train(sb3_ppo.Args(total_timesteps=128, n_envs=4, n_steps=32, batch_size=64, limit=1,
                                     runs_dir=str(tmp_path)))
    assert out["steps"] >= 128
    _flies(out["checkpoint"])
