"""What Table II is measured against (bounds.py) and the perception targets report (eval_perception.py), on
synthetic view caches: no rendering, no perception net."""

import argparse
import csv

import numpy as np
import pytest
import torch

from uavsearch.testing.synthetic_views import synthetic_cache
from test_eval_search import _models
from uavsearch.errors import UavsearchError
from uavsearch.parallel import npz_bytes
from uavsearch.search.evaluate.bounds import (
    FixedRoutes,
    all_routes,
    bootstrap_ci,
    hidden_shares,
    label_greedy_af1,
    paired_differences,
    route_af1,
    route_bounds,
    scene_af1,
)
from uavsearch.search.fusion import FUSIONS, LearnedFusion
from uavsearch.search.config import SearchConfig
from uavsearch.search.evaluate.perception import (
    EvalArgs as PerceptionArgs,
    add_eval_perception_parser,
    eval_perception,
    perception_stats,
    targets_figure,
)
from uavsearch.search.evaluate.search import ROWS, EvalArgs, eval_search
from uavsearch.search.scoring import evaluate_agent
from uavsearch.search.perception import ConfidenceNet
from uavsearch.search.policy import CoverageRoute, RandomPolicy
from uavsearch.search.search_loop import Agent, CachedViews, run_search
from uavsearch.search.data.view_cache import FORMAT, ViewCache, load_view_cache
from uavsearch.viz import overflow_in, pyplot

CONFIG = SearchConfig()


def _with_person_px(cache, seed=0):
    g = torch.Generator().manual_seed(seed)
    return cache._replace(person_px=torch.randint(0, 20, cache.valid.shape, generator=g, dtype=torch.int32))


def _result(per_scene_f1, seeds=2, episodes=3):
    """An evaluated row whose every episode of scene s scores per_scene_f1[s]."""
    f1 = np.repeat(np.asarray(per_scene_f1, float), episodes)[None, :, None].repeat(seeds, 0).repeat(5, 2)
    return {"f1": f1, "acc": f1, "scenes": len(per_scene_f1)}


def test_bootstrap_of_a_constant_difference_is_that_value_and_seeded():
    assert bootstrap_ci(np.full(10, 0.25)) == (0.25, 0.25, 0.25)
    d = np.random.default_rng(1).normal(0.1, 0.2, 40)
    a, b, c = bootstrap_ci(d, resamples=2000, seed=3), bootstrap_ci(d, resamples=2000, seed=3), bootstrap_ci(d, 2000, 4)
    assert a == b and a != c
    assert a[1] < a[0] < a[2] and a[0] == pytest.approx(d.mean())
    # the interval's half width is about 1.96 standard errors
    assert (a[2] - a[1]) / 2 == pytest.approx(1.96 * d.std() / np.sqrt(len(d)), rel=0.15)


def test_paired_differences_are_per_scene_and_count_wins():
    base = np.array([0.2, 0.5, 0.4, 0.9])
    res = {"learned_coverage": _result(base), "learned_policy": _result(base + 0.125),
           "average_policy": _result(base + [0.1, -0.1, 0.0, 0.0])}
    out = paired_differences(res, ("learned_coverage", "learned_greedy"), {}, resamples=500)
    by = {p["key"]: p for p in out}
    assert set(by) == {"learned_policy", "average_policy"} and all(p["reference"] == "learned_coverage" for p in out)
    ours = by["learned_policy"]
    assert ours["diff"] == pytest.approx(0.125) and ours["ci_low"] == pytest.approx(0.125)
    assert ours["ci_high"] == pytest.approx(0.125)
    assert (ours["wins"], ours["ties"], ours["losses"], ours["scenes"], ours["seeds"], ours["episodes_per_scene"]) == \
        (4, 0, 0, 4, 2, 3)
    avg = by["average_policy"]
    assert (avg["wins"], avg["ties"], avg["losses"]) == (1, 2, 1) and avg["ci_low"] < 0 < avg["ci_high"]
    assert np.allclose(scene_af1(res["average_policy"]), base + [0.1, -0.1, 0.0, 0.0])


def test_hindsight_best_route_bounds_every_fixed_route_and_any_moving_policy():
    torch.manual_seed(0)
    cache, conf = synthetic_cache(4), ConfidenceNet(6).eval()
    af1 = route_af1(cache, LearnedFusion(conf), CONFIG, max_episodes=300)  # two scenes per batch: chunks agree with one batch
    assert af1.shape == (4, 4 ** 4) and np.array_equal(af1, route_af1(cache, LearnedFusion(conf), CONFIG))
    rb = route_bounds(cache, LearnedFusion(conf), CONFIG)
    assert np.array_equal(rb.best, af1.max(1)) and (rb.best[:, None] >= af1).all()
    assert rb.best_fixed == pytest.approx(af1.mean(0).max()) and rb.best_fixed <= rb.best.mean()
    # the coverage route, evaluated as Table II does, is one of the routes
    cov = evaluate_agent(cache, Agent(LearnedFusion(conf), CoverageRoute(CONFIG)), 1).f1[:, -1]
    assert np.allclose(cov, rb.coverage) and (rb.best >= cov - 1e-12).all()
    # random moves are routes too: no episode beats its scene's hindsight-best
    rows = np.repeat(np.arange(4), 8)
    ep = run_search(CachedViews(cache, rows, CONFIG, conf), Agent(LearnedFusion(conf), RandomPolicy()),
                    generator=torch.Generator().manual_seed(0))
    from uavsearch.search.metrics import map_f1
    assert (map_f1(ep.maps[:, -1].numpy(), ep.labels.numpy()) <= rb.best[rows] + 1e-12).all()
    # a FixedRoutes episode flies its route
    one = run_search(CachedViews(cache, [0], CONFIG), Agent(FUSIONS["average"](), FixedRoutes(all_routes(CONFIG)[[27]])))
    assert one.actions.tolist() == [all_routes(CONFIG)[27].tolist()]


def test_eval_search_leaves_out_rows_without_checkpoints_and_writes_the_comparisons(tmp_path, capsys):
    models = _models(tmp_path / "models")
    (models / "search_s2_size.pt").unlink()
    out = tmp_path / "eval"
    cache = _with_person_px(synthetic_cache(3))
    res = eval_search(EvalArgs(setting="2", out=str(out), models_dir=str(models), episodes=1, seeds=2,
                               bootstrap=200, progress=False), caches={2: cache})
    printed = capsys.readouterr().out
    notice = "'by grid size + policy' left out: "
    assert printed.count(notice) == 2  # printed once, and once under the table
    assert "size_policy" not in res["results"][2]
    md = (out / "table2.md").read_text()
    assert notice in md and "by grid size" not in md.replace(notice, "")
    keys = [r["key"] for r in csv.DictReader((out / "table2.csv").open())]
    assert "size_policy" not in keys and "learned_policy" in keys
    paired = list(csv.DictReader((out / "table2_paired.csv").open()))
    assert {p["reference"] for p in paired} == {"learned_coverage", "learned_greedy"}
    assert all(p["scenes"] == "3" and p["seeds"] == "2" for p in paired)
    bounds = list(csv.DictReader((out / "table2_bounds.csv").open()))[0]
    assert float(bounds["hindsight_best_af1"]) >= float(bounds["coverage_af1"]) >= 0
    assert float(bounds["hindsight_minus_coverage"]) == pytest.approx(
        float(bounds["hindsight_best_af1"]) - float(bounds["coverage_af1"]))
    hidden = hidden_shares(cache, CONFIG)
    assert float(bounds["hidden_start"]) == pytest.approx(hidden[0])
    for section in ("Paired with the fixed routes", "Difficulty and upper bounds", "gap closed"):
        assert section in md
    # without any trained checkpoint only the rows that need none are left, and no bound needs one
    res = eval_search(EvalArgs(setting="2", out=str(tmp_path / "none"), models_dir=str(tmp_path / "empty"),
                               episodes=1, seeds=1, bootstrap=50, progress=False), caches={2: synthetic_cache(2)})
    assert set(res["results"][2]) == {"single_view", "oracle_random"}
    assert "route bounds skipped" in (tmp_path / "none" / "table2.md").read_text()
    trained_rows = [r for r in ROWS if r[0] not in ("single_view", "oracle_random")]
    assert len(res["notices"]) == len(trained_rows) == 10  # every row with a checkpoint, the PPO (external) one too


def test_person_px_is_optional_in_the_cache_file(tmp_path):
    c = synthetic_cache(2)
    arrays = {"format": np.array(FORMAT), "perception_tag": np.array(c.perception_tag), "scene_seed": c.scene_seed,
              "occupied_cells": c.occupied_cells, "occupancy": c.occupancy.numpy().astype(np.int8),
              **{k: getattr(c, k).numpy() for k in ("log_probs", "cell_features", "global_feature", "cell_area_px",
                                                     "valid")}}
    (tmp_path / "old.npz").write_bytes(npz_bytes(arrays, compress=False))
    old = load_view_cache(tmp_path / "old.npz")
    assert old.person_px is None and old.subset([1]).person_px is None and hidden_shares(old) is None
    px = np.arange(2 * 25 * 100, dtype=np.int32).reshape(2, 25, 100) % 7
    (tmp_path / "new.npz").write_bytes(npz_bytes({**arrays, "person_px": px}, compress=False))
    new = load_view_cache(tmp_path / "new.npz")
    assert new.person_px.dtype == torch.int32 and np.array_equal(new.subset([1]).person_px.numpy(), px[[1]])


def _tiny_cache() -> ViewCache:
    """One scene, two views, four cells: cells 0-1 occupied; view 1 does not measure cell 3."""
    p = torch.tensor([[[0.9, 0.3, 0.6, 0.1], [0.8, 0.7, 0.6, 0.2]]])
    valid = torch.ones(1, 2, 4, dtype=torch.bool)
    valid[0, 1, 3] = False
    return ViewCache(scene_seed=np.zeros(1, np.int64), occupied_cells=np.array([2]),
                     occupancy=torch.tensor([[True, True, False, False]]),
                     log_probs=torch.stack([(1 - p).log(), p.log()], -1), cell_features=torch.zeros(1, 2, 4, 3),
                     global_feature=torch.zeros(1, 2, 5), cell_area_px=torch.full((1, 2, 4), 196.0), valid=valid,
                     perception_tag="tiny",
                     person_px=torch.tensor([[[5, 0, 0, 0], [20, 2, 0, 0]]], dtype=torch.int32))


def test_perception_targets_on_a_hand_computed_cache():
    st = perception_stats([_tiny_cache()])
    # valid (score, label) ranked: .9 1, .8 1, .7 1, .6 0, .6 0, .3 1, .1 0 -> AP = mean(1, 1, 1, 4/6)
    assert st["cell_ap"] == pytest.approx(0.75 + 0.25 * 4 / 6, abs=1e-6)
    assert st["fa_per_view"] == 1.0 and st["fa_hist"].tolist() == [0, 2]
    assert st["precision"] == pytest.approx(3 / 5) and st["recall"] == pytest.approx(3 / 4)
    assert st["persistent_fa_per_scene"] == 1.0  # cell 2 fires in both views that measure it; cell 3 in none
    by = st["recall_by_px"]
    assert by["0"] == (0.0, 1) and by["1-3"] == (1.0, 1) and by["4-7"] == (1.0, 1) and by["16+"] == (1.0, 1)
    assert np.isnan(by["8-15"][0]) and by["8-15"][1] == 0 and st["recall_4_7px"] == 1.0
    assert perception_stats([_tiny_cache()._replace(person_px=None)])["recall_by_px"] is None


def test_eval_perception_writes_the_report_and_fits_its_figure(tmp_path):
    caches = {1: _with_person_px(synthetic_cache(2, k=2), 1), 2: _with_person_px(synthetic_cache(2, k=5, seed=1), 2)}
    args = PerceptionArgs(out=str(tmp_path), setting="all", progress=False)
    with pytest.raises(UavsearchError, match="no view cache for setting 3"):
        eval_perception(args, caches)
    res = eval_perception(PerceptionArgs(out=str(tmp_path), setting="2", progress=False), caches)
    assert list(res["stats"]) == ["setting 2 (5 cells)"]
    res = eval_perception(PerceptionArgs(out=str(tmp_path), setting="all", progress=False),
                          {**caches, 3: _with_person_px(synthetic_cache(2, k=10, seed=2), 3)})
    md = (tmp_path / "perception_targets.md").read_text()
    for text in ("cell average precision | >= 0.75", "false alarms per view | <= 1", "recall at 4-7",
                 "persistent false-alarm cells per scene | <= 0.3", "| met |", "pooled column 'all'"):
        assert text in md
    rows = {r["key"]: r for r in csv.DictReader((tmp_path / "perception_targets.csv").open())}
    assert float(rows["cell_ap"]["all"]) == pytest.approx(res["stats"]["all"]["cell_ap"])
    assert rows["cell_ap"]["met"] in ("True", "False")
    assert (tmp_path / "perception_targets.png").stat().st_size > 10_000
    fig = targets_figure(res["stats"])
    try:
        assert overflow_in(fig) <= 0.01
    finally:
        pyplot().close(fig)
    parser = argparse.ArgumentParser()
    add_eval_perception_parser(parser.add_subparsers())
    ns = parser.parse_args(["perception", "--split", "large", "--part", "test", "--out", "d"])
    assert (ns.split, ns.part, ns.out, ns.setting) == ("large", "test", "d", "all")


def test_one_line_errors():
    with pytest.raises(UavsearchError, match="non-empty"):
        bootstrap_ci([])
    with pytest.raises(UavsearchError, match="confidence"):
        route_af1(synthetic_cache(1), None)
    with pytest.raises(UavsearchError, match="setting"):
        eval_perception(PerceptionArgs(out="x", setting="9", progress=False), {})


def test_label_greedy_bound_is_a_route_so_hindsight_best_bounds_it():
    torch.manual_seed(0)
    cache, conf = synthetic_cache(3), ConfidenceNet(6).eval()
    f1 = label_greedy_af1(cache, LearnedFusion(conf), CONFIG)
    assert f1.shape == (3,) and ((0 <= f1) & (f1 <= 1)).all()
    assert (f1 <= route_bounds(cache, LearnedFusion(conf), CONFIG).best + 1e-12).all()
