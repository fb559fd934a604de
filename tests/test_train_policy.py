"""Stage 2 smoke and determinism on a synthetic view cache (no rendering, a few iterations)."""

import argparse
import csv
import json

import pytest
import torch

from uavsearch.testing.synthetic_views import synthetic_cache
from uavsearch.errors import UavsearchError
from uavsearch.search.policy import load_search_model
from uavsearch.search.search_loop import Episode
from uavsearch.cli_args import dataclass_from_args
from uavsearch.search.train.policy import Args, add_train_policy_parser, cmd_train_policy, returns, train


def _args(tmp_path, **kw):
    base = dict(iterations=4, scenes_per_batch=2, episodes_per_scene=3, eval_every=2, eval_episodes=2,
                runs_dir=str(tmp_path / "runs"), progress=False)
    base.update(kw)
    return Args(**base)


def _caches():
    return synthetic_cache(2, seed=0), synthetic_cache(2, seed=1)


def test_smoke_run_writes_the_run_folder_and_a_loadable_checkpoint(tmp_path):
    out = tmp_path / "models" / "search_s2_learned.pt"
    res = train(_args(tmp_path, out=str(out)), caches=_caches())
    files = {p.name for p in res.run_dir.iterdir()}
    assert {"args.json", "metrics.csv", "learning_curve.png", "model.pt", "summary.json"} <= files
    assert json.loads((res.run_dir / "args.json").read_text())["iterations"] == 4
    rows = list(csv.DictReader((res.run_dir / "metrics.csv").open()))
    assert len(rows) == 4 and rows[1]["eval/af1"] != "" and rows[0]["eval/af1"] == ""
    fusion, net, extra = load_search_model(out)
    assert fusion.name == "learned" and fusion.trainable and extra["best"]["iteration"] in (2, 4)
    assert res.steps_per_s > 0


def test_baseline_fusions_train_a_policy_without_confidence_net(tmp_path):
    for fusion in ("average", "oracle"):
        res = train(_args(tmp_path, fusion=fusion, iterations=2, baseline="ema", plot=False), caches=_caches())
        f = load_search_model(res.checkpoint).fusion
        assert f.name == fusion and not f.trainable


def test_same_seed_same_numbers(tmp_path):
    def run(seed, sub):
        res = train(_args(tmp_path / sub, seed=seed, plot=False), caches=_caches())
        rows = list(csv.DictReader((res.run_dir / "metrics.csv").open()))
        nums = [{k: v for k, v in r.items() if k != "charts/steps_per_s"} for r in rows]
        fusion, net, _ = load_search_model(res.checkpoint)
        return nums, net.state_dict(), fusion.state_dict()

    a, b, c = run(7, "a"), run(7, "b"), run(8, "c")
    assert a[0] == b[0]
    assert all(torch.equal(a[1][k], b[1][k]) for k in a[1]) and all(torch.equal(a[2][k], b[2][k]) for k in a[2])
    assert a[0] != c[0]


def test_returns_follow_eq_13_to_15():
    labels = torch.tensor([[True, True, False, False]])
    final = torch.tensor([[0.9, 0.2, 0.7, 0.1]])  # 1 tp, 1 fp
    revisit = torch.tensor([[False, False, True, False, True]])
    ep = Episode(None, None, None, None, revisit, final[:, None].expand(1, 5, 4), labels)
    args = Args(r_tp=2.0, r_fp=-1.5, r_re=-0.5)
    R, r_cls = returns(ep, args)
    assert r_cls.tolist() == [0.5]
    # rewards per move: [0, -0.5, 0, -0.5 + 0.5] -> returns to go
    assert R.tolist() == [[-0.5, -0.5, 0.0, 0.0]]


@pytest.mark.parametrize("kw", [dict(fusion="median"), dict(baseline="critic"), dict(episodes_per_scene=1),
                                dict(iterations=0)])
def test_bad_arguments_are_one_line_errors(tmp_path, kw):
    with pytest.raises(UavsearchError):
        train(_args(tmp_path, **kw), caches=_caches())


def test_cli_parser_maps_flags_to_args():
    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers()
    add_train_policy_parser(sub)
    ns = parser.parse_args(["policy", "--setting", "3", "--fusion", "bayes", "--out", "x.pt", "--r-re", "-2",
                            "--state-extras", "false"])
    # what the command trains with: these flags, every other field at the dataclass's default
    assert dataclass_from_args(Args, ns) == Args(setting=3, fusion="bayes", out="x.pt", r_re=-2.0, state_extras=False)
    assert ns.func is cmd_train_policy


def _per_episode_confidence_loss(conf, cache, rows, lattice_idx, pos_weight):
    """Eq. 11 the direct way: the net on every episode's every view (the reference for the shared form)."""
    from uavsearch.search.fusion import fuse

    r = rows[:, None]
    p = cache.log_probs[r, lattice_idx][..., 1].exp()
    fused = fuse("learned", p, cache.valid[r, lattice_idx], scores=conf(cache.cell_features[r, lattice_idx]))
    fused = fused.clamp(1e-6, 1 - 1e-6)
    y = cache.occupancy[rows]
    w = torch.where(y, torch.full_like(fused, pos_weight), torch.ones_like(fused))
    return -(w * torch.where(y, fused.log(), (1 - fused).log())).sum() / w.sum()


def test_confidence_loss_shared_per_scene_and_position_equals_the_per_episode_loss():
    from uavsearch.search.perception import ConfidenceNet
    from uavsearch.search.fusion import LearnedFusion
    from uavsearch.search.train.policy import confidence_loss

    cache = synthetic_cache(3, seed=2)
    conf = ConfidenceNet(int(cache.cell_features.shape[-1])).eval()  # no dropout: both forms are exact
    rows = torch.tensor([0, 0, 1, 2, 2, 2])
    g = torch.Generator().manual_seed(0)
    idx = torch.randint(cache.num_positions, (6, 5), generator=g)
    idx[:, 0] = 12  # every episode starts at the centre: shared views
    a = confidence_loss(LearnedFusion(conf), cache, rows, idx, 3.0)
    ga = torch.autograd.grad(a, list(conf.parameters()))
    b = _per_episode_confidence_loss(conf, cache, rows, idx, 3.0)
    gb = torch.autograd.grad(b, list(conf.parameters()))
    assert torch.allclose(a, b, atol=1e-6)
    assert all(torch.allclose(x, y, atol=1e-6) for x, y in zip(ga, gb))


def test_rollout_scores_computed_on_first_sight_equal_scores_of_every_view():
    from uavsearch.search.config import SearchConfig
    from uavsearch.search.perception import ConfidenceNet
    from uavsearch.search.search_loop import CachedViews

    cache = synthetic_cache(3, seed=3)
    conf = ConfidenceNet(int(cache.cell_features.shape[-1])).eval()
    rows = torch.tensor([2, 0, 2, 1])
    src = CachedViews(cache, rows, SearchConfig(), conf)
    for p in (torch.tensor([12, 12, 12, 12]), torch.tensor([7, 12, 13, 24]), torch.tensor([7, 7, 0, 24])):
        with torch.no_grad():
            want = conf(cache.cell_features[rows, p])
        assert torch.allclose(src.observe(p).scores, want, atol=1e-6)
