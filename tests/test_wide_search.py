"""The wide-area search: its lattice (72 + the start viewpoint, any viewpoint next, flight times), the time
budget of run_search, the baselines' routes and the rule on known maps, and Table III on a tiny synthetic
family (no rendering)."""

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from uavsearch.errors import UavsearchError
from uavsearch.search.agents import build_agent
from uavsearch.search.config import SearchConfig, config_from_dict, config_to_dict, setting_config, wide_budgets
from uavsearch.search.data.view_cache import CacheKey
from uavsearch.search.evaluate.wide import eval_wide, oracle_perception
from uavsearch.search.fusion import FUSIONS
from uavsearch.search.metrics import map_f1
from uavsearch.search.search_loop import Agent, CachedViews, PolicyInput, run_search
from uavsearch.search.wide_policies import (RULE_VARIANTS, SURVEY_OUTER_M, DescendRule, EntropyPerSecond, RoutePolicy,
                                            footprints, greedy_view_set, label_routes, lawnmower, rule_policy,
                                            survey_then_lawnmower, viewpoints_at)
from uavsearch.testing.synthetic_views import synthetic_cache, synthetic_wide_cache

WIDE = setting_config("wide")


def wide_cache(num_scenes=4, seed=0, config=WIDE, k=10):
    """A synthetic cache on the wide lattice where each view measures only its footprint."""
    return synthetic_wide_cache(num_scenes, seed, config, k)


def test_wide_lattice_has_72_viewpoints_plus_the_start():
    lat = WIDE.lattice
    assert lat.num_positions == 73 and lat.start_index == 72 and lat.extra_start
    assert lat.positions_enu[72].tolist() == [0.0, 0.0, 70.0]
    assert lat.positions_enu[0].tolist() == [-62.5, 62.5, 70.0] and lat.positions_enu[36].tolist() == [-62.5, 62.5, 40.0]
    assert WIDE.grid.num_cells == 900 and WIDE.budget_T == 8 and WIDE.budget_s == 240.0
    assert torch.equal(lat.moves[5], torch.arange(73)) and WIDE.num_actions == 73  # any viewpoint next
    t = lat.flight_time_s
    assert t.shape == (73, 73) and t[72, 72] == 0.0 and t[0, 36] == pytest.approx(21.1, abs=0.3)  # 30 m descent
    assert t[0, 1] < t[0, 2] < t[0, 5]  # farther costs more
    assert config_from_dict(config_to_dict(WIDE)) == WIDE and hash(WIDE) == hash(config_from_dict(config_to_dict(WIDE)))
    assert setting_config(2) == SearchConfig() and CacheKey("wide", "large", "test").scenes()[0] == (132000, 10)
    assert CacheKey("wide", "large", "train", limit=3).name == "large_swide_train_first3"


def test_bad_wide_configs_are_one_line_errors():
    with pytest.raises(UavsearchError, match="move_set"):
        SearchConfig(move_set="teleport")
    with pytest.raises(UavsearchError, match="budget_s"):
        SearchConfig(budget_s=-1.0)
    with pytest.raises(UavsearchError, match="odd"):
        dataclasses.replace(WIDE, move_set="steps").lattice.moves


def test_without_budget_s_the_loop_is_unchanged():
    cache = synthetic_cache(3)
    agent = build_agent("average", "random", cache.config).agent
    ep = run_search(CachedViews(cache, [0, 1, 2, 0]), agent, generator=torch.Generator().manual_seed(0))
    assert ep.taken is None and ep.flight_s is None and ep.maps.shape[1] == 5


def test_time_budget_ends_episodes_and_masks_viewpoints():
    cfg = dataclasses.replace(WIDE, budget_T=73, budget_s=30.0)
    cache = wide_cache(2, config=cfg)
    seen = []

    class Far:  # the farthest allowed viewpoint, recording what it was offered
        def act(self, inp, generator=None):
            seen.append((inp.time_left_s.clone(), inp.allowed.clone()))
            cost = torch.as_tensor(cfg.lattice.flight_time_s, dtype=torch.float32)[inp.lattice_idx]
            return torch.where(inp.allowed, cost, torch.full_like(cost, -1.0)).argmax(1), None, None

    ep = run_search(CachedViews(cache, [0, 1]), Agent(FUSIONS["average"](), Far()))
    t = cfg.lattice.flight_time_s
    assert seen[0][0].tolist() == [30.0, 30.0]
    assert torch.equal(seen[0][1][0], torch.as_tensor((t[72] <= 30.0) & (np.arange(73) != 72)))
    assert (ep.flight_s <= 30.0).all() and ep.taken[:, 0].all()
    last = ep.lattice_idx[0, ep.taken[0]][-1]
    left = 30.0 - float(ep.flight_s[0])
    assert not ((t[last] <= left) & ~np.isin(np.arange(73), ep.lattice_idx[0].numpy())).any()  # nothing affordable
    # an ended episode's map stays; the batch stopped when both ended, well before 73 views
    assert ep.maps.shape[1] < 10
    for b in range(2):
        n = int(ep.taken[b].sum())
        assert torch.equal(ep.maps[b, n - 1], ep.maps[b, -1])


def test_a_move_it_cannot_afford_ends_the_episode():
    cfg = dataclasses.replace(WIDE, budget_s=10.0)
    cache = wide_cache(1, config=cfg)
    ep = run_search(CachedViews(cache, [0]), Agent(FUSIONS["average"](), RoutePolicy([0, 1, 2])))
    assert ep.taken[0].tolist() == [True] + [False] * (ep.maps.shape[1] - 1) and float(ep.flight_s[0]) == 0.0


def test_fixed_routes():
    low = lawnmower(WIDE, 40.0)
    assert low[:7] == [36, 37, 38, 39, 40, 41, 47] and sorted(low) == list(range(36, 72))
    assert lawnmower(WIDE, 70.0)[:7] == [0, 1, 2, 3, 4, 5, 11]
    outer = viewpoints_at(WIDE, SURVEY_OUTER_M, 70.0)
    assert WIDE.lattice.positions_enu[outer][:, :2].tolist() == [list(p) for p in SURVEY_OUTER_M]
    assert survey_then_lawnmower(WIDE, SURVEY_OUTER_M)[:5] == outer + [36]
    assert footprints(WIDE)[outer].any(0).all()  # the 4 covering 70 m views see every cell
    with pytest.raises(UavsearchError, match="no viewpoint"):
        viewpoints_at(WIDE, [(0.0, 0.0)], 40.0)


def _inp(fused, visited_idx, positions, low_valid=None, step=5):
    P, N = WIDE.lattice.num_positions, WIDE.grid.num_cells
    visited = torch.zeros(1, P, dtype=torch.bool)
    visited[0, visited_idx] = True
    pos = torch.tensor([positions])
    vv = footprints(WIDE)[pos]
    return PolicyInput(torch.zeros(1, 4), torch.zeros(1, N), fused[None], pos[:, -1], visited, step, 8, pos,
                       torch.zeros(1, len(positions), N), vv, None, None, None)


def test_the_rule_surveys_then_descends_over_the_brightest_unresolved_cell():
    rule = DescendRule(WIDE)
    survey = viewpoints_at(WIDE, SURVEY_OUTER_M, 70.0)
    fused = torch.full((900,), 0.05)
    assert rule.act(_inp(fused, [72], [72], step=0), None)[0].item() == survey[0]
    cell = 15 * 30 + 27  # a bright cell near the east edge, middle row
    fused[cell] = 0.9
    done = [72, *survey]
    a = rule.act(_inp(fused, done, done, step=4), None)[0].item()
    assert WIDE.lattice.positions_enu[a][2] == 40.0 and footprints(WIDE)[a, cell]
    # once a 40 m view has measured the cell, the next descent goes elsewhere
    fused2 = fused.clone()
    fused2[0] = 0.6  # NW corner cell
    b = rule.act(_inp(fused2, done + [a], done + [a], step=5), None)[0].item()
    assert b != a and footprints(WIDE)[b, 0] and WIDE.lattice.positions_enu[b][2] == 40.0
    # with a resurvey threshold: nothing open that likely -> the nearest unvisited 70 m viewpoint; else descend
    keep = DescendRule(WIDE, resurvey_below=0.4)
    dim = torch.full((900,), 0.05)
    here = survey[-1]
    c = keep.act(_inp(dim, done, done, step=4), None)[0].item()
    pos = WIDE.lattice.positions_enu
    assert pos[c][2] == 70.0 and c not in done
    assert np.linalg.norm(pos[c] - pos[here]) == pytest.approx(25.0)  # a neighbour on the 25 m lattice
    assert keep.act(_inp(fused, done, done, step=4), None)[0].item() == a  # 0.9 >= 0.4: the same descent
    assert DescendRule(WIDE, resurvey_below=0.95).act(_inp(fused, done, done, step=4), None)[0].item() != a
    # per second of flight: a near dim spot beats a far bright one; without it the brightest wins
    two = torch.full((900,), 0.05)
    far, near = 29, 25 * 30 + 2  # the NE corner cell, one near the SW corner: the survey ends above the SW
    two[far], two[near] = 0.9, 0.8  # about 30 s and 21 s of flight away
    assert pos[here][0] < 0 and pos[here][1] < 0
    plain = DescendRule(WIDE).act(_inp(two, done, done, step=4), None)[0].item()
    timed = DescendRule(WIDE, per_second_overhead_s=30.0).act(_inp(two, done, done, step=4), None)[0].item()
    assert footprints(WIDE)[plain, far] and footprints(WIDE)[timed, near]


def test_entropy_per_second_prefers_near_uncertainty():
    pol = EntropyPerSecond(WIDE)
    fused = torch.full((900,), 0.01)
    fused[:30 * 5] = 0.5  # the uncertain north rows
    a = pol.act(_inp(fused, [72], [72], step=0), None)[0].item()
    assert WIDE.lattice.positions_enu[a][1] > 0  # north of the centre


def test_route_searches_on_a_known_map():
    cfg = wide_budgets(WIDE)["T = 8 views"]
    cache = wide_cache(3, config=cfg, k=3)
    route = greedy_view_set(cache, FUSIONS["average"](), cfg)
    assert len(route) == 7 and len(set(route)) == 7 and 72 not in route
    routes = label_routes(cache, FUSIONS["average"](), cfg, beam=2)
    assert routes.shape == (3, 7)
    oracle = oracle_perception(cache)
    p = oracle.log_probs[..., 1].exp()
    assert bool(((p > 0.5) == (cache.occupancy[:, None, :] & (cache.person_px > 0))).all())


def test_table3_on_a_tiny_synthetic_family(tmp_path):
    caches = {"wide": {"test": wide_cache(3, 1), "val": wide_cache(2, 2), "train": wide_cache(2, 3)}}
    # a learned policy for the time budget only: that table gets its row, the other does not
    from uavsearch.search.map_policy import MapPolicyConfig, MapPolicyNet, wide_checkpoint
    from uavsearch.search.policy import save_search_model

    timed_cfg = wide_budgets(WIDE)["240 s"]
    save_search_model(wide_checkpoint("240", tmp_path / "models"), FUSIONS["average"](),
                      MapPolicyNet(MapPolicyConfig(config_to_dict(timed_cfg))), {"args": {"family": "wide-uniform"}})
    args = SimpleNamespace(out=str(tmp_path), wide_fusion="average", episodes=2, seeds=1, bootstrap=200,
                           bootstrap_seed=0, perception="models/perception.pt", progress=False,
                           wide_policy_dir=str(tmp_path / "models"))
    res = eval_wide(args, ["wide"], caches)
    text = (tmp_path / "table3.md").read_text()
    assert "the rule" in text and "(best fixed)" in text and "240 s" in text and "T = 8 views" in text
    rows = res["rows"]
    assert len(rows) == 12 + 13 and (tmp_path / "table3.csv").is_file() and (tmp_path / "table3_paired.csv").is_file()
    # Fig. 6's curves end where the table's AF1 does: after the last view, and at the end of the time budget
    assert res["figure"] == tmp_path / "fig6.png" and res["figure"].stat().st_size > 10_000
    for (_, name), cond in res["conditions"].items():
        for key, r in cond["results"].items():
            final = float(r["f1"][:, :, -1].mean())
            curve = r["f1_by_s"] if name == "240 s" else r["f1_by_view"]
            assert curve[-1] == pytest.approx(final, abs=1e-9), (name, key)
            assert r["f1_by_s"][0] == pytest.approx(r["f1_by_view"][0], abs=1e-9)  # at 0 s: the start view
    ours = [r for r in rows if r["key"] == "map_policy"]
    assert [r["budget"] for r in ours] == ["240 s"] and np.isfinite(ours[0]["vs_rule"])
    assert np.isfinite(ours[0]["vs_best_fixed"]) and text.count("ours: learned wide-area policy") == 1
    assert "search_wide_240s_map.pt (average:0.1), trained on `wide-uniform`'s training scenes" in text
    # a checkpoint made for the other budget is refused in one line
    from uavsearch.search.agents import load_wide_agent

    with pytest.raises(UavsearchError, match="trained for 240 s of flight, this search has T = 8 views"):
        load_wide_agent(wide_checkpoint("240", tmp_path / "models"), wide_budgets(WIDE)["T = 8 views"])
    timed = [r for r in rows if r["budget"] == "240 s"]
    assert all(r["flight_s"] <= 240.0 + 1e-6 for r in timed)
    views = [r for r in rows if r["budget"] == "T = 8 views"]
    assert all(r["views"] <= 8 for r in views)
    hs = next(r for r in views if r["key"] == "hindsight")
    lg = next(r for r in views if r["key"] == "label_greedy")
    assert hs["af1"] >= lg["af1"] - 1e-9


def test_table3_names_the_two_stacks_when_the_learned_policy_carries_a_learned_aggregation(tmp_path):
    """A learned policy whose checkpoint carries the neighbour fusion: Table III then has the hand-made stack (the
    rule on the hand-made fusion), the learned stack, the rule on the learned aggregation (its variant chosen on
    validation with it), and every row paired against the learned stack too."""
    from uavsearch.search.fusion import CalibratedFusion
    from uavsearch.search.map_policy import MapPolicyConfig, MapPolicyNet, wide_checkpoint
    from uavsearch.search.neighbour_fusion import CorrectionNet, NeighbourFusion
    from uavsearch.search.policy import save_search_model

    caches = {"wide": {"test": wide_cache(3, 1), "val": wide_cache(2, 2), "train": wide_cache(2, 3)}}
    cfg = wide_budgets(WIDE)["T = 8 views"]
    torch.manual_seed(0)
    learned = NeighbourFusion.around(CalibratedFusion((1.1, -0.05, -0.3, 0.02), 0.08, 0.25), CorrectionNet(kernel=3),
                                     0.25, cfg)
    save_search_model(wide_checkpoint("8", tmp_path / "models"), learned,
                      MapPolicyNet(MapPolicyConfig(config_to_dict(cfg))), {"args": {"family": "wide"}})
    args = SimpleNamespace(out=str(tmp_path), wide_fusion="average", episodes=2, seeds=1, bootstrap=200,
                           bootstrap_seed=0, perception="models/perception.pt", progress=False,
                           wide_policy_dir=str(tmp_path / "models"))
    res = eval_wide(args, ["wide"], caches)
    rows = [r for r in res["rows"] if r["budget"] == "T = 8 views"]
    keys = [r["key"] for r in rows]
    assert keys[keys.index("descend_rule"):keys.index("descend_rule") + 3] == ["descend_rule", "map_policy",
                                                                             "rule_learned"]
    by = {r["key"]: r for r in rows}
    assert by["descend_rule"]["method"].startswith("the hand-made stack")
    assert by["map_policy"]["method"].startswith("the learned stack")
    assert np.isfinite(by["rule_learned"]["vs_learned"]) and np.isfinite(by["descend_rule"]["vs_learned"])
    assert not np.isfinite(by["map_policy"]["vs_learned"])  # the reference itself
    # the rule on the learned aggregation is the rule flying the learned fusion, with its own variant
    cond = res["conditions"][("wide", "T = 8 views")]
    variant = cond["rule_learned_variant"]
    assert variant in cond["rule_learned_variant_af1"]
    ep = run_search(CachedViews(caches["wide"]["test"], np.arange(3), cfg), Agent(learned.eval(),
                                                                                  rule_policy(cfg, variant)))
    assert by["rule_learned"]["af1"] == pytest.approx(map_f1(ep.maps[:, -1].numpy(),
                                                             caches["wide"]["test"].occupancy.numpy()).mean(), abs=1e-6)
    text = (tmp_path / "table3.md").read_text()
    section = text.split("### wide, T = 8 views")[1].split("###")[0]
    assert "Δ AF1 vs the learned policy" in section and f"with that fusion, {variant} (" in section
    import re

    # the choices' parser (table3_choices) reads the hand-made stack's variant: the first bold one
    assert re.search(r"chosen on the validation scenes: \*\*([^*]+)\*\*", section).group(1) == cond["rule_variant"]
    other = text.split("### wide, 240 s")[1]
    assert "Δ AF1 vs the learned policy" not in other  # no learned policy for that budget here


def test_family_perception_report_judges_each_altitude_on_its_own_views(tmp_path):
    from uavsearch.search.evaluate.perception import EvalArgs, eval_perception

    cache = wide_cache(3, 4)
    alt = torch.as_tensor(WIDE.lattice.positions_enu[:, 2].copy())
    occ = cache.occupancy[:, None, :].expand_as(cache.valid)
    # 40 m views: perfect; 70 m views: every empty cell in view fires
    p = torch.where((alt == 40.0)[None, :, None], occ.float(), torch.ones_like(occ, dtype=torch.float32))
    p = p.clamp(1e-3, 1 - 1e-3)
    net = cache._replace(log_probs=torch.stack([(1 - p).log(), p.log()], -1), person_px=occ.int() * 9)
    args = EvalArgs(out=str(tmp_path / "same"), setting="wide")
    res = eval_perception(args, {"net": net, "reference": net})
    low, high = res["stats"]["40 m"], res["stats"]["70 m"]
    assert low["recall_8px"] == 1.0 and low["fa_per_cell_view"] == 0.0
    assert high["fa_per_cell_view"] == 1.0 and high["views"] == 3 * 37
    text = (tmp_path / "same" / "perception_targets.md").read_text()
    assert "| recall at >= 8 visible person pixels at 40 m | >= 0.75 | 1.000 | 1.000 | yes |" in text
    assert "holds up against the reference: yes" in text
    # a net that misses every occupied cell at 70 m falls short of a reference that finds them
    miss = torch.where((alt == 70.0)[None, :, None], torch.full_like(p, 1e-3), p)
    worse = net._replace(log_probs=torch.stack([(1 - miss).log(), miss.log()], -1))
    eval_perception(dataclasses.replace(args, out=str(tmp_path / "worse")), {"net": worse, "reference": net})
    assert "holds up against the reference: **no**" in (tmp_path / "worse" / "perception_targets.md").read_text()


def test_wide_fusion_specs():
    from uavsearch.search.fusion import fusion_name
    from uavsearch.search.agents import make_fusion

    assert fusion_name(make_fusion("bayes")) == "bayes:0.1"
    assert fusion_name(make_fusion("bayes:0.02")) == "bayes:0.02" and make_fusion("size").name == "size"
    for bad in ("learned", "oracle", "bayes:2", "bayes:x", "nope"):
        with pytest.raises(UavsearchError):
            make_fusion(bad)


def test_table3_chooses_its_fusion_on_validation(tmp_path):
    from uavsearch.search.evaluate.wide import choose_fusion

    val = wide_cache(2, 5)
    fusion, scores = choose_fusion(val, dataclasses.replace(WIDE, budget_s=None), ("bayes:0.1", "average"))
    assert set(scores) == {"bayes:0.1", "average:0.1"} and all(0.0 <= v <= 1.0 for v in scores.values())
    assert f"{fusion.name}:{fusion.prior:g}" == max(scores, key=scores.get)
    caches = {"wide": {"test": wide_cache(2, 1), "val": val, "train": wide_cache(2, 3)}}
    args = SimpleNamespace(out=str(tmp_path), wide_fusion="auto", episodes=1, seeds=1, bootstrap=100, wide_policy_dir=str(tmp_path),
                           bootstrap_seed=0, perception="models/perception.pt", progress=False)
    res = eval_wide(args, ["wide"], caches)
    text = (tmp_path / "table3.md").read_text()
    assert text.count("chosen on the validation scenes by the mean AF1") == 2
    assert {r["fusion"] for r in res["rows"]} <= {"bayes:0.05", "bayes:0.1", "bayes:0.2", "bayes:0.3", "bayes:0.5",
                                                  "average:0.1", *(f"calibrated:{g:g}" for g in (0, 0.25, 0.5, 0.75, 1))}
    assert "calibrated:0.25" in text  # fitted on the training cache, scored on validation beside the others
    assert text.count("The rule's survey (70 m views), the fused p below which it keeps surveying") == 2
    for cond in res["conditions"].values():
        assert cond["rule_variant"] in cond["rule_variant_af1"] and set(cond["rule_variant_af1"]) == set(RULE_VARIANTS)
    assert {"4 covering", "4 covering + 4 inner, resurvey below p 0.4", "4 covering, resurvey below p 0.5, per second"} <= set(RULE_VARIANTS)


def test_table3_calibrated_fusion_is_fitted_on_the_training_scenes():
    from uavsearch.search.agents import make_fusion
    from uavsearch.search.fusion import calibrated_candidates

    train = wide_cache(2, 3)
    fits = calibrated_candidates(train)
    assert [f.gamma for f in fits] == [0.0, 0.25, 0.5, 0.75, 1.0] and len({tuple(f.coef) for f in fits}) == 1
    assert fits[0].prior == pytest.approx(train.occupancy.float().mean().item(), rel=0.05)
    one = make_fusion("calibrated:0.25", train)
    assert (one.spec, one.coef) == ("calibrated:0.25", fits[0].coef)
    for bad in ("calibrated:2", "calibrated:x"):
        with pytest.raises(UavsearchError, match="discount"):
            make_fusion(bad, train)
        with pytest.raises(UavsearchError, match="discount"):  # before any cache is built (none is given here)
            eval_wide(SimpleNamespace(wide_fusion=bad), ["wide"])


def test_f1_by_seconds_reads_the_map_after_the_views_taken_by_then():
    from uavsearch.search.evaluate.wide import f1_by_seconds

    cfg = wide_budgets(WIDE)["240 s"]
    t = cfg.lattice.flight_time_s
    s, a, b = cfg.lattice.start_index, 0, 5
    idx = torch.tensor([[s, a, b, b]])  # the episode ended after three views: its last column repeats
    f1 = np.array([[0.1, 0.2, 0.3, 0.3]])
    seconds = np.array([0.0, t[s, a] - 1.0, t[s, a], t[s, a] + t[a, b], 240.0])
    assert f1_by_seconds(cfg, idx, f1, seconds).tolist() == [[0.1, 0.1, 0.2, 0.3, 0.3]]


def test_rows_of_seeds_whose_episodes_take_different_numbers_of_views():
    """Under a time budget a stochastic row's seeds may end after different numbers of views: the F1-by-view
    curve holds each seed's final F1 instead of failing on ragged curves."""
    from uavsearch.search.evaluate.wide import run_rows
    from uavsearch.search.wide_policies import MaskedRandom

    cfg = dataclasses.replace(WIDE, budget_T=73, budget_s=60.0)
    cache = wide_cache(2, config=cfg)
    agent = Agent(FUSIONS["average"](), MaskedRandom(cfg))
    lengths = []
    for s in range(6):
        ep = run_search(CachedViews(cache, [0, 1]), agent, generator=torch.Generator().manual_seed(s))
        lengths.append(ep.maps.shape[1])
    assert len(set(lengths)) > 1  # the seeds really differ in length
    res = run_rows(cache, cfg, {"random": (agent, 2)}, seeds=6)["random"]
    assert res["f1_by_view"].shape == (max(lengths),) and np.isfinite(res["f1_by_view"]).all()
