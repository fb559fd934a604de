"""Per-scene tasks on two executors give the same bytes: real renders on a local process pool, in
process, and on a 2-node Ray cluster on loopback; shard manifests make a resumed run skip finished work."""

import csv
import io
import ipaddress
import json
import os
import socket
import subprocess
import sys
import time
import zipfile

import numpy as np
import pytest
import torch

from uavsearch.errors import UavsearchError
from uavsearch.parallel import Executor, Store, map_scenes, npz_bytes
from uavsearch.testing.clean_env import clean_env
from uavsearch.search.data.dataset import (
    ViewSetSpec,
    generate_views,
    load_views,
    perception_scenes,
    render_scene_shard,
    render_tag,
    shard_key,
    shard_path,
)

SPEC = ViewSetSpec("par_v2_s7", perception_scenes("train", 3, 7), views_per_scene=2, seed=7)


def _files(root) -> dict[str, bytes]:
    """Every file of a view set or cache folder (shards and manifests), by path relative to it."""
    out = {}
    for dirpath, _, names in os.walk(root):
        for n in names:
            p = os.path.join(dirpath, n)
            out[os.path.relpath(p, root)] = open(p, "rb").read()
    return out


def _entries(root) -> dict:
    return json.loads((root / "manifest.json").read_text())["shards"]


def test_npz_bytes_are_a_pure_function_of_the_arrays(tmp_path):
    arrays = {"a": np.arange(6, dtype=np.int16).reshape(2, 3), "b": np.float32(2.5), "c": np.array("x")}
    data = npz_bytes(arrays)
    assert data == npz_bytes(dict(arrays))
    with zipfile.ZipFile(io.BytesIO(data)) as z:
        assert {i.date_time for i in z.infolist()} == {(1980, 1, 1, 0, 0, 0)}
    (tmp_path / "x.npz").write_bytes(data)
    with np.load(tmp_path / "x.npz") as z:
        assert np.array_equal(z["a"], arrays["a"]) and float(z["b"]) == 2.5 and str(z["c"]) == "x"


def test_store_writes_whole_files_and_lists_keys(tmp_path):
    store = Store(tmp_path / "s")
    assert store.keys("shards") == [] and store.read_json("manifest.json") is None
    store.write_bytes("shards/a.npz", b"12345")
    store.write_json("manifest.json", {"x": 1})
    assert store.keys("shards") == ["shards/a.npz"] and store.size("shards/a.npz") == 5
    assert store.read_json("manifest.json") == {"x": 1}
    same = Store(f"file://{tmp_path / 's'}")
    assert same.read_bytes("shards/a.npz") == b"12345" and same.local
    with pytest.raises(UavsearchError, match="not found"):
        store.read_bytes("shards/none.npz")
    with pytest.raises(UavsearchError, match="unknown executor"):
        Executor("dask")


@pytest.mark.slow  # renders scenes in a pool and in one process (about 24 s): `make test-all` runs it
def test_local_pool_and_one_process_write_the_same_bytes_and_resume_skips_finished_shards(tmp_path):
    a, b = tmp_path / "one", tmp_path / "pool"
    generate_views(SPEC, a, executor=Executor("local", 1), progress=False)
    generate_views(SPEC, b, executor=Executor("local", 2), progress=False)
    fa = _files(a)
    assert len(fa) == len(SPEC.scenes) + 1 and fa == _files(b)
    entries = _entries(a)
    assert entries == _entries(b)
    tag = render_tag()
    for s, k in SPEC.scenes:
        e = entries[shard_key(s, k)]
        assert e["tag"] == tag and e["size"] == len(fa[shard_key(s, k)])
    # Resume: an unchanged set renders nothing (the files are not rewritten) ...
    stamp = {k: os.stat(a / k).st_mtime_ns for k in fa if k.startswith("shards")}
    generate_views(SPEC, a, workers=1, progress=False)
    assert {k: os.stat(a / k).st_mtime_ns for k in stamp} == stamp
    # ... a shard of another renderer's tag, a truncated shard and a missing one are rendered again, a
    # shard the manifest never recorded (a run killed between writing and recording) is adopted.
    (s0, k0), (s1, k1), (s2, k2) = SPEC.scenes
    man = json.loads((a / "manifest.json").read_text())
    man["shards"][shard_key(s0, k0)]["tag"] = "old-renderer"
    del man["shards"][shard_key(s2, k2)]
    (a / "manifest.json").write_text(json.dumps(man))
    shard_path(a, s1, k1).write_bytes(fa[shard_key(s1, k1)][:100])
    generate_views(SPEC, a, workers=1, progress=False)
    assert _files(a) == fa and _entries(a) == entries
    assert os.stat(shard_path(a, s2, k2)).st_mtime_ns == stamp[shard_key(s2, k2)]
    assert len(load_views(a)) == 2 * len(SPEC.scenes)


def test_a_url_store_holds_the_same_bytes_as_a_folder(tmp_path):
    """Any fsspec URL works as the store (memory:// here: the s3:// code path without a network)."""
    spec = ViewSetSpec("url", SPEC.scenes[:1], views_per_scene=2, seed=7)
    url = f"memory://uavsearch-test-{os.getpid()}/views"
    generate_views(spec, url, workers=1, progress=False)
    generate_views(spec, tmp_path / "v", workers=1, progress=False)
    store = Store(url)
    assert not store.local and store.keys("shards") == [shard_key(*spec.scenes[0])]
    assert store.read_bytes(shard_key(*spec.scenes[0])) == shard_path(tmp_path / "v", *spec.scenes[0]).read_bytes()
    assert store.read_bytes("manifest.json") == (tmp_path / "v" / "manifest.json").read_bytes()
    assert np.array_equal(load_views(url).images, load_views(tmp_path / "v").images)


def test_ray_asked_for_without_the_extra_is_a_one_line_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    before = dict(os.environ)
    with pytest.raises(UavsearchError, match=r"pip install 'uavsearch\[ray\]'"):
        map_scenes(abs, [1], Executor("ray"), progress=False)
    assert dict(os.environ) == before  # nothing of Ray's is set in this process
    assert Executor.from_args(type("A", (), {"ray_address": "auto", "workers": 3})()) == Executor("ray", 3, "auto")


def test_an_unreachable_ray_address_is_a_one_line_error_not_a_wait():
    pytest.importorskip("ray", reason="needs the ray extra")
    with socket.socket() as s:  # a port that was free a moment ago: nothing listens there
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    for address, match in ((f"127.0.0.1:{port}", "cannot reach the Ray cluster"), ("nohost", "HOST:PORT")):
        with pytest.raises(UavsearchError, match=match):
            map_scenes(abs, [1], Executor("ray", address=address), progress=False)


# A child that runs map_scenes on a Ray it starts itself, and reports what that Ray is: the results, the
# addresses its nodes and processes listen on, whether its own environment changed, and the head's processes.
LOCAL_RAY_CHILD = """
import json, os, ray
import psutil  # Ray's own copy (ray/thirdparty_files), on the path once ray is imported
from uavsearch.parallel import Executor, map_scenes
def magnitude(x):  # a function, as ray.remote needs (a builtin is not one)
    return abs(x)
env = dict(os.environ)
out = map_scenes(magnitude, [-3, 1, -2, 5], Executor("ray", 2), progress=False)
head = [p for p in psutil.Process().children() if "ray.scripts.scripts" in " ".join(p.cmdline())]
procs = [q for h in head for q in [h] + h.children(recursive=True)]
listen = sorted({c.laddr.ip for q in procs for c in q.net_connections("tcp") if c.status == psutil.CONN_LISTEN})
print(json.dumps({"out": out, "nodes": [n["NodeManagerAddress"] for n in ray.nodes()], "listen": listen,
                  "env_same": dict(os.environ) == env, "pids": [q.pid for q in procs]}))
"""


@pytest.mark.slow  # starts a Ray head (the ray extra): `make test-all` runs it
@pytest.mark.timeout(300)
def test_a_local_ray_listens_on_loopback_only_and_stops_with_its_driver(tmp_path):
    pytest.importorskip("ray", reason="needs the ray extra")
    psutil = pytest.importorskip("psutil")
    child = subprocess.run([sys.executable, "-c", LOCAL_RAY_CHILD], env=clean_env(), cwd=tmp_path,
                           capture_output=True, text=True, timeout=240)
    assert child.returncode == 0, child.stderr[-2000:]
    got = json.loads(child.stdout.strip().splitlines()[-1])
    assert got["out"] == [3, 1, 2, 5]
    assert got["nodes"] == ["127.0.0.1"] and got["listen"]
    for ip in map(ipaddress.ip_address, got["listen"]):  # 127.0.0.1, or it mapped into IPv6 (::ffff:127.0.0.1)
        assert (getattr(ip, "ipv4_mapped", None) or ip).is_loopback, got["listen"]
    assert got["env_same"]
    assert len(got["pids"]) > 2  # the head, its GCS and raylet at least
    def alive():
        out = []
        for pid in got["pids"]:
            try:
                if psutil.Process(pid).status() != psutil.STATUS_ZOMBIE:
                    out.append(pid)
            except psutil.NoSuchProcess:
                pass
        return out

    deadline = time.monotonic() + 30.0  # the head has exited; its last processes may take a moment on a busy machine
    while alive() and time.monotonic() < deadline:
        time.sleep(0.5)
    assert alive() == []  # the driver's exit stopped the head and everything it started


def test_map_scenes_keeps_the_order_of_its_items():
    assert map_scenes(abs, [-3, 1, -2, 5], Executor("local", 2), progress=False) == [3, 1, 2, 5]
    assert map_scenes(abs, [], progress=False) == []


# --------------------------------------------------------------------------------------------------
# Ray: a 2-node cluster on this machine (ray.cluster_utils), loopback only


@pytest.fixture(scope="module")
def ray_cluster():
    ray = pytest.importorskip("ray", reason="the Ray cluster test needs the ray extra: pip install 'uavsearch[ray]'")
    from ray.cluster_utils import Cluster

    # Set for the cluster's lifetime only (its nodes inherit them), undone for every later test.
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("RAY_USAGE_STATS_ENABLED", "0")
        mp.setenv("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")  # every node and the driver on 127.0.0.1
        cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
        try:
            cluster.add_node(num_cpus=1)
            cluster.wait_for_nodes()
            yield cluster
        finally:
            ray.shutdown()
            cluster.shutdown()


@pytest.mark.slow  # a 2-node Ray cluster (the ray extra): `make test-all` runs it
@pytest.mark.timeout(300)
def test_a_ray_cluster_and_the_local_pool_build_the_same_view_cache_and_table2(tmp_path, ray_cluster):
    import ray

    from uavsearch.search.evaluate.search import EvalArgs, eval_search, model_path
    from uavsearch.search.fusion import FUSIONS, LearnedFusion
    from uavsearch.search.perception import ConfidenceNet, PerceptionNet
    from uavsearch.search.policy import PolicyConfig, PolicyNet, save_search_model
    from uavsearch.search.data.view_cache import CacheKey, build_view_cache, load_view_cache

    torch.manual_seed(0)
    net = PerceptionNet().eval()
    key = CacheKey(2, "paper", "test")
    scenes = key.scenes()[:2]
    on_ray = Executor("ray", address=ray_cluster.address)
    path_ray = build_view_cache(net, key, scenes=scenes, cache_dir=tmp_path / "ray", executor=on_ray, progress=False)
    assert len({n["NodeID"] for n in ray.nodes() if n["Alive"]}) == 2
    path_local = build_view_cache(net, key, scenes=scenes, cache_dir=tmp_path / "local",
                                  executor=Executor("local", 2), progress=False)
    ray_files, local_files = _files(tmp_path / "ray"), _files(tmp_path / "local")
    assert len(ray_files) == len(scenes) + 2  # a shard per scene, the view set's manifest, the perception cache
    assert ray_files == local_files
    assert path_ray.read_bytes() == path_local.read_bytes()
    # A task's bad input comes back as its one-line error, not a remote traceback.
    bad = [(SPEC.to_json(), Store(tmp_path / "bad"), 1, 999, render_tag())]
    with pytest.raises(UavsearchError, match="out of range") as err:
        map_scenes(render_scene_shard, bad, on_ray, progress=False)
    assert "\n" not in str(err.value)

    models = tmp_path / "models"
    torch.manual_seed(0)
    for fusion in ("learned", "average", "bayes", "size", "oracle"):
        fu = LearnedFusion(ConfidenceNet(net.cfg.cell_dim)) if fusion == "learned" else FUSIONS[fusion]()
        save_search_model(model_path(2, fusion, models), fu, PolicyNet(PolicyConfig(net.cfg.global_dim)))
    tables = []
    for name, path in (("ray", path_ray), ("local", path_local)):
        out = tmp_path / f"eval_{name}"
        eval_search(EvalArgs(setting="2", out=str(out), models_dir=str(models), episodes=2, seeds=2, progress=False),
                    caches={2: load_view_cache(path)})
        tables.append((out / "table2.csv").read_bytes())
    assert tables[0] == tables[1] and len(list(csv.DictReader(tables[0].decode().splitlines()))) > 5


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_flight_vs_teleport_rows_are_the_same_on_ray_and_here(tmp_path, ray_cluster):
    """Two real SITL flights per executor (each a `uavsearch sitl` process over UDP on 127.0.0.1)."""
    from uavsearch.fly.missions import load_mission
    from uavsearch.fly.flight_vs_teleport import eval_flight_vs_teleport

    timing = ("wall_s", "flight_wall_s")
    rows = []
    for name, executor in (("here", Executor("local", 1)), ("ray", Executor("ray", address=ray_cluster.address))):
        res = eval_flight_vs_teleport(load_mission(None), 2, scenes=[0, 1], out=tmp_path / name, progress=False,
                                      executor=executor)
        assert res["summary"]["completed"] == 2
        rows.append([{k: v for k, v in r.items() if k not in timing} for r in res["rows"]])
    assert rows[0] == rows[1] and [r["scene"] for r in rows[0]] == [0, 1]
