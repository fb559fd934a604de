"""The neighbour fusion: view by view equals the whole history, saves and loads to the same maps, a spec names it,
what it cannot do is a one-line error; `uavsearch train fusion` fits it, the map policy trains on it and the env
fuses with it (small synthetic views and synthetic wide caches)."""

import pytest
import torch

from uavsearch.errors import UavsearchError
from uavsearch.search.agents import make_fusion
from uavsearch.search.fusion import FUSIONS, CalibratedFusion, FusionViews
from uavsearch.search.neighbour_fusion import (CorrectionNet, NeighbourEnsemble, NeighbourFusion, load_neighbour,
                                               save_neighbour, view_planes)

B, T, N, P, n = 3, 4, 36, 10, 6


def views():
    g = torch.Generator().manual_seed(0)
    p = torch.rand(B, T, N, generator=g)
    valid = torch.rand(B, T, N, generator=g) < 0.7
    area = torch.rand(B, T, N, generator=g) * 400 + 20
    idx = torch.randint(P, (B, T), generator=g)
    return FusionViews(p, valid, area, viewpoints=idx)


def fusion(seed: int = 0, shift: float = 0.75, gamma: float = 0.25):
    torch.manual_seed(seed)
    lowest = torch.arange(P) >= 6
    return NeighbourFusion(CalibratedFusion((1.1, -0.05, -0.3, 0.02), 0.08, gamma), CorrectionNet(kernel=5).eval(),
                           shift, lowest, n)


def test_registered_and_view_by_view_equals_the_history():
    f, v = fusion(), views()
    assert FUSIONS["neighbour"] is NeighbourFusion
    whole = f.fuse(v)
    assert torch.allclose(f.prefixes(v)[:, -1], whole, atol=1e-6)
    # the probe's correction, written out: the net over the calibrated map's planes, shifted
    fused = f.base.fuse(v)
    planes = view_planes(fused, v.p, v.valid, v.area_px, v.viewpoints, f.base.coef, f.lowest, n)
    with torch.no_grad():
        want = torch.sigmoid(f.net(planes).flatten(1) + 0.75)
    assert torch.allclose(whole, want, atol=1e-6)


def test_save_load_round_trip_and_spec(tmp_path):
    f, v = fusion(), views()
    path = save_neighbour(f, tmp_path / "nf.pt", {"seed": 0})
    g = load_neighbour(path)
    assert torch.equal(g.fuse(v), f.fuse(v))
    assert torch.equal(make_fusion(f"neighbour:{path}").fuse(v), f.fuse(v))


def test_an_ensemble_averages_its_members_shifted_log_odds_and_round_trips(tmp_path):
    members, v = [fusion(0, 0.75), fusion(1, 1.0), fusion(2, 0.5)], views()
    paths = [save_neighbour(m, tmp_path / f"m{k}.pt") for k, m in enumerate(members)]
    ens = make_fusion("neighbour:" + ",".join(str(p) for p in paths))
    assert isinstance(ens, NeighbourEnsemble) and ens.spec.endswith("x 3")
    logit = torch.stack([torch.logit(m.fuse(v).double()) for m in members]).mean(0)
    whole = ens.fuse(v)
    assert torch.allclose(whole.double(), torch.sigmoid(logit), atol=1e-5)
    assert not torch.allclose(whole, members[0].fuse(v), atol=1e-3)  # the others count
    assert torch.allclose(ens.prefixes(v)[:, -1], whole, atol=1e-6)  # view by view, as the search runs it
    back = load_neighbour(save_neighbour(ens, tmp_path / "ens.pt"))  # one checkpoint holds the whole ensemble
    assert isinstance(back, NeighbourEnsemble) and torch.equal(back.fuse(v), whole)
    with pytest.raises(UavsearchError, match="share their base fusion"):
        NeighbourEnsemble.of([members[0], fusion(3, gamma=0.75)])


def test_a_shipped_stack_names_its_learned_aggregation(tmp_path, monkeypatch):
    """neighbour:PATH of a search policy's checkpoint is the learned aggregation it carries (the shipped stack's,
    an ensemble of feature fits); a relative path names the repository's file wherever the command runs."""
    monkeypatch.chdir(tmp_path)
    f = make_fusion("neighbour:models/search_wide_240s_map.pt")
    assert isinstance(f, NeighbourEnsemble) and "cell_features" in f.needs


def test_errors(tmp_path):
    with pytest.raises(UavsearchError, match="not found"):
        make_fusion(f"neighbour:{tmp_path / 'missing.pt'}")
    with pytest.raises(UavsearchError, match="neighbour:PATH"):
        make_fusion("neighbour")
    bad = tmp_path / "bad.pt"
    torch.save({"format": "other"}, bad)
    with pytest.raises(UavsearchError, match="not a neighbour fusion"):
        load_neighbour(bad)
    with pytest.raises(UavsearchError, match="nor a search policy carrying one"):
        load_neighbour("models/search_s1_bayes.pt")  # a policy checkpoint, its fusion no neighbour fusion
    v = views()
    with pytest.raises(UavsearchError, match="viewpoint"):
        fusion().fuse(v._replace(viewpoints=None))


def test_train_fusion_fits_logs_and_saves_a_fusion_a_spec_names_and_a_resumed_run_is_the_same_fit(tmp_path):
    """`uavsearch train fusion` on synthetic wide caches: the loss falls, validation is logged beside the rule on
    the base fusion, model.pt is a neighbour fusion `neighbour:PATH` loads (the rule flies with it), the same
    seed gives the same weights, and a run stopped after two epochs and resumed is the uninterrupted run."""
    import csv
    import json

    import numpy as np
    from test_wide_search import wide_cache
    from uavsearch.search.config import wide_budgets
    from uavsearch.search.metrics import map_f1
    from uavsearch.search.search_loop import Agent, CachedViews, run_search
    from uavsearch.search.train.fusion import Args, train, weights_sha
    from uavsearch.search.wide_policies import rule_policy

    caches = wide_cache(6, seed=1), wide_cache(3, seed=2)
    kw = dict(family="wide", budget="8", fusion="calibrated:0.25", calibration_scenes=4, rollouts=3, epochs=4,
              batch_size=4, hidden=8, eval_every=2, runs_dir=str(tmp_path), progress=False, seed=5)
    res = train(Args(**kw), caches=caches)
    rows = list(csv.DictReader((res.run_dir / "metrics.csv").open()))
    assert [int(r["epoch"]) for r in rows] == [1, 2, 3, 4]
    assert float(rows[-1]["losses/train"]) < float(rows[0]["losses/train"])
    assert [r["eval/val_af1"] != "" for r in rows] == [False, True, False, True]
    summary = json.loads((res.run_dir / "summary.json").read_text())
    scenes = summary["scenes"]
    assert (scenes["train"], scenes["val"]) == (6, 3) and 6 * 3 <= scenes["maps"] <= 6 * 3 * 3
    assert summary["validation"][1]["af1"] == pytest.approx(np.mean(summary["per_scene_f1"]["neighbour"]))
    assert float(rows[-1]["eval/val_af1"]) == pytest.approx(summary["validation"][1]["af1"])
    assert (res.run_dir / "learning_curve.png").stat().st_size > 0
    fusion = make_fusion(f"neighbour:{res.checkpoint}")
    assert isinstance(fusion, NeighbourFusion) and weights_sha(fusion.net) == summary["weights_sha256"]
    config = wide_budgets(caches[1].config)["T = 8 views"]
    ep = run_search(CachedViews(caches[1], np.arange(3), config), Agent(fusion, rule_policy(config, summary["rule"])))
    assert ep.maps.shape[1] == 8 and np.mean(map_f1(ep.maps[:, -1].numpy(), caches[1].occupancy.numpy())) \
        == pytest.approx(summary["validation"][1]["af1"])
    again = train(Args(**kw), caches=caches)
    assert json.loads((again.run_dir / "summary.json").read_text())["weights_sha256"] == summary["weights_sha256"]
    stopped = train(Args(**{**kw, "stop_after": 2}), caches=caches)
    assert stopped.table == [] and not (stopped.run_dir / "model.pt").exists()
    with pytest.raises(UavsearchError, match="started for 4 epochs"):
        train(Args(**{**kw, "epochs": 6, "resume": str(stopped.run_dir)}), caches=caches)
    resumed = train(Args(**{**kw, "resume": str(stopped.run_dir)}), caches=caches)
    assert resumed.run_dir == stopped.run_dir
    assert [int(r["epoch"]) for r in csv.DictReader((resumed.run_dir / "metrics.csv").open())] == [1, 2, 3, 4]
    assert json.loads((resumed.run_dir / "summary.json").read_text())["weights_sha256"] == summary["weights_sha256"]
    with pytest.raises(UavsearchError, match="no train_state.pt"):
        train(Args(**{**kw, "resume": str(tmp_path / "nowhere")}), caches=caches)
    with pytest.raises(UavsearchError, match="calibrated"):
        train(Args(**{**kw, "fusion": "average"}), caches=caches)


def test_the_map_policy_trains_on_a_fitted_neighbour_fusion_and_carries_it(tmp_path):
    """The learned policy is trained on the learned aggregation: the label teacher re-fuses every candidate view
    (route views with their viewpoints, the fusion's state repeated per candidate), and the policy's checkpoint
    carries the neighbour fusion, which gives the same maps as the file it was fitted into."""
    from test_wide_search import wide_cache
    from uavsearch.search.policy import load_search_model
    from uavsearch.search.train import fusion as fusion_train
    from uavsearch.search.train import map_policy

    caches = wide_cache(6, seed=1), wide_cache(3, seed=2)
    fitted = fusion_train.train(fusion_train.Args(family="wide", budget="8", fusion="calibrated:0.25",
                                                  calibration_scenes=4, rollouts=2, epochs=1, batch_size=4, hidden=8,
                                                  runs_dir=str(tmp_path), progress=False, plot=False, seed=5),
                                caches=caches)
    spec = f"neighbour:{fitted.checkpoint}"
    res = map_policy.train(map_policy.Args(family="wide", budget="8", fusion=spec, teacher="labels",
                                           calibration_scenes=4, train_eval_scenes=2, dagger_iterations=1,
                                           dagger_episodes=6, dagger_epochs=1, batch_size=16, pg_iterations=1,
                                           scenes_per_batch=2, episodes_per_scene=2, eval_every=1, channels=8,
                                           conv_layers=2, hidden=16, runs_dir=str(tmp_path), progress=False,
                                           plot=False, seed=0), caches=caches)
    carried, net, _ = load_search_model(res.checkpoint)
    assert isinstance(carried, NeighbourFusion) and net.KIND == "map"
    v = views()._replace(viewpoints=torch.randint(72, (B, T), generator=torch.Generator().manual_seed(1)))
    v = v._replace(p=torch.rand(B, T, 900), valid=torch.ones(B, T, 900, dtype=torch.bool),
                   area_px=torch.full((B, T, 900), 200.0))
    assert torch.allclose(carried.fuse(v), make_fusion(spec).fuse(v), atol=2e-3)  # the checkpoint keeps half floats


def test_numpy_views_fuse_as_tensors_do_and_the_env_flies_the_rule_on_it(tmp_path):
    """The envs' buffered episodes keep each view's viewpoint, so WideSearch-v0 fuses with a neighbour fusion:
    the rule played through the env flies the evaluation's routes and scores its AF1."""
    import numpy as np

    from uavsearch.search.config import setting_config
    from uavsearch.search.envs.search_env import LoopPolicyPlayer, WideSearchEnv, play_scenes
    from uavsearch.search.scoring import score_episode
    from uavsearch.search.search_loop import Agent, CachedViews, run_search
    from uavsearch.search.wide_policies import rule_policy
    from uavsearch.testing.synthetic_views import synthetic_cache

    f, v = fusion(), views()
    host = FusionViews(v.p.double().numpy(), v.valid.numpy(), v.area_px.double().numpy(),
                       viewpoints=v.viewpoints.numpy())
    np.testing.assert_allclose(f.fuse_host(host), f.fuse(v).numpy(), atol=1e-5)

    cache = synthetic_cache(4, k=10, seed=2, config=setting_config("wide"))
    torch.manual_seed(1)
    env = WideSearchEnv(cache=cache, budget="8", progress=False)
    wide = NeighbourFusion.around(CalibratedFusion((1.1, -0.05, -0.3, 0.02), 0.08, 0.25), CorrectionNet(kernel=5),
                                  0.5, env.config)
    path = save_neighbour(wide, tmp_path / "n.pt")
    env = WideSearchEnv(cache=cache, budget="8", fusion=f"neighbour:{path}", progress=False)
    assert isinstance(env.fusion, NeighbourFusion)
    rule = rule_policy(env.config, "4 covering, resurvey below p 0.4")
    f1, routes = play_scenes(env, LoopPolicyPlayer(rule, env.config).act, cache.scene_seed)
    with torch.no_grad():
        ep = run_search(CachedViews(cache, np.arange(cache.num_scenes), env.config), Agent(env.fusion, rule))
    assert [ep.lattice_idx[i, :len(r)].tolist() for i, r in enumerate(routes)] == routes
    np.testing.assert_allclose(f1, score_episode(ep).f1[:, -1], atol=1e-6)


D = 5


def feature_fusion(seed: int = 0, shift: float = 0.5):
    from uavsearch.search.neighbour_fusion import FeatureCorrectionNet

    torch.manual_seed(seed)
    return NeighbourFusion(CalibratedFusion((1.1, -0.05, -0.3, 0.02), 0.08, 0.25),
                           FeatureCorrectionNet(2 * D, kernel=3, reduce=4, hidden=8).eval(), shift,
                           torch.arange(P) >= 6, n)


def feature_views():
    f = torch.randn(B, T, N, D, generator=torch.Generator().manual_seed(3))
    return views()._replace(cell_features=f)


def test_a_fusion_reading_cell_features_is_the_layer_means_written_out_view_by_view_and_round_trips(tmp_path):
    """The features' planes are, per altitude layer, the mean of the features of the views that measured the
    cell (zero where none did); the running sums give the whole history's map; the checkpoint rebuilds it; a
    source without features, or an ensemble mixing inputs, is a one-line error."""
    f, v = feature_fusion(), feature_views()
    assert "cell_features" in f.needs and "cell_features" not in NeighbourFusion.needs and f.spec.startswith(
        "neighbour+features")
    whole = f.fuse(v)
    low = f.lowest[v.viewpoints]  # (B, T)
    means = []
    for layer in (low, ~low):
        m = (v.valid & layer[..., None]).float()[..., None]  # (B, T, N, 1)
        means.append((v.cell_features * m).sum(1) / m.sum(1).clamp(min=1))  # (B, N, D)
    feats = torch.cat(means, -1).permute(0, 2, 1).reshape(B, 2 * D, n, n)
    planes = view_planes(f.base.fuse(v), v.p, v.valid, v.area_px, v.viewpoints, f.base.coef, f.lowest, n)
    with torch.no_grad():
        want = torch.sigmoid(f.net(torch.cat([planes, feats], 1)).flatten(1) + 0.5)
    assert torch.allclose(whole, want, atol=1e-6)
    assert torch.allclose(f.prefixes(v)[:, -1], whole, atol=1e-6)
    moved = v._replace(cell_features=v.cell_features + 1.0)  # the features count
    assert not torch.allclose(f.fuse(moved), whole, atol=1e-3)
    rows = torch.arange(B * T).view(B, T)  # a cache batch's (U, N, D) features indexed per view
    assert torch.allclose(f.fuse(v._replace(cell_features=v.cell_features.reshape(B * T, N, D), feature_rows=rows)),
                          whole, atol=1e-6)
    back = make_fusion(f"neighbour:{save_neighbour(f, tmp_path / 'f.pt')}")
    assert back.reads_features and torch.equal(back.fuse(v), whole)
    ens = NeighbourEnsemble.of([f, feature_fusion(1, 1.0)])
    assert ens.reads_features and torch.allclose(ens.prefixes(v)[:, -1], ens.fuse(v), atol=1e-6)
    with pytest.raises(UavsearchError, match="all with cell features or all without"):
        NeighbourEnsemble.of([f, fusion()])
    with pytest.raises(UavsearchError, match="cell features"):
        f.fuse(v._replace(cell_features=None))
    with pytest.raises(UavsearchError, match="cell features"):
        f.fuse(v._replace(cell_features=v.cell_features[..., :0]))
    assert f.cell_dim == D and fusion().cell_dim is None
    with pytest.raises(UavsearchError, match=f"reads {D} cell features per view .* gives 3"):
        f.fuse(v._replace(cell_features=v.cell_features[..., :3]))


def test_train_fusion_with_features_fits_a_fusion_the_rule_flies_with(tmp_path):
    """`uavsearch train fusion --features` on synthetic wide caches (their features in memory): the checkpoint
    reads the cell features, and the rule flying with it over the cache (which then serves the features) scores
    the summary's validation AF1; the same seed gives the same weights."""
    import json

    import numpy as np
    from test_wide_search import wide_cache
    from uavsearch.search.config import wide_budgets
    from uavsearch.search.metrics import map_f1
    from uavsearch.search.search_loop import Agent, CachedViews, run_search
    from uavsearch.search.train.fusion import Args, train
    from uavsearch.search.wide_policies import rule_policy

    caches = wide_cache(6, seed=1), wide_cache(3, seed=2)
    kw = dict(family="wide", budget="8", fusion="calibrated:0.25", calibration_scenes=4, rollouts=2, epochs=2,
              batch_size=4, hidden=8, reduce=3, features=True, eval_every=1, runs_dir=str(tmp_path), progress=False,
              plot=False, seed=5)
    res = train(Args(**kw), caches=caches)
    summary = json.loads((res.run_dir / "summary.json").read_text())
    fusion = make_fusion(f"neighbour:{res.checkpoint}")
    assert fusion.reads_features and fusion.net.features == 2 * caches[0].cell_features.shape[-1]
    assert "cell features" in summary["validation"][1]["method"]
    config = wide_budgets(caches[1].config)["T = 8 views"]
    source = CachedViews(caches[1], np.arange(3), config)
    ep = run_search(source, Agent(fusion, rule_policy(config, summary["rule"])))
    assert source.features  # the fusion had the cache serve them
    assert np.mean(map_f1(ep.maps[:, -1].numpy(), caches[1].occupancy.numpy())) == pytest.approx(
        summary["validation"][1]["af1"])
    again = json.loads((train(Args(**kw), caches=caches).run_dir / "summary.json").read_text())
    assert again["weights_sha256"] == summary["weights_sha256"]


def test_replay_refuses_a_flight_with_its_neighbour_fusion_and_replays_a_feature_fusions_own_maps():
    """Replay re-fuses a log's views with the checkpoint's neighbour fusion (the log keeps each view's viewpoint);
    a fusion reading cell features, which no log holds, replays the maps the flight fused, and naming one for
    a re-fusion is a one-line error."""
    import numpy as np

    from uavsearch.errors import LogError
    from uavsearch.replay.replay import _fuse_all

    f, v = fusion(), views()
    got = _fuse_all(f, v.p[0].numpy(), v.valid[0].numpy(), v.area_px[0].numpy(), viewpoints=v.viewpoints[0].tolist())
    np.testing.assert_allclose(got, f.prefixes(v)[0].numpy(), atol=1e-6)
    with pytest.raises(LogError, match="viewpoint"):
        _fuse_all(f, v.p[0].numpy(), v.valid[0].numpy(), v.area_px[0].numpy())
    logged = np.random.default_rng(0).random((T, N))
    ff = feature_fusion()
    assert np.array_equal(_fuse_all(ff, v.p[0].numpy(), v.valid[0].numpy(), v.area_px[0].numpy(),
                                    viewpoints=v.viewpoints[0].tolist(), logged=logged), logged)
    with pytest.raises(LogError, match="cell features"):
        _fuse_all(ff, v.p[0].numpy(), v.valid[0].numpy(), v.area_px[0].numpy(), viewpoints=v.viewpoints[0].tolist())


def test_a_map_policy_fine_tunes_from_a_checkpoint_on_a_fusion_reading_features(tmp_path):
    """`uavsearch train map --init CKPT --fusion neighbour:FEATURES.pt`: the start is validated before any step
    (iteration 0), the label teacher re-fuses candidates with their cell features, and the checkpoint carries
    the feature fusion; a net made for another budget is a one-line error."""
    import csv

    from test_wide_search import wide_cache
    from uavsearch.search.policy import load_search_model
    from uavsearch.search.train import fusion as fusion_train
    from uavsearch.search.train import map_policy

    caches = wide_cache(6, seed=1), wide_cache(3, seed=2)
    fitted = fusion_train.train(fusion_train.Args(family="wide", budget="8", fusion="calibrated:0.25",
                                                  calibration_scenes=4, rollouts=2, epochs=1, batch_size=4, hidden=8,
                                                  reduce=3, features=True, runs_dir=str(tmp_path), progress=False,
                                                  plot=False, seed=5), caches=caches)
    kw = dict(family="wide", budget="8", calibration_scenes=4, train_eval_scenes=2, dagger_episodes=6,
              dagger_epochs=1, batch_size=16, scenes_per_batch=2, episodes_per_scene=2, eval_every=1, channels=8,
              conv_layers=2, hidden=16, runs_dir=str(tmp_path), progress=False, plot=False, seed=0)
    start = map_policy.train(map_policy.Args(fusion="calibrated:0.25", dagger_iterations=1, pg_iterations=0, **kw),
                             caches=caches)
    spec = f"neighbour:{fitted.checkpoint}"
    res = map_policy.train(map_policy.Args(fusion=spec, teacher="labels", init=str(start.checkpoint),
                                           dagger_iterations=0, pg_iterations=2, **kw), caches=caches)
    rows = list(csv.DictReader((res.run_dir / "metrics.csv").open()))
    assert [r["phase"] for r in rows] == ["init", "pg", "pg"] and rows[0]["eval/val_af1"] != ""
    carried, net, extra = load_search_model(res.checkpoint)
    assert isinstance(carried, NeighbourFusion) and carried.reads_features
    if extra["best"]["iteration"] == 0:  # no step beat the start: its weights, now carrying the feature fusion
        first = load_search_model(start.checkpoint)[1]
        assert all(torch.equal(a, b) for a, b in zip(net.state_dict().values(), first.state_dict().values()))
    other = map_policy.train(map_policy.Args(fusion="calibrated:0.25", dagger_iterations=1, pg_iterations=0,
                                             **{**kw, "budget": "240"}), caches=caches)
    with pytest.raises(UavsearchError, match="another search"):
        map_policy.train(map_policy.Args(fusion=spec, init=str(other.checkpoint), dagger_iterations=0,
                                         pg_iterations=1, **kw), caches=caches)


def test_the_envs_fly_a_fusion_reading_cell_features_as_the_loop_does(tmp_path):
    """WideSearch-v0 takes a learned aggregation that reads cell features: the buffered episodes keep its running
    feature sums, and the rule played through the env flies the loop's routes with the loop's AF1, also across
    resets (the sums start afresh); a fusion reading features without a running sum, or a cache without
    features, is a one-line error. (The team env: tests/test_team_env.py.)"""
    import numpy as np

    from uavsearch.search.envs.search_env import LoopPolicyPlayer, WideSearchEnv, check_buffered_fusion, play_scenes
    from uavsearch.search.fusion import Fusion
    from uavsearch.search.neighbour_fusion import FeatureCorrectionNet
    from uavsearch.search.scoring import score_episode
    from uavsearch.search.search_loop import Agent, CachedViews, run_search
    from uavsearch.search.wide_policies import rule_policy
    from uavsearch.testing.synthetic_views import synthetic_wide_cache

    cache = synthetic_wide_cache(3, seed=2, cell_dim=D)
    env = WideSearchEnv(cache=cache, budget="8", progress=False)
    torch.manual_seed(0)
    wide = NeighbourFusion.around(CalibratedFusion((1.1, -0.05, -0.3, 0.02), 0.08, 0.25),
                                  FeatureCorrectionNet(2 * D, kernel=3, reduce=4, hidden=8).eval(), 0.5, env.config)
    path = save_neighbour(wide, tmp_path / "f.pt")
    env = WideSearchEnv(cache=cache, budget="8", fusion=f"neighbour:{path}", progress=False)
    assert env.fusion.reads_features
    rule = rule_policy(env.config, "4 covering, resurvey below p 0.4")
    seeds = [*cache.scene_seed, *cache.scene_seed[::-1]]  # the second pass: each episode's sums start at zero
    f1, routes = play_scenes(env, LoopPolicyPlayer(rule, env.config).act, seeds)
    with torch.no_grad():
        ep = run_search(CachedViews(cache, np.arange(cache.num_scenes), env.config), Agent(env.fusion, rule))
    want = score_episode(ep).f1[:, -1]
    assert [ep.lattice_idx[i, :len(r)].tolist() for i, r in enumerate(routes[:3])] == routes[:3]
    np.testing.assert_allclose(f1[:3], want, atol=1e-5)
    np.testing.assert_allclose(f1[3:], want[::-1], atol=1e-5)

    class FeaturesNoSum(Fusion):
        name, needs = "features-no-sum", ("cell_features",)

    with pytest.raises(UavsearchError, match="buffered episodes do not keep"):
        check_buffered_fusion(FeaturesNoSum())
    bare = cache._replace(cell_features=cache.cell_features[..., :0])  # a cache that kept no features
    env = WideSearchEnv(cache=bare, budget="8", fusion=f"neighbour:{path}", progress=False)
    with pytest.raises(UavsearchError, match="cell features"):
        env.reset(seed=0)
