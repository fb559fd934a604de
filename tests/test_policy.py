"""Policies, the shared search loop and the view cache: move rules, routes, gradients, checkpoints."""

import numpy as np
import pytest
import torch

from uavsearch.testing.synthetic_views import synthetic_cache
from uavsearch.errors import UavsearchError
from uavsearch.search.fusion import FUSIONS, LearnedFusion
from uavsearch.search.config import SearchConfig
from uavsearch.search.perception import ConfidenceNet
from uavsearch.search.policy import (
    ArgmaxPolicy,
    CoverageRoute,
    GreedyUncertainty,
    PolicyConfig,
    PolicyNet,
    RandomPolicy,
    coverage_route,
    load_search_model,
    round_trip_half,
    save_search_model,
)
from uavsearch.search.search_loop import (
    Agent,
    CachedViews,
    PolicyInput,
    classification_reward,
    run_search,
    step_rewards,
)

CONFIG = SearchConfig()
AHEAD, RIGHT, LEFT, BACK = range(4)


class Fixed:
    """Always the same action."""

    def __init__(self, a):
        self.a = a

    def act(self, inp, generator=None):
        return torch.full((inp.lattice_idx.shape[0],), self.a), None, None


def _inp(B=3, fused=None, idx=None, visited=None, g=16):
    P = 25
    idx = torch.full((B,), 12) if idx is None else idx
    if visited is None:
        visited = torch.zeros(B, P, dtype=torch.bool)
        visited[torch.arange(B), idx] = True
    return PolicyInput(torch.rand(B, g), torch.ones(B, 100), torch.full((B, 100), 0.05) if fused is None else fused,
                       idx, visited, 0, 5)


def test_lattice_moves_follow_the_env_rules():
    m = CONFIG.lattice.moves
    c = CONFIG.lattice.start_index
    assert c == CONFIG.lattice.index((0, 0)) == 12
    assert m[c, AHEAD] == CONFIG.lattice.index((0, 1))
    assert m[c, RIGHT] == CONFIG.lattice.index((1, 0))
    assert m[c, LEFT] == CONFIG.lattice.index((-1, 0))
    assert m[c, BACK] == CONFIG.lattice.index((0, -1))
    nw = CONFIG.lattice.index((-2, 2))
    assert m[nw, AHEAD] == nw and m[nw, LEFT] == nw  # leaving the lattice keeps the camera in place
    assert m[nw, RIGHT] == CONFIG.lattice.index((-1, 2))


def test_run_search_revisits_and_start_view():
    cache = synthetic_cache(3)
    ep = run_search(CachedViews(cache, [0, 1, 2]), Agent(FUSIONS["average"](), Fixed(AHEAD)))
    north = [12, 7, 2, 2, 2]
    assert ep.lattice_idx.tolist() == [north] * 3
    assert ep.revisit.tolist() == [[False, False, False, True, True]] * 3
    # The first fused map is the start view's own estimate (every cell is in view).
    assert torch.allclose(ep.maps[:, 0], cache.log_probs[:3, 12, :, 1].exp().double().float(), atol=1e-6)
    # And the last one is the average over the five views taken.
    p = cache.log_probs[0, north, :, 1].exp()
    assert torch.allclose(ep.maps[0, -1].float(), p.mean(0), atol=1e-6)


def test_on_step_reports_each_view_before_the_next_and_changes_nothing():
    """The hook sees view t (its map, the move chosen after it, its reward) before view t+1 is taken; the
    episode is the same with and without it, and the step rewards add up to R_cls + R_re."""
    cache = synthetic_cache(2)
    conf = ConfidenceNet(cache.cell_features.shape[-1]).eval()  # no dropout: two runs comparable
    events, infos = [], []

    class Watched(CachedViews):
        def observe(self, lattice_idx):
            events.append(("observe", lattice_idx.clone()))
            return super().observe(lattice_idx)

    def on_step(info):
        events.append(("step", info.t))
        infos.append(info)

    def episode(views, **kw):
        with torch.no_grad():
            return run_search(views, Agent(LearnedFusion(conf), RandomPolicy()), generator=torch.Generator().manual_seed(3),
                              **kw)

    rows = [0, 1, 1]
    plain = episode(CachedViews(cache, rows, confidence=conf))
    ep = episode(Watched(cache, rows, confidence=conf), on_step=on_step)
    assert all(torch.equal(getattr(ep, k), getattr(plain, k)) for k in ("lattice_idx", "actions", "revisit", "maps"))
    T = CONFIG.budget_T
    assert [e[0] for e in events] == ["observe", "step"] * T and [i.t for i in infos] == list(range(T))
    for t, info in enumerate(infos):
        assert torch.equal(info.viewpoint, ep.lattice_idx[:, t]) and torch.equal(info.fused, ep.maps[:, t])
        assert torch.equal(info.revisit, ep.revisit[:, t]) and info.scores.shape == (3, 100)
        assert torch.equal(info.p, cache.log_probs[torch.tensor(rows), ep.lattice_idx[:, t], :, 1].exp())
        assert info.action is None if t == T - 1 else torch.equal(info.action, ep.actions[:, t])
    rewards = torch.stack([i.reward for i in infos], 1)
    assert torch.equal(rewards, step_rewards(ep.maps, ep.labels, ep.revisit))
    total = classification_reward(ep.maps[:, -1], ep.labels).float() - 0.5 * ep.revisit.sum(1)
    assert torch.equal(rewards.sum(1), total)
    assert torch.equal(step_rewards(ep.maps, ep.labels, ep.revisit, shaped=True).sum(1), total)
    assert ep.revisit.any(), "the seed should give a revisit, so R_re is tested"


def test_learned_fusion_backpropagates_into_the_confidence_net():
    torch.manual_seed(0)  # the net's initial weights
    cache = synthetic_cache(2)
    conf = ConfidenceNet(cache.cell_features.shape[-1])
    ep = run_search(CachedViews(cache, [0, 1]), Agent(LearnedFusion(conf), RandomPolicy()), generator=torch.Generator().manual_seed(0))
    ep.maps[:, -1].sum().backward()
    *hidden, (out_bias_name, out_bias) = list(conf.named_parameters())
    assert out_bias_name.endswith("bias") and out_bias.numel() == 1
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for _, p in hidden)
    # the softmax over views ignores a shift shared by every score: the output bias gets no gradient
    assert out_bias.grad is not None and out_bias.grad.abs().item() < 1e-5


def test_learned_fusion_needs_a_confidence_net_and_oracle_the_truth():
    cache = synthetic_cache(1)
    with pytest.raises(UavsearchError):
        run_search(CachedViews(cache, [0]), Agent(LearnedFusion(), RandomPolicy()))
    src = CachedViews(cache, [0])
    src.labels = None
    with pytest.raises(UavsearchError, match="ground truth"):
        run_search(src, Agent(FUSIONS["oracle"](), RandomPolicy()))


def test_policy_net_samples_reproducibly_and_gives_log_probs():
    torch.manual_seed(0)
    net = PolicyNet(PolicyConfig(global_dim=16))
    inp = _inp(B=64)
    a1, lp, ent = net.act(inp, torch.Generator().manual_seed(3))
    a2, _, _ = net.act(inp, torch.Generator().manual_seed(3))
    assert torch.equal(a1, a2) and a1.shape == (64,)
    logits = net.logits(inp)
    assert torch.allclose(lp, torch.log_softmax(logits, -1).gather(1, a1[:, None])[:, 0])
    assert (ent > 0).all() and (ent <= np.log(4) + 1e-6).all()
    ag, _, _ = ArgmaxPolicy(net).act(inp)
    assert torch.equal(ag, logits.argmax(-1))
    # The state grows by the extras (position, visited, step) only when asked.
    assert PolicyConfig(global_dim=16).state_in == 512 + 200 + 55
    assert PolicyConfig(global_dim=16, extras=False).state_in == 712


def test_random_policy_is_uniform_and_seeded():
    r = RandomPolicy()
    a, lp, _ = r.act(_inp(B=4000), torch.Generator().manual_seed(1))
    assert lp is None
    counts = torch.bincount(a, minlength=4).float() / 4000
    assert (counts - 0.25).abs().max() < 0.03
    assert torch.equal(a, r.act(_inp(B=4000), torch.Generator().manual_seed(1))[0])


def test_coverage_route_never_revisits_and_sees_every_cell_closer():
    route = coverage_route(CONFIG)
    assert len(route) == CONFIG.budget_T - 1
    m, pos = CONFIG.lattice.moves, [CONFIG.lattice.start_index]
    for a in route:
        pos.append(int(m[pos[-1], a]))
    assert len(set(pos)) == len(pos)
    d = CONFIG.lattice.cell_distances
    assert d[pos].amin(0).sum() < d[[12, 7, 2, 2, 2]].amin(0).sum()  # beats flying straight into the edge
    ep = run_search(CachedViews(synthetic_cache(2), [0, 1]), Agent(FUSIONS["average"](), CoverageRoute(CONFIG)))
    assert ep.lattice_idx[0].tolist() == pos == ep.lattice_idx[1].tolist()


def test_greedy_moves_toward_uncertain_cells_and_avoids_revisits():
    g = GreedyUncertainty(CONFIG)
    fused = torch.full((1, 100), 0.01)
    fused[0, [7, 8, 9, 17, 18, 19]] = 0.5  # uncertain cells in the north-east corner
    a, _, _ = g.act(_inp(B=1, fused=fused))
    assert a.item() in (AHEAD, RIGHT)
    # From the centre with north and east already visited it must take a new position.
    visited = torch.zeros(1, 25, dtype=torch.bool)
    visited[0, [12, 7, 13]] = True
    a, _, _ = g.act(_inp(B=1, fused=fused, visited=visited))
    assert a.item() in (LEFT, BACK)


def test_search_model_round_trip(tmp_path):
    torch.manual_seed(0)
    net, conf = PolicyNet(PolicyConfig(global_dim=16)), ConfidenceNet(6)
    round_trip_half(net), round_trip_half(conf)
    path = save_search_model(tmp_path / "m.pt", LearnedFusion(conf), net, {"note": 1})
    fusion, net2, extra = load_search_model(path)
    assert isinstance(fusion, LearnedFusion) and extra == {"note": 1}
    conf2 = fusion.net
    inp = _inp()
    net.eval(), conf.eval()
    assert torch.equal(net.logits(inp), net2.logits(inp))
    x = torch.rand(5, 6)
    assert torch.equal(conf(x), conf2(x))
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(UavsearchError):
        load_search_model(tmp_path / "bad.pt")
    with pytest.raises(UavsearchError):
        load_search_model(tmp_path / "missing.pt")


@pytest.mark.slow  # renders live views (about 12 s): `make test-all` runs it
def test_view_cache_matches_live_perception_on_the_teleport_vehicle(tmp_path):
    """The cached outputs of a scene equal running perception on a fresh capture (the flight path)."""
    from uavsearch.search.perception import PerceptionNet
    from uavsearch.search.search_loop import LiveViews
    from uavsearch.search.data.view_cache import CacheKey, build_view_cache, load_view_cache
    from uavsearch.search.views import TeleportVehicle
    from uavsearch.world.scene import generate_scene

    torch.manual_seed(0)
    net = PerceptionNet().eval()
    key = CacheKey(1, "paper", "test")
    seed, k = key.scenes()[0]
    path = build_view_cache(net, key, scenes=[(seed, k)], cache_dir=tmp_path, workers=1, progress=False)
    cache = load_view_cache(path)
    assert cache.log_probs.shape[:3] == (1, 25, 100) and cache.occupancy.sum() == k
    assert build_view_cache(net, key, scenes=[(seed, k)], cache_dir=tmp_path, progress=False) == path  # reused
    with TeleportVehicle(generate_scene(seed, k), CONFIG) as vehicle:
        live = LiveViews(vehicle, net, labels=cache.occupancy[0].numpy())
        ep_live = run_search(live, Agent(FUSIONS["bayes"](), Fixed(RIGHT)))
        ep_cache = run_search(CachedViews(cache, [0]), Agent(FUSIONS["bayes"](), Fixed(RIGHT)))
    assert torch.equal(ep_live.lattice_idx, ep_cache.lattice_idx)
    assert torch.allclose(ep_live.maps, ep_cache.maps, atol=1e-5)
    assert len(live.views) == CONFIG.budget_T
    # person_px comes through build/load: each visited view's person pixels per cell, counted afresh here
    assert cache.person_px.shape == (1, 25, 100) and cache.person_px.dtype == torch.int32
    for t, view in enumerate(live.views):
        lab = view.cell_label
        fresh = np.bincount(lab[view.person_mask & (lab >= 0)].astype(np.int64), minlength=100)[:100]
        assert np.array_equal(cache.person_px[0, int(ep_live.lattice_idx[0, t])].numpy(), fresh)
    assert cache.subset([0]).person_px.shape == (1, 25, 100)
