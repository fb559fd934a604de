"""The feature store: per-view cell features in memory-mapped float16 files, one per scene, that a view
cache serves view by view instead of holding them."""

import dataclasses
import json
import pickle

import numpy as np
import pytest
import torch

from uavsearch.errors import UavsearchError
from uavsearch.parallel import npz_bytes
from uavsearch.search.config import config_to_dict, setting_config
from uavsearch.search.data.feature_store import FeatureStore
from uavsearch.search.data.view_cache import FORMAT, load_view_cache
from uavsearch.search.fusion import FUSIONS, LearnedFusion
from uavsearch.search.perception import ConfidenceNet
from uavsearch.search.policy import RandomPolicy
from uavsearch.search.search_loop import Agent, CachedViews, run_search
from uavsearch.testing.synthetic_views import synthetic_cache

WIDE = setting_config("wide")
OUTPUTS = ("log_probs", "global_feature", "cell_area_px", "valid")


def _outputs(cache, row):
    return {k: getattr(cache, k)[row].numpy() for k in OUTPUTS}


def _write_cache(tmp_path, cache, stored: bool):
    """The cache as build_view_cache writes it: its features in the .npz, or in a feature store beside it."""
    arrays = {"format": np.array(FORMAT), "perception_tag": np.array(cache.perception_tag),
              "scene_seed": cache.scene_seed, "occupied_cells": cache.occupied_cells,
              "occupancy": cache.occupancy.numpy().astype(np.int8),
              "search_config": np.array(json.dumps(config_to_dict(cache.config), sort_keys=True)),
              **{k: getattr(cache, k).numpy() for k in ("log_probs", "cell_features", "global_feature",
                                                       "cell_area_px", "valid")}}
    if stored:
        store = FeatureStore(tmp_path / "part.features", cache.perception_tag)
        for row, seed in enumerate(cache.scene_seed):
            store.write(seed, arrays["cell_features"][row], _outputs(cache, row))
        arrays["cell_features"] = np.zeros((*arrays["log_probs"].shape[:3], 0), np.float16)
        arrays["feature_store"] = np.array("part.features")
    path = tmp_path / ("stored.npz" if stored else "plain.npz")
    path.write_bytes(npz_bytes(arrays, compress=False))
    return path


def test_a_store_reads_back_the_views_asked_for_from_mapped_files(tmp_path):
    cache = synthetic_cache(3, 10, cell_dim=8, config=WIDE)
    store = FeatureStore(tmp_path / "fs", "synthetic")
    for row in range(2):
        store.write(cache.scene_seed[row], cache.cell_features[row].numpy(), _outputs(cache, row))
    want = cache.cell_features.half()
    assert store.shape == (73, 900, 8) and len(store) == 2
    assert (tmp_path / "fs" / "1.npy").stat().st_size < 73 * 900 * 8 * 2 + 200  # float16 on disk
    mapped = store.scene(1)
    assert isinstance(mapped, np.memmap) and mapped.dtype == np.float16 and not mapped.flags.writeable
    views = torch.tensor([72, 0, 5])
    got = store.read(1, views)
    assert got.dtype == torch.float16 and got.device.type == "cpu" and torch.equal(got, want[1, views])
    assert torch.equal(store.read(0, [3], dtype=torch.float32), want[0, [3]].float())
    assert (got.half().float() - cache.cell_features[1, views]).abs().max() < 1e-2  # float16 rounding only
    seeds, pos = np.array([1, 0, 1, 1]), torch.tensor([4, 4, 0, 60])
    assert torch.equal(store.gather(seeds, pos), want[seeds, pos])
    for k, v in store.outputs(0).items():
        assert np.array_equal(v, getattr(cache, k)[0].numpy())
    # a reopened store (another process) sees the same, and pickles without its mapped files
    again = pickle.loads(pickle.dumps(FeatureStore(tmp_path / "fs")))
    assert again.tag == "synthetic" and not again._maps and torch.equal(again.read(0, views), want[0, views])
    with pytest.raises(UavsearchError, match="no features of scene 2"):
        store.read(2, [0])
    with pytest.raises(UavsearchError, match="perception"):
        FeatureStore(tmp_path / "fs", "other-weights")
    with pytest.raises(UavsearchError, match="features"):
        store.write(2, np.zeros((73, 900, 4)), _outputs(cache, 2))


def test_a_resumed_build_skips_the_scenes_done_and_redoes_a_broken_one(tmp_path):
    cache = synthetic_cache(2, 10, cell_dim=4, config=WIDE)
    store = FeatureStore(tmp_path / "fs", "synthetic")
    assert not store.done(0)
    store.write(0, cache.cell_features[0].numpy(), _outputs(cache, 0))
    store.write(1, cache.cell_features[1].numpy(), _outputs(cache, 1))
    resumed = FeatureStore(tmp_path / "fs", "synthetic")
    assert resumed.done(0) and resumed.done(1)
    (tmp_path / "fs" / "1.npy").write_bytes((tmp_path / "fs" / "1.npy").read_bytes()[:-10])  # a killed copy
    assert resumed.done(0) and not resumed.done(1)


def test_a_cache_serves_its_features_from_its_store_as_it_would_from_memory(tmp_path):
    cache = synthetic_cache(3, 10, cell_dim=6, config=WIDE)
    cache = cache._replace(cell_features=cache.cell_features.half())  # a family's features are float16
    plain, stored = _write_cache(tmp_path, cache, False), _write_cache(tmp_path, cache, True)
    lean = load_view_cache(stored, features=False)
    assert lean.cell_features.shape == (3, 73, 900, 0) and lean.feature_store is not None
    full = load_view_cache(stored)
    assert full.feature_store is None and torch.equal(full.cell_features, cache.cell_features)
    rows, pos = torch.tensor([[2, 0], [1, 1]]), torch.tensor([[5, 5], [0, 72]])
    assert torch.equal(lean.features_at(rows, pos), cache.cell_features[rows, pos])
    assert torch.equal(lean.subset([2, 1]).features_at(torch.tensor([0]), torch.tensor([5])),
                       cache.cell_features[[2], [5]])

    # the learned fusion's scores from the store equal those from memory; without `features` nothing else reads them
    conf = ConfidenceNet(6).eval()
    fusion = LearnedFusion(conf)
    runs = {}
    for name, c, features in (("memory", load_view_cache(plain), False), ("store", lean, False),
                              ("store+features", lean, True)):
        src = CachedViews(c, [0, 1, 2, 2], WIDE, conf, features=features)
        obs = src.observe(torch.tensor([0, 3, 3, 7]))
        assert (obs.cell_features is not None) == features
        runs[name] = run_search(src, Agent(fusion, RandomPolicy()), 4, generator=torch.Generator().manual_seed(0))
    for name in ("store", "store+features"):
        assert torch.equal(runs[name].maps, runs["memory"].maps)
        assert torch.equal(runs[name].lattice_idx, runs["memory"].lattice_idx)
    src = CachedViews(lean, [1, 2], WIDE, features=True)
    assert torch.equal(src.observe(torch.tensor([4, 9])).cell_features, cache.cell_features[[1, 2], [4, 9]].float())
    fv = src.fusion_views(torch.tensor([[4, 9], [9, 9]]))  # each distinct (scene, view) once
    assert torch.equal(fv.cell_features[fv.feature_rows], cache.cell_features[[[1, 1], [2, 2]], [[4, 9], [9, 9]]].float())


def test_a_cache_without_a_store_behaves_as_before(tmp_path):
    cache = synthetic_cache(2, 5)
    path = _write_cache(tmp_path, cache, False)
    lean, full = load_view_cache(path, features=False), load_view_cache(path)
    assert lean.feature_store is None and full.feature_store is None
    assert lean.cell_features.shape == (2, 25, 100, 0) and torch.equal(full.cell_features, cache.cell_features)
    r, p = torch.tensor([1, 0]), torch.tensor([3, 24])
    assert lean.features_at(r, p).shape == (2, 100, 0)
    assert torch.equal(full.features_at(r, p), cache.cell_features[r, p])
    fusion = FUSIONS["bayes"]()
    eps = [run_search(CachedViews(c, [0, 1, 1], features=f), Agent(fusion, RandomPolicy()),
                      generator=torch.Generator().manual_seed(3)) for c, f in ((full, False), (lean, False), (full, True))]
    for ep in eps[1:]:
        assert torch.equal(ep.maps, eps[0].maps) and torch.equal(ep.lattice_idx, eps[0].lattice_idx)


def test_a_store_needs_every_scene_of_its_cache(tmp_path):
    cache = synthetic_cache(2, 5)
    path = _write_cache(tmp_path, cache, True)
    (tmp_path / "part.features" / "manifest.json").write_text(
        (tmp_path / "part.features" / "manifest.json").read_text().replace('"1": {', '"7": {'))
    with pytest.raises(UavsearchError, match="lacks some of its scenes"):
        load_view_cache(path, features=False)


@pytest.mark.slow  # renders two wide scenes (about 30 s): `make test-all` runs it
def test_a_family_cache_writes_its_features_scene_by_scene_and_resumes(tmp_path):
    from uavsearch.search.data.view_cache import CacheKey, build_view_cache
    from uavsearch.search.perception import PerceptionConfig, PerceptionNet

    torch.manual_seed(0)
    net = PerceptionNet(PerceptionConfig(num_cells=900, altitude_feature=True)).eval()
    config = dataclasses.replace(WIDE, altitudes_m=(), lattice_points=2)  # 5 viewpoints: cheap renders
    one = load_view_cache(build_view_cache(net, CacheKey("wide", "large", "test", config, limit=1),
                                           cache_dir=tmp_path, workers=1, progress=False), features=False)
    first = sorted((tmp_path / "search_views").glob("*/*.features/*.np[yz]"))
    stamps = [f.stat().st_mtime_ns for f in first]
    two_path = build_view_cache(net, CacheKey("wide", "large", "test", config, limit=2), cache_dir=tmp_path,
                                workers=1, progress=False)
    assert [f.stat().st_mtime_ns for f in first] == stamps  # scene 1 was not redone
    two, full = load_view_cache(two_path, features=False), load_view_cache(two_path)
    assert len(two.feature_store) == 2 and two.cell_features.shape == (2, 5, 900, 0)
    assert full.cell_features.shape == (2, 5, 900, net.cfg.cell_dim) and full.cell_features.dtype == torch.float16
    assert torch.equal(two.log_probs[:1], one.log_probs) and torch.equal(two.valid[:1], one.valid)
    assert torch.equal(two.features_at(torch.tensor([1, 0]), torch.tensor([4, 2])), full.cell_features[[1, 0], [4, 2]])
    assert full.cell_features.float().abs().sum() > 0
