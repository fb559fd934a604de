"""The one episode engine (search/episode.py): its event order, a team's separation of viewpoints, batched runs
equal to episodes run one by one, and the envs' buffered state following run_search's episodes. Synthetic caches:
no rendering."""

import dataclasses

import numpy as np
import torch

from uavsearch.search.cells import SearchBatch, TableSource, cell_tables
from uavsearch.search.config import setting_config
from uavsearch.search.episode import SearchState
from uavsearch.search.fusion import FUSIONS
from uavsearch.search.policy import GreedyUncertainty
from uavsearch.search.search_loop import Agent, CachedViews, run_search
from uavsearch.search.team import TeamRule, run_team
from uavsearch.search.wide_policies import DescendRule, footprints
from uavsearch.testing.synthetic_views import synthetic_cache

PAPER_CFG = setting_config(2)
PAPER = synthetic_cache(5, k=5, seed=3)
WIDE_CFG = setting_config("wide")
WIDE = synthetic_cache(4, k=10, seed=4, config=WIDE_CFG)
WIDE = WIDE._replace(valid=footprints(WIDE_CFG)[None].expand(4, -1, -1).clone())


def test_the_next_vehicle_to_arrive_acts():
    st = SearchState(WIDE_CFG, FUSIONS["bayes"](), 2, 3, team=True)
    st.clock_s[:] = torch.tensor([[5.0, 2.0, 2.0], [1.0, 9.0, 0.5]], dtype=torch.float64)
    v, live, now = st.next_vehicle()
    assert v.tolist() == [1, 2] and live.all() and now.tolist() == [2.0, 0.5]  # ties: the lower vehicle
    st.stop(torch.tensor([1, 2]), torch.tensor([True, True]))
    v, _, now = st.next_vehicle()
    assert v.tolist() == [2, 0] and now.tolist() == [2.0, 1.0]  # a stopped vehicle never acts again
    st.stop(torch.zeros(2, dtype=torch.long), torch.tensor([False, True]))
    st.stop(torch.ones(2, dtype=torch.long), torch.tensor([False, True]))
    v, live, now = st.next_vehicle()
    assert live.tolist() == [True, False] and now[1] == 0.0


def test_a_team_never_chooses_a_claimed_viewpoint():
    """A vehicle's choices exclude where another vehicle flies; one vehicle alone may revisit."""
    st = SearchState(WIDE_CFG, FUSIONS["bayes"](), 1, 2, team=True, budget_s=1e6)
    st.take(CachedViews(WIDE, [0], WIDE_CFG), torch.zeros(1, dtype=torch.long))
    st.capture[:, 0] = False
    st.fly(torch.ones(1, dtype=torch.long), torch.tensor([5]), torch.tensor([True]), torch.zeros(1, dtype=torch.float64))
    zero = torch.zeros(1, dtype=torch.long)
    allowed = st.choices(st.visited(zero), st.pos[:, 0], torch.zeros(1, dtype=torch.float64))
    start = WIDE_CFG.lattice.start_index
    assert not allowed[0, 5] and not allowed[0, start] and allowed[0].sum() == WIDE_CFG.lattice.num_positions - 2
    alone = SearchState(WIDE_CFG, FUSIONS["bayes"](), 1)
    alone.take(CachedViews(WIDE, [0], WIDE_CFG))
    assert alone.visited()[0, start] and alone.visited().sum() == 1


def _same(a, b):
    """Decisions bit for bit; float32 maps to rounding (a sum over views rounds by the batch's layout: the envs
    keep float64 buffers where bits matter)."""
    for x, y in zip(a, b):
        if isinstance(x, torch.Tensor) and x.is_floating_point():
            torch.testing.assert_close(x, y, atol=1e-6, rtol=0)
        elif isinstance(x, torch.Tensor):
            assert torch.equal(x, y)
        else:
            assert x == y


def test_batched_episodes_equal_episodes_one_by_one():
    """B episodes stepped together give each episode's episode, alone and in a team."""
    cfg = dataclasses.replace(WIDE_CFG, budget_s=150.0)
    rows = [2, 0, 3, 1]
    for config, cache, policy in [(PAPER_CFG, PAPER, GreedyUncertainty(PAPER_CFG)), (cfg, WIDE, DescendRule(cfg))]:
        agent = Agent(FUSIONS["bayes"](), policy)
        batch = run_search(CachedViews(cache, rows, config), agent)
        for b, r in enumerate(rows):
            one = run_search(CachedViews(cache, [r], config), agent)
            _same([x[b:b + 1] if isinstance(x, torch.Tensor) and x.dim() else x for x in batch], one)
    team = run_team(CachedViews(WIDE, rows, WIDE_CFG), FUSIONS["average"](), TeamRule(WIDE_CFG), 3, 90.0)
    for b, r in enumerate(rows):
        one = run_team(CachedViews(WIDE, [r], WIDE_CFG), FUSIONS["average"](), TeamRule(WIDE_CFG), 3, 90.0)
        E = one.vehicle.shape[1]  # a batch runs until its longest episode ends: its later events take nothing
        assert not team.taken[b, E:].any()
        _same([getattr(team, f)[b, :E] for f in ("vehicle", "lattice_idx", "time_s", "taken", "maps")],
              [getattr(one, f)[0] for f in ("vehicle", "lattice_idx", "time_s", "taken", "maps")])


def test_the_envs_state_follows_run_search():
    """The envs' buffered engine, stepped with the actions run_search chose, takes the same views, revisits and
    time, and fuses the same maps (float64 buffers: equal to float32 rounding)."""
    cfg = dataclasses.replace(WIDE_CFG, budget_s=150.0)
    for config, cache, policy in [(PAPER_CFG, PAPER, GreedyUncertainty(PAPER_CFG)), (cfg, WIDE, DescendRule(cfg))]:
        fusion = FUSIONS["bayes"]()
        rows = np.arange(cache.num_scenes)
        ep = run_search(CachedViews(cache, rows, config), Agent(fusion, policy))
        env = SearchBatch(config, fusion, len(rows))
        env.source = TableSource(cell_tables(cache, fusion), len(rows))
        env.source.rows[:] = torch.as_tensor(rows)
        env.start(rows, cache.occupancy[rows])
        taken = ep.taken if ep.taken is not None else torch.ones_like(ep.revisit)
        for t in range(ep.lattice_idx.shape[1]):
            if t:
                live = taken[:, t] & ~env.done
                env.step(ep.actions[:, t - 1], active=live)
                assert torch.equal(env.revisit[live], ep.revisit[live, t])
            assert torch.equal(env.idx[taken[:, t]], ep.lattice_idx[taken[:, t], t])
            torch.testing.assert_close(env.fused[taken[:, t]], ep.maps[taken[:, t], t], atol=1e-6, rtol=0)
        assert env.done.all()
        if ep.flight_s is not None:
            assert torch.equal(torch.from_numpy(env.state.clock_s[:, 0]).float(), ep.flight_s)


class _FeatureReader(GreedyUncertainty):
    """A policy that says it reads per-view features: it records what each decision saw."""

    reads_view_features = True

    def __init__(self, config):
        super().__init__(config)
        self.seen = []

    def act(self, state, generator=None):
        self.seen.append((state.view_positions.clone(), state.view_features))
        return super().act(state, generator)


def test_a_policy_that_reads_view_features_gets_every_view_s_features():
    """The engine stacks each view's cell features into the policy's input for a policy that asks (and only then)."""
    reader = _FeatureReader(PAPER_CFG)
    rows = [0, 1, 2]
    source = CachedViews(PAPER, rows, PAPER_CFG, features=True)
    run_search(source, Agent(FUSIONS["average"](), reader), generator=torch.Generator().manual_seed(0))
    assert len(reader.seen) == PAPER_CFG.budget_T - 1
    for t, (positions, feats) in enumerate(reader.seen):
        assert feats.shape == (len(rows), t + 1, PAPER_CFG.grid.num_cells, PAPER.cell_features.shape[-1])
        for b, row in enumerate(rows):
            expect = PAPER.cell_features[row, positions[b]]
            assert torch.equal(feats[b], expect.to(feats.dtype))
    plain = GreedyUncertainty(PAPER_CFG)
    seen = []
    plain.act = lambda state, generator=None, _act=plain.act: (seen.append(state.view_features), _act(state, generator))[1]
    run_search(source, Agent(FUSIONS["average"](), plain), generator=torch.Generator().manual_seed(0))
    assert seen and all(f is None for f in seen)
