"""The reactive policy: masked moves, the label-greedy teacher, the episode history it reads, DAgger, checkpoints."""

import argparse
import csv

import numpy as np
import pytest
import torch

from uavsearch.testing.synthetic_views import synthetic_cache
from uavsearch.errors import UavsearchError
from uavsearch.fly.missions import mission_from_dict
from uavsearch.search.agents import build_agent, checkpoint_path, new_agent
from uavsearch.search.fusion import FUSIONS, LearnedFusion
from uavsearch.search.config import SearchConfig
from uavsearch.search.perception import ConfidenceNet
from uavsearch.search.policy import (ArgmaxPolicy, PolicyNet, RandomPolicy, load_search_model, round_trip_half,
                                     save_search_model)
from uavsearch.search.reactive import (LabelGreedyTeacher, ReactiveConfig, ReactivePolicyNet, action_mask,
                                      mirror_states)
from uavsearch.search.search_loop import (Agent, CachedViews, Observation, PolicyInput, classification_reward,
                                          run_search)
from uavsearch.search.train.dagger import DaggerMixture
from uavsearch.search.train.reactive import Args, add_train_reactive_parser, imitation_loss, train

CONFIG = SearchConfig()
MOVES = CONFIG.lattice.moves


def _conf(cell_dim=6, seed=0):
    torch.manual_seed(seed)
    return ConfidenceNet(cell_dim).eval()


class _Recorder:
    """Wraps a policy and keeps every PolicyInput it is shown."""

    def __init__(self, inner):
        self.inner, self.seen = inner, []

    def act(self, inp, generator=None):
        self.seen.append(inp)
        return self.inner.act(inp, generator)


def _biased_net(action: int) -> ReactivePolicyNet:
    """A net that wants `action` above all (so only the mask keeps it from an illegal move)."""
    torch.manual_seed(0)
    net = ReactivePolicyNet()
    with torch.no_grad():
        net.head[-1].bias.zero_()
        net.head[-1].bias[action] = 50.0
    return net


@pytest.mark.parametrize("action,start", [(0, 2), (1, 14), (2, 10), (3, 22)])  # each into the lattice's edge
def test_masked_moves_never_leave_the_lattice_nor_revisit(action, start):
    cache = synthetic_cache(3)
    net = _biased_net(action)
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        ep = run_search(CachedViews(cache, np.repeat(np.arange(3), 20)), Agent(FUSIONS["average"](), net), generator=gen,
                        start_idx=start)
    assert (ep.lattice_idx[:, 1:] != ep.lattice_idx[:, :-1]).all()  # no move off the lattice (it would stay)
    assert not ep.revisit.any()  # a new position is always reachable from 5 views on the 5x5 lattice
    assert (ep.actions[:, 0] != action).all()  # the wanted move left the lattice at the start
    assert torch.isfinite(ep.log_prob).all() and torch.isfinite(ep.entropy).all()


def test_mask_allows_a_revisit_only_when_no_new_position_is_reachable():
    def inp(idx, visited):
        v = torch.zeros(1, 25, dtype=torch.bool)
        v[0, visited] = True
        return PolicyInput(None, None, None, torch.tensor([idx]), v, 1, 5)

    # the NW corner (0) with its neighbours east (1) and south (5) visited: both revisits allowed, nothing else
    assert action_mask(inp(0, [0, 1, 5]), MOVES).tolist() == [[False, True, False, True]]
    # from the centre with north visited: east, west, south
    assert action_mask(inp(12, [12, 7]), MOVES).tolist() == [[False, True, True, True]]


@pytest.mark.parametrize("east_west,north_south", [(True, False), (False, True), (True, True)])
def test_a_mirrored_world_gives_the_mirrored_state_and_moves(east_west, north_south):
    cache = synthetic_cache(2)
    conf = _conf()
    rec = _Recorder(RandomPolicy())
    run_search(CachedViews(cache, [0, 1, 1]), Agent(LearnedFusion(conf), rec), generator=torch.Generator().manual_seed(2))

    def mirror_index(size):  # row-major from the NW corner: columns run west -> east, rows north -> south
        rc = torch.arange(size * size)
        r, c = rc // size, rc % size
        return (size - 1 - r if north_south else r) * size + (size - 1 - c if east_west else c)

    cells, lat = mirror_index(10), mirror_index(5)
    torch.manual_seed(0)
    net = ReactivePolicyNet()
    inp = rec.seen[2]
    mirrored = inp._replace(fused=inp.fused[:, cells], cells_in_view=inp.cells_in_view[:, cells],
                            lattice_idx=lat[inp.lattice_idx], visited=inp.visited[:, lat],
                            view_positions=lat[inp.view_positions], view_probs=inp.view_probs[..., cells],
                            view_valid=inp.view_valid[..., cells], view_scores=inp.view_scores[..., cells])
    a = torch.tensor([0, 1, 3])
    state, mask, moves = mirror_states(net.state(inp), net.mask(inp), a, CONFIG, east_west, north_south)
    assert torch.allclose(state, net.state(mirrored), atol=1e-5)
    assert torch.equal(mask, net.mask(mirrored))
    # a move and its mirror image reach mirror-image positions
    assert torch.equal(lat[MOVES[inp.lattice_idx, a]], MOVES[lat[inp.lattice_idx], moves])


def test_policy_input_carries_the_episode_so_far():
    cache = synthetic_cache(3)
    conf = _conf()
    rows = torch.tensor([0, 1, 2, 2])
    rec = _Recorder(RandomPolicy())
    with torch.no_grad():
        ep = run_search(CachedViews(cache, rows), Agent(LearnedFusion(conf), rec), generator=torch.Generator().manual_seed(3))
    assert len(rec.seen) == CONFIG.budget_T - 1
    r = rows[:, None]
    for t, inp in enumerate(rec.seen):
        pos = ep.lattice_idx[:, :t + 1]
        assert inp.step == t and torch.equal(inp.view_positions, pos)
        assert torch.equal(inp.view_probs, cache.log_probs[r, pos][..., 1].exp())
        assert torch.equal(inp.view_valid, cache.valid[r, pos])
        assert torch.allclose(inp.view_scores, conf(cache.cell_features[r, pos]), atol=1e-6)
        assert torch.allclose(inp.fused, ep.maps[:, t], atol=1e-6)
    rec = _Recorder(RandomPolicy())
    run_search(CachedViews(cache, rows), Agent(FUSIONS["average"](), rec), generator=torch.Generator().manual_seed(3))
    assert rec.seen[-1].view_scores is None and rec.seen[-1].view_probs.shape == (4, 4, 100)


def test_teacher_takes_the_best_allowed_move_and_beats_random():
    cache = synthetic_cache(6, seed=4)
    conf = _conf()
    rows = np.repeat(np.arange(6), 4)
    teacher = LabelGreedyTeacher(cache, rows, conf, CONFIG)
    rec = _Recorder(teacher)
    with torch.no_grad():
        ep = run_search(CachedViews(cache, rows, CONFIG, conf), Agent(LearnedFusion(conf), rec))
        for inp, a in zip(rec.seen, ep.actions.T):
            r = teacher.rewards(inp).masked_fill(~action_mask(inp, MOVES), -1e9)
            assert torch.equal(r.gather(1, a[:, None])[:, 0], r.amax(1))
        taught = classification_reward(ep.maps[:, -1], ep.labels).float().mean()
        rand = [classification_reward(run_search(CachedViews(cache, rows, CONFIG, conf), Agent(LearnedFusion(conf), RandomPolicy()),
                                                 generator=torch.Generator().manual_seed(s)).maps[:, -1],
                                      ep.labels).float().mean() for s in range(3)]
    assert not ep.revisit.any()
    assert taught >= max(rand)


def test_reactive_policy_flies_a_single_live_like_episode():
    """B = 1, scores from the agent's confidence net, no labels: what LiveViews hands the loop."""
    cache = synthetic_cache(2)
    conf = _conf()

    class LiveLike:
        config, batch_size, labels = CONFIG, 1, None

        def observe(self, idx):
            p = int(idx.reshape(-1)[0])
            return Observation(cache.log_probs[1:2, p], cache.cell_features[1:2, p], cache.global_feature[1:2, p],
                               cache.cell_area_px[1:2, p], cache.valid[1:2, p])

    torch.manual_seed(1)
    net = ReactivePolicyNet()
    with torch.no_grad():
        live = run_search(LiveLike(), Agent(LearnedFusion(conf), ArgmaxPolicy(net)))
        cached = run_search(CachedViews(cache, [1], CONFIG, conf), Agent(LearnedFusion(conf), ArgmaxPolicy(net)))
    assert torch.equal(live.lattice_idx, cached.lattice_idx) and live.lattice_idx.shape == (1, CONFIG.budget_T)
    assert torch.allclose(live.maps, cached.maps, atol=1e-6)


def test_checkpoint_round_trip_through_build_agent_and_a_mission(tmp_path):
    torch.manual_seed(0)
    net = round_trip_half(ReactivePolicyNet(ReactiveConfig(channels=8, hidden=16)))
    conf = round_trip_half(_conf())
    path = checkpoint_path(2, "learned", tmp_path, policy="reactive")
    assert path.name == "search_s2_learned_reactive.pt"
    assert checkpoint_path(2, "learned", tmp_path).name == "search_s2_learned.pt"
    save_search_model(path, LearnedFusion(conf), net, {"best": {"iteration": 3}})
    fusion, loaded, extra = load_search_model(path)
    assert isinstance(loaded, ReactivePolicyNet) and loaded.cfg == net.cfg and extra["best"]["iteration"] == 3
    agent = build_agent("learned", "reactive", CONFIG, checkpoint=path).agent
    greedy = build_agent("learned", "reactive", CONFIG, checkpoint=path, greedy=True).agent
    assert isinstance(greedy.policy, ArgmaxPolicy) and agent.fusion.trainable
    cache = synthetic_cache(2)
    with torch.no_grad():
        for a, ref in ((agent, net), (greedy, ArgmaxPolicy(net))):
            eps = [run_search(CachedViews(cache, [0, 1, 1]), ag, generator=torch.Generator().manual_seed(5))
                   for ag in (a, Agent(LearnedFusion(conf), ref))]
            assert torch.equal(eps[0].lattice_idx, eps[1].lattice_idx) and torch.allclose(eps[0].maps, eps[1].maps)
    # a paper checkpoint is no reactive policy, and one saved before checkpoints had a kind loads as the paper's
    paper = new_agent("learned", CONFIG, 16, 6)
    old = tmp_path / "old.pt"
    save_search_model(old, paper.fusion, paper.policy)
    ck = torch.load(old, weights_only=True)
    del ck["policy_kind"]
    torch.save(ck, old)
    assert isinstance(load_search_model(old)[1], PolicyNet)
    with pytest.raises(UavsearchError, match="holds a 'paper' policy net, not the 'reactive'"):
        build_agent("learned", "reactive", CONFIG, checkpoint=old)
    with pytest.raises(UavsearchError, match="holds a 'reactive' policy net, not the 'learned'"):
        build_agent("learned", "learned", CONFIG, checkpoint=path)
    m = mission_from_dict({"policy": "reactive"}, "x.yaml")
    assert m.checkpoint_path.name == "search_s2_learned_reactive.pt"
    assert mission_from_dict({"policy": "random"}, "x.yaml").checkpoint_path.name == "search_s2_learned.pt"
    m = mission_from_dict({"policy": "reactive", "checkpoint": str(path), "greedy_policy": True}, "x.yaml")
    loaded = m.agent()
    assert isinstance(loaded.agent.policy, ArgmaxPolicy) and isinstance(loaded.agent.policy.net, ReactivePolicyNet)


def _tiny(tmp_path, **kw):
    torch.manual_seed(0)
    a = new_agent("learned", CONFIG, 16, 6)
    save_search_model(tmp_path / "conf.pt", a.fusion, a.policy)
    base = dict(confidence=str(tmp_path / "conf.pt"), dagger_iterations=2, dagger_episodes=24, dagger_epochs=2,
                batch_size=32, pg_iterations=4, scenes_per_batch=3, episodes_per_scene=2, eval_every=2, channels=8,
                hidden=16, runs_dir=str(tmp_path / "runs"), progress=False)
    base.update(kw)
    return Args(**base)


def _caches():
    return synthetic_cache(8, seed=0), synthetic_cache(3, seed=1)


def test_dagger_lowers_the_imitation_loss_and_a_run_is_reproducible(tmp_path):
    train_cache, val_cache = _caches()
    conf = round_trip_half(_conf())  # as train() loads it from its checkpoint
    # the teacher's moves on the training scenes, and the loss of a fresh net on them
    rows = torch.arange(8).repeat(3)
    fresh = ReactivePolicyNet(ReactiveConfig(channels=8, hidden=16))
    mix = DaggerMixture(fresh, LabelGreedyTeacher(train_cache, rows, conf), 1.0, torch.Generator().manual_seed(0))
    with torch.no_grad():
        run_search(CachedViews(train_cache, rows, CONFIG, conf), Agent(LearnedFusion(conf), mix))
        X, M, Y = mix.aggregate()
        before = float(imitation_loss(fresh, X, M, Y)[0])
    save_search_model(tmp_path / "c.pt", LearnedFusion(conf), fresh)
    res = train(_tiny(tmp_path, confidence=str(tmp_path / "c.pt"), dagger_iterations=3, dagger_epochs=6,
                      pg_iterations=0, mirror=False, plot=False), caches=(train_cache, val_cache))
    _, net, extra = load_search_model(res.checkpoint)
    with torch.no_grad():
        after = float(imitation_loss(net, X, M, Y)[0])
    assert after < before - 0.1
    assert extra["best"]["phase"] == "dagger"

    def run(sub, seed):
        r = train(_tiny(tmp_path / sub, seed=seed, plot=sub == "a"), caches=_caches())
        rows = list(csv.DictReader((r.run_dir / "metrics.csv").open()))
        return rows, load_search_model(r.checkpoint)[1].state_dict(), r

    a, b, c = run("a", 7), run("b", 7), run("c", 8)
    assert a[0] == b[0] and all(torch.equal(a[1][k], b[1][k]) for k in a[1])
    assert a[0] != c[0]
    files = {p.name for p in a[2].run_dir.iterdir()}
    assert {"args.json", "metrics.csv", "learning_curve.png", "model.pt", "summary.json"} <= files
    phases = [row["phase"] for row in a[0]]
    assert phases == ["dagger"] * 2 + ["pg"] * 4 and a[0][1]["eval/af1_vs_coverage"] != ""
    assert [row["method"].split(" (")[0] for row in a[2].table] == [
        "learned fusion + coverage route", "learned fusion + reactive policy", "learned fusion + label-greedy teacher"]


@pytest.mark.parametrize("kw", [dict(beta_decay=1.5), dict(dagger_iterations=0, pg_iterations=0), dict(channels=0)])
def test_bad_arguments_are_one_line_errors(tmp_path, kw):
    with pytest.raises(UavsearchError):
        train(_tiny(tmp_path, **kw), caches=_caches())


def test_a_confidence_checkpoint_without_a_confidence_net_is_refused(tmp_path):
    a = new_agent("average", CONFIG, 16, 6)
    save_search_model(tmp_path / "avg.pt", FUSIONS["average"](), a.policy)
    with pytest.raises(UavsearchError, match="holds no confidence network"):
        train(_tiny(tmp_path, confidence=str(tmp_path / "avg.pt")), caches=_caches())


def test_cli_parser_maps_flags_to_args():
    from uavsearch.cli import build_parser

    parser = argparse.ArgumentParser()
    add_train_reactive_parser(parser.add_subparsers())
    ns = parser.parse_args(["reactive", "--setting", "3", "--pg-iterations", "7", "--confidence", "c.pt", "--ship"])
    assert (ns.setting, ns.pg_iterations, ns.confidence, ns.ship) == (3, 7, "c.pt", True) and callable(ns.func)
    ns = build_parser("train").parse_args(["train", "reactive", "--dagger-iterations", "2"])
    assert ns.dagger_iterations == 2
