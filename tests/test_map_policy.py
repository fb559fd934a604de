"""The wide-area search's learned policy: its map state and masks, the label-peeking teacher, the leave-one-out
baseline, a checkpoint's round trip, and a short DAgger + REINFORCE run end to end on a synthetic wide cache."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import torch

from test_wide_search import WIDE, wide_cache
from uavsearch.errors import UavsearchError
from uavsearch.search.config import config_to_dict, wide_budgets
from uavsearch.search.agents import make_fusion
from uavsearch.search.fusion import FUSIONS, FusionViews
from uavsearch.search.map_policy import MAP_PLANES, VIEWPOINT_FEATURES, MapPolicyConfig, MapPolicyNet, wide_checkpoint
from uavsearch.search.policy import ArgmaxPolicy, load_search_model, save_search_model
from uavsearch.search.search_loop import Agent, CachedViews, classification_reward, run_search
from uavsearch.search.train.map_policy import Args, LabelLookahead, leave_one_out, train
from uavsearch.search.wide_policies import footprints

TIMED = wide_budgets(WIDE)["240 s"]


def _net(config=TIMED, **kw) -> MapPolicyNet:
    torch.manual_seed(0)
    return MapPolicyNet(MapPolicyConfig(config_to_dict(config), **kw))


class Record:
    """Wraps a policy and keeps the inputs it was asked about."""

    def __init__(self, policy):
        self.policy, self.inputs = policy, []

    def act(self, inp, generator=None):
        self.inputs.append(inp)
        return self.policy.act(inp, generator)


def test_the_map_policy_reads_the_map_and_masks_what_it_may_not_take():
    cache = wide_cache(3)
    net = _net()
    rec = Record(net)
    ep = run_search(CachedViews(cache, np.arange(3), TIMED), Agent(FUSIONS["average"](), rec),
                    generator=torch.Generator().manual_seed(0))
    assert ep.log_prob is not None and ep.log_prob.requires_grad and ep.flight_s.max() <= 240.0
    inp = rec.inputs[3]
    planes, vp = net.state(inp)
    assert planes.shape == (3, len(MAP_PLANES), 30, 30) and vp.shape == (3, len(VIEWPOINT_FEATURES), 73)
    here = planes[:, MAP_PLANES.index("here")].flatten(1)
    assert torch.equal(here.bool(), footprints(TIMED)[inp.lattice_idx])
    secs = planes[:, MAP_PLANES.index("seconds_left"), 0, 0]
    assert torch.allclose(secs, inp.time_left_s / 240.0)
    logits = net.logits(inp)
    assert (logits[inp.visited] <= -1e8).all() and (logits[inp.allowed] > -1e8).all()
    # a view-budget net has a constant seconds plane and counts views left
    untimed = wide_budgets(WIDE)["T = 8 views"]
    net8 = _net(untimed)
    rec8 = Record(net8)
    run_search(CachedViews(cache, np.arange(3), untimed), Agent(FUSIONS["average"](), rec8))
    p8, _ = net8.state(rec8.inputs[2])
    assert (p8[:, MAP_PLANES.index("seconds_left")] == 1).all()
    assert p8[0, MAP_PLANES.index("views_left"), 0, 0].item() == pytest.approx(1 - 3 / 8)
    with pytest.raises(UavsearchError, match="move_set"):
        _net(config=wide_budgets(WIDE)["T = 8 views"].__class__())  # the paper's steps config


def test_a_map_policy_checkpoint_round_trips_with_its_calibrated_fusion(tmp_path):
    cache = wide_cache(3)
    fusion = make_fusion("calibrated:0.5", cache)
    net = _net()
    path = save_search_model(tmp_path / "m.pt", fusion, net, {"search_config": config_to_dict(TIMED)})
    fusion2, net2, extra = load_search_model(path)
    assert net2.KIND == "map" and fusion2.spec == "calibrated:0.5" and fusion2.coef == pytest.approx(fusion.coef)
    a = run_search(CachedViews(cache, np.arange(3), TIMED), Agent(fusion, ArgmaxPolicy(net.eval())))
    b = run_search(CachedViews(cache, np.arange(3), TIMED), Agent(fusion2, ArgmaxPolicy(net2)))
    assert torch.equal(a.lattice_idx, b.lattice_idx)  # weights stored at half precision, same choices here
    assert wide_checkpoint("8").name == "search_wide_T8_map.pt" and wide_checkpoint("240").name == "search_wide_240s_map.pt"


def test_the_teacher_takes_the_view_that_finds_people_per_second():
    cache = wide_cache(2, k=3)
    fusion = FUSIONS["average"]()
    teacher = LabelLookahead(cache, torch.arange(2), fusion, TIMED)
    rec = Record(teacher)
    ep = run_search(CachedViews(cache, np.arange(2), TIMED), Agent(fusion, rec))
    inp = rec.inputs[0]
    g = LabelLookahead(cache, torch.arange(2), fusion, TIMED).gains(inp)
    assert torch.isinf(g[inp.visited]).all() and torch.isfinite(g[inp.allowed]).all()
    # its first choice is the best gain per second: the change of N_tp - N_fp (+ a tenth of the occupied cells'
    # summed p) of the map fused from the start view and that view, over the flight time to it
    a = ep.lattice_idx[:, 1]
    assert torch.equal(a, g.argmax(1)) and (g.amax(1) > 0).all()

    def score(views):
        fused = fusion.fuse(FusionViews(cache.log_probs[0, views, :, 1].exp()[None], cache.valid[0, views][None]))
        y = cache.occupancy[:1]
        return float(classification_reward(fused, y) + 0.1 * (fused * y).sum(-1))

    start, first = TIMED.lattice.start_index, int(a[0])
    expect = (score([start, first]) - score([start])) / float(TIMED.lattice.flight_time_s[start, first])
    assert float(g[0, first]) == pytest.approx(expect, rel=1e-5)
    # the teacher's maps end better than the untrained net's
    net_ep = run_search(CachedViews(cache, np.arange(2), TIMED), Agent(fusion, ArgmaxPolicy(_net().eval())))
    from uavsearch.search.scoring import score_episode
    assert score_episode(ep).f1[:, -1].mean() > score_episode(net_ep).f1[:, -1].mean()
    with pytest.raises(UavsearchError, match="forward"):
        teacher.gains(rec.inputs[0])  # it follows one batch forward only


def test_leave_one_out_baseline_subtracts_the_other_episodes_of_the_scene():
    G = torch.tensor([[1.0, 0.0], [3.0, 2.0], [5.0, 5.0], [7.0, 9.0]])  # 2 scenes x 2 episodes
    assert torch.equal(leave_one_out(G, 2), torch.tensor([[-2.0, -2.0], [2.0, 2.0], [-2.0, -4.0], [2.0, 4.0]]))
    three = torch.tensor([[0.0], [3.0], [6.0]])
    assert torch.allclose(leave_one_out(three, 3), torch.tensor([[-4.5], [0.0], [4.5]]))


def test_training_imitates_the_teacher_then_reinforces_and_keeps_the_best_on_validation(tmp_path):
    train_c, val_c = wide_cache(6, seed=1), wide_cache(3, seed=2)
    args = Args(family="wide", budget="240", fusion="calibrated:0.5", teacher="labels", calibration_scenes=4, train_eval_scenes=3,
                dagger_iterations=3, dagger_episodes=12, dagger_epochs=4, batch_size=64, pg_iterations=2,
                scenes_per_batch=2, episodes_per_scene=2, eval_every=1, channels=8, conv_layers=2, hidden=16,
                runs_dir=str(tmp_path), progress=False, plot=True, seed=3)
    res = train(args, caches=(train_c, val_c))
    rows = list(csv.DictReader((res.run_dir / "metrics.csv").open()))
    assert [r["phase"] for r in rows] == ["dagger"] * 3 + ["pg"] * 2
    dagger = rows[:3]
    assert int(dagger[2]["charts/aggregate"]) > int(dagger[0]["charts/aggregate"]) > 0
    assert float(dagger[2]["losses/imitation"]) < float(dagger[0]["losses/imitation"]) - 0.3  # it learns the teacher
    for r in rows:  # validation and training margins after every DAgger and REINFORCE iteration
        assert r["eval/val_vs_rule"] != "" and r["eval/train_vs_rule"] != ""
    summary = json.loads((res.run_dir / "summary.json").read_text())
    best = max(float(r["eval/val_vs_rule"]) for r in rows)
    assert summary["best"]["val_vs_rule"] == pytest.approx(best)
    assert (res.run_dir / "learning_curve.png").stat().st_size > 0
    fusion, net, extra = load_search_model(res.checkpoint)
    assert net.KIND == "map" and extra["best"]["iteration"] == summary["best"]["iteration"]
    assert fusion.spec == "calibrated:0.5" and extra["rule"] in {t["method"][10:-1] for t in summary["validation"][:1]}
    # the same seed gives the same run
    again = train(args, caches=(train_c, val_c))
    assert json.loads((again.run_dir / "summary.json").read_text())["best"] == summary["best"]


def test_bad_training_arguments_are_one_line_errors():
    with pytest.raises(UavsearchError, match="episodes-per-scene"):
        train(Args(episodes_per_scene=1), caches=(wide_cache(2), wide_cache(2)))
    with pytest.raises(UavsearchError, match="wide family"):
        from uavsearch.testing.synthetic_views import synthetic_cache
        train(Args(progress=False, plot=False), caches=(synthetic_cache(2), synthetic_cache(2)))


def test_the_rule_can_be_the_teacher(tmp_path):
    args = Args(family="wide", budget="8", fusion="average", teacher="rule", calibration_scenes=2,
                train_eval_scenes=2, dagger_iterations=3, dagger_episodes=16, dagger_epochs=6, batch_size=32,
                pg_iterations=0, channels=8, conv_layers=2, hidden=16, runs_dir=str(tmp_path), progress=False,
                plot=False, seed=0)
    res = train(args, caches=(wide_cache(4, seed=5), wide_cache(2, seed=6)))
    rows = list(csv.DictReader((res.run_dir / "metrics.csv").open()))
    assert [r["phase"] for r in rows] == ["dagger"] * 3 and rows[-1]["eval/val_vs_rule"] != ""
    assert float(rows[-1]["losses/imitation"]) < float(rows[0]["losses/imitation"])
    with pytest.raises(UavsearchError, match="teacher"):
        train(Args(teacher="oracle"), caches=(wide_cache(2), wide_cache(2)))


def test_route_measures_count_views_near_found_groups_and_empty_40m_views():
    """tools/wide_routes.py's measures on a hand-made route: a group found at view 1, a 40 m look above it that
    adds nothing (near, empty), then a far 40 m look (not near, empty)."""
    from uavsearch.research.wide_routes import route_stats

    pos = TIMED.lattice.positions_enu
    top, low = pos[:, 2] == pos[:, 2].max(), pos[:, 2] == pos[:, 2].min()
    a = int(np.flatnonzero(top)[0])
    below = int(np.flatnonzero(low & (np.abs(pos[:, :2] - pos[a, :2]).sum(1) < 1e-6))[0])
    far = int(np.flatnonzero(low)[np.argmax(np.hypot(*(pos[low][:, :2] - pos[a, :2]).T))])
    n = TIMED.grid.num_cells
    cell = 17
    labels = np.zeros(n, bool)
    labels[cell] = True
    maps = np.zeros((4, n))
    maps[1:, cell] = 0.9  # found by view 1 and kept
    idx = np.array([TIMED.lattice.start_index, a, below, far])
    r = route_stats(TIMED, idx, maps, labels, np.array([pos[a, :2]]), [np.array([cell])])
    assert r["views"] == 4 and r["low"] == 2
    assert r["near_found"] == pytest.approx(1 / 3)  # view 1: nothing found yet; view 2: above the group; view 3: far
    assert r["empty_low"] == 1.0 and r["f1"] == 1.0
    t = TIMED.lattice.flight_time_s
    assert r["flight_s"] == pytest.approx(t[idx[0], a] + t[a, below] + t[below, far])


def test_imitating_gains_fits_the_label_teachers_gain_of_every_viewpoint(tmp_path):
    train_c, val_c = wide_cache(6, seed=1), wide_cache(3, seed=2)
    args = Args(family="wide", budget="8", fusion="average", teacher="labels", imitate="gains", calibration_scenes=4,
                train_eval_scenes=3, dagger_iterations=3, dagger_episodes=12, dagger_epochs=6, batch_size=64,
                pg_iterations=1, scenes_per_batch=2, episodes_per_scene=2, eval_every=1, channels=8, conv_layers=2,
                hidden=16, runs_dir=str(tmp_path), progress=False, plot=False, seed=3)
    res = train(args, caches=(train_c, val_c))
    rows = list(csv.DictReader((res.run_dir / "metrics.csv").open()))
    assert float(rows[2]["losses/imitation"]) < float(rows[0]["losses/imitation"])  # least squares on the gains
    fusion, net, extra = load_search_model(res.checkpoint)
    scale = extra["gain_scale"]
    assert scale > 0
    # the net's scores track the teacher's gains on states of a fresh rollout (scenes it was not fitted on)
    untimed = wide_budgets(WIDE)["T = 8 views"]
    teacher = LabelLookahead(val_c, torch.arange(3), fusion, untimed)
    rec = Record(teacher)
    run_search(CachedViews(val_c, np.arange(3), untimed), Agent(fusion, rec))
    g = LabelLookahead(val_c, torch.arange(3), fusion, untimed).gains(rec.inputs[0])
    s = net.logits(rec.inputs[0])
    ok = torch.isfinite(g)
    assert np.corrcoef(s[ok].detach().numpy(), g[ok].numpy())[0, 1] > 0.5
    with pytest.raises(UavsearchError, match="--teacher labels"):
        train(Args(imitate="gains", teacher="rule"), caches=(train_c, val_c))


def test_fusion_probe_planes_hold_each_cells_views_per_altitude():
    """tools/wide_fusion_probe.py's per-cell planes, checked against the views of a route flown on a synthetic
    wide cache: the fused log-odds, and per altitude layer the count and the highest, mean and lowest calibrated
    log-odds of the cell's views; its symmetries of the square are the eight distinct ones."""
    from uavsearch.research.wide_fusion_probe import cell_planes
    from uavsearch.search.symmetry import square_symmetry as dihedral
    from uavsearch.search.fusion import calibrated_logit
    from uavsearch.search.wide_policies import RoutePolicy

    cache = wide_cache(2, k=3)
    fusion = make_fusion("calibrated:0.25", cache)
    config = wide_budgets(WIDE)["T = 8 views"]
    pos = config.lattice.positions_enu
    low = np.flatnonzero(pos[:, 2] == pos[:, 2].min())
    route = [config.lattice.start_index, 0, int(low[0]), 1]
    ep = run_search(CachedViews(cache, np.arange(2), config), Agent(fusion, RoutePolicy(route[1:])), budget_T=4)
    assert ep.lattice_idx[0].tolist() == route
    x = cell_planes(cache, np.arange(2), ep, fusion, config)
    assert x.shape == (2, 11, 30, 30)
    flat = x.view(2, 11, -1)
    assert torch.allclose(flat[:, 0], torch.logit(ep.maps[:, -1].float().clamp(1e-5, 1 - 1e-5)))
    for scene in range(2):
        for layer, views in ((0, [int(low[0])]), (1, [config.lattice.start_index, 0, 1])):
            v = cache.valid[scene, views]
            c = calibrated_logit(cache.log_probs[scene, views, :, 1].exp().float(),
                                 cache.cell_area_px[scene, views].float(), fusion.coef)
            n = v.sum(0)
            seen = n > 0
            planes = flat[scene, 1 + 5 * layer: 6 + 5 * layer]
            assert torch.equal(planes[0], n.clamp(max=4).float() / 4)
            c_max = torch.where(v, c, torch.full_like(c, -20.0)).amax(0).clamp(min=-8)
            assert torch.allclose(planes[1][seen], c_max[seen]) and (planes[1][~seen] == 0).all()
            mean = (c * v).sum(0) / n.clamp(min=1)
            assert torch.allclose(planes[2][seen], mean[seen], atol=1e-5)
    m = torch.arange(16.0).view(4, 4)
    images = [dihedral(m, k) for k in range(8)]
    assert len({tuple(i.flatten().tolist()) for i in images}) == 8
    assert torch.equal(dihedral(dihedral(m, 1), 3), m) and torch.equal(dihedral(dihedral(m, 4), 4), m)


def test_fusion_seeds_study_refuses_a_missing_start_policy_before_fitting(tmp_path, capsys):
    """tools/wide_fusion_seeds.py checks --start before its fits (each minutes to an hour): one line, exit 2,
    no run folder made and no report written."""
    from uavsearch.research.wide_fusion_seeds import main
    from uavsearch.errors import run_command

    out = tmp_path / "report.md"
    argv = ["--budget", "240", "--start", str(tmp_path / "missing.pt"), "--runs-dir", str(tmp_path / "runs"),
            "--out", str(out)]
    assert run_command(main, argv, "wide_fusion_seeds.py") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"wide_fusion_seeds.py: error: --start {tmp_path / 'missing.pt'}: no such file"]
    assert not out.exists() and not (tmp_path / "runs").exists()
