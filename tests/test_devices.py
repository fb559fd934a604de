"""The device seam: resolve_device's convention (SB3's get_device), seeded generators per device, caches and plain
objects moved, `--device` on every training and evaluation command, tools/gpu_check.py --quick on the CPU, and
the hot paths run as if their device were not torch's default one (HostVsDevice), the check a CPU-only suite can
make of code written for CUDA."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.overrides import TorchFunctionMode
from torch.utils._pytree import tree_flatten

from uavsearch.devices import cpu_state, follow, make_generator, resolve_device, to_device
from uavsearch.errors import UavsearchError
from uavsearch.search.config import setting_config, wide_budgets
from uavsearch.testing.clean_env import clean_env
from uavsearch.testing.synthetic_views import synthetic_cache, synthetic_wide_cache

REPO = Path(__file__).resolve().parents[1]
NO_CUDA = not torch.cuda.is_available()


def test_auto_is_cuda_where_torch_sees_one_else_the_cpu():
    assert resolve_device("auto") == torch.device("cuda" if torch.cuda.is_available() else "cpu")
    assert resolve_device(None) == resolve_device("auto")
    cpu = torch.device("cpu")
    assert resolve_device("cpu") == resolve_device(" CPU ") == resolve_device(cpu) == cpu


@pytest.mark.skipif(not NO_CUDA, reason="this machine has CUDA")
def test_cuda_without_cuda_and_unknown_devices_are_one_line_errors():
    for name in ("cuda", "cuda:0"):
        with pytest.raises(UavsearchError, match="sees no CUDA GPU") as e:
            resolve_device(name)
        assert "\n" not in str(e.value)
    for bad in ("tpu", "cuda:x", "cpu:1", ""):
        with pytest.raises(UavsearchError, match="unknown device"):
            resolve_device(bad)


def test_a_cpu_generator_draws_what_torch_generator_draws():
    a, b = make_generator(7, "cpu"), torch.Generator().manual_seed(7)
    assert a.device == torch.device("cpu")
    assert torch.equal(torch.rand(5, generator=a), torch.rand(5, generator=b))
    assert torch.equal(torch.randperm(9, generator=a, device=a.device), torch.randperm(9, generator=b))


def test_moving_a_cache_moves_its_tensors_and_keeps_the_rest():
    c = synthetic_cache(2)
    moved = to_device(c, "cpu")
    assert moved.occupancy is c.occupancy and moved.config is c.config and moved.scene_seed is c.scene_seed
    assert to_device(None, "cpu") is None

    class Rule:
        def __init__(self):
            self.cost, self.name = torch.ones(3), "rule"

    r = Rule()
    assert follow(r, torch.device("cpu")) is r and r.name == "rule" and r.cost.device.type == "cpu"
    net = torch.nn.Linear(2, 3)
    assert all(v.device.type == "cpu" and not v.requires_grad for v in cpu_state(net).values())


def _train_eval_subcommands():
    from uavsearch.cli import build_parser

    for group in ("train", "eval"):
        parser = build_parser(group)
        top = next(a for a in parser._actions if a.dest == "cmd").choices[group]
        for name, sub in next(a for a in top._actions if a.dest.endswith("_cmd")).choices.items():
            yield f"{group} {name}", sub


def test_every_training_and_evaluation_command_takes_device_auto_by_default():
    seen = []
    for name, sub in _train_eval_subcommands():
        device = [a for a in sub._actions if a.dest == "device"]
        assert device and device[0].default == "auto" and "--device" in device[0].option_strings, name
        seen.append(name)
    assert {"train perception", "train policy", "train reactive", "train map", "eval search", "eval team"} <= set(seen)


@pytest.mark.skipif(not NO_CUDA, reason="this machine has CUDA")
def test_a_training_asked_for_cuda_without_one_stops_with_one_line(capsys, tmp_path):
    from uavsearch.cli import main

    assert main(["train", "map", "--device", "cuda", "--runs-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "sees no CUDA GPU" in err[0]
    assert not list(tmp_path.iterdir())  # refused before any run directory


# --------------------------------------------------------------------------------------------------
# Host vs device on the CPU

_FACTORIES = {"tensor", "as_tensor", "asarray", "zeros", "ones", "full", "empty", "arange", "rand", "randn",
              "randint", "randperm", "eye", "linspace", "from_numpy"}
HOST, RUN, ANY = True, False, None


def mark_host(*objs):
    """Say these tensors (a cache's, a lattice's) live on torch's default device, as loaded or built."""
    for x in objs:
        if isinstance(x, torch.Tensor):
            x._on_host = HOST
        elif isinstance(x, tuple):
            mark_host(*x)
        elif x is not None and hasattr(x, "__dict__") and not isinstance(x, torch.nn.Module):
            mark_host(*[v for v in vars(x).values() if isinstance(v, (torch.Tensor, tuple))])


def _state(t):
    return getattr(t, "_on_host", RUN)


def _set(out, state):
    for t in tree_flatten(out)[0]:
        if isinstance(t, torch.Tensor) and not isinstance(t, torch.nn.Parameter):
            t._on_host = state
    return out


def _moved(out, src, state):
    out = out.clone() if out is src else out
    out._on_host = state
    return out


class HostVsDevice(TorchFunctionMode):
    """A run on the CPU as if its device were not torch's default one (CUDA): a tensor a factory makes without
    `device=` (or from numpy) lives on the default device, the host; one moved with `.to(device)` /
    `as_tensor(..., device=)`, and the nets and data made before, live on the run's device; a factory given a
    device follows whatever it meets. An op mixing host and run tensors raises as CUDA would (a host 0-dim
    tensor may join, copy_ crosses), and so does numpy() of a run tensor."""

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = getattr(func, "__name__", "")
        flat = [t for t in tree_flatten((args, kwargs))[0] if isinstance(t, torch.Tensor)]
        from_tensor = bool(args) and isinstance(args[0], torch.Tensor)
        if name in _FACTORIES and not (name in ("as_tensor", "asarray") and from_tensor):
            return _set(func(*args, **kwargs), HOST if kwargs.get("device") is None else ANY)
        if name in ("as_tensor", "asarray") and kwargs.get("device") is not None:
            return _moved(func(*args, **kwargs), args[0], RUN)
        if name in ("to", "cuda"):
            other = [a for a in args[1:] if isinstance(a, torch.Tensor)]
            moves = name == "cuda" or any(isinstance(a, (torch.device, str)) for a in (*args[1:], kwargs.get("device")))
            out = func(*args, **kwargs)
            if other:
                return _moved(out, args[0], _state(other[0]))
            if moves:
                return out if isinstance(out, torch.nn.Parameter) else _moved(out, args[0], RUN)
            return out if out is args[0] else _set(out, _state(args[0]))
        if name == "cpu":
            return _moved(func(*args, **kwargs), args[0], HOST)
        states = [_state(t) for t in flat]
        if name in ("numpy", "__array__") and RUN in states:
            raise RuntimeError(f"{name}() of a tensor on the run's device (.cpu() first)")
        mixing = [_state(t) for t in flat if not (_state(t) is HOST and t.dim() == 0)]
        if HOST in mixing and RUN in mixing and name != "copy_":
            raise RuntimeError(f"{name} mixes host tensors {[tuple(t.shape) for t in flat if _state(t) is HOST]} "
                               f"with the run's {[tuple(t.shape) for t in flat if _state(t) is RUN]}")
        out = func(*args, **kwargs)
        return _set(out, HOST if HOST in states else RUN if RUN in states else ANY) if flat else out


def _host_lattices(*configs):
    for cfg in configs:
        for k in ("moves", "flight_time_t", "cell_distances", "cell_areas"):
            getattr(cfg.lattice, k)  # built now, on the host, as a config builds them
        mark_host(cfg.lattice)


WIDE = setting_config("wide")
TIMED = wide_budgets(WIDE)["240 s"]


def test_the_check_sees_a_host_tensor_meet_the_runs():
    run = torch.ones(3)
    with HostVsDevice():
        with pytest.raises(RuntimeError, match="mixes host"):
            run + torch.zeros(3)
        with pytest.raises(RuntimeError, match="numpy"):
            run.numpy()
        assert torch.equal(run + torch.zeros(3, device=run.device), run) and run.cpu().numpy().sum() == 3
        host = torch.arange(3)
        with pytest.raises(RuntimeError, match="mixes host"):
            run[host]
        assert torch.equal(run[host.to(run.device)], run)


def test_map_policy_training_keeps_every_tensor_on_the_runs_device(tmp_path):
    from uavsearch.search.train.map_policy import Args, train

    caches = (synthetic_wide_cache(3, seed=1), synthetic_wide_cache(2, seed=2))
    mark_host(*caches)
    _host_lattices(WIDE, TIMED)
    for teacher in ("labels", "rule"):
        args = Args(family="wide", budget="240", fusion="calibrated:0.5", teacher=teacher, calibration_scenes=2,
                    train_eval_scenes=2, dagger_iterations=1, dagger_episodes=4, dagger_epochs=1, batch_size=16,
                    pg_iterations=1, scenes_per_batch=2, episodes_per_scene=2, eval_every=1, channels=8,
                    conv_layers=2, hidden=16, runs_dir=str(tmp_path / teacher), progress=False, plot=False, seed=3,
                    device="cpu")
        with HostVsDevice():
            train(args, caches=caches)


def test_vector_envs_and_team_search_keep_every_tensor_on_the_runs_device():
    from uavsearch.search.envs.vector_env import SearchVectorEnv
    from uavsearch.search.evaluate.team import team_scores

    paper, wide = synthetic_cache(3), synthetic_wide_cache(3)
    mark_host(paper, wide)
    _host_lattices(WIDE, TIMED, setting_config(2))
    rng = np.random.default_rng(0)
    with HostVsDevice():
        for kw in ({"setting": "wide", "config": TIMED, "cache": wide},
                   {"setting": 2, "cache": paper, "fusion": "bayes"}):
            env = SearchVectorEnv(num_envs=4, device="cpu", progress=False, **kw)
            _, info = env.reset(seed=0)
            for _ in range(6):
                mask = info.get("action_mask", np.ones((4, env.single_action_space.n), np.int8)).astype(bool)
                _, _, _, _, info = env.step(np.array([rng.choice(np.flatnonzero(m)) if m.any() else 0 for m in mask]))
        for planner in ("rule", "partition", "entropy_per_s", "team_entropy"):
            team_scores(to_device(wide, "cpu"), planner, "bayes", 2, 120.0)


def test_the_paper_policy_and_reactive_trainers_keep_every_tensor_on_the_runs_device(tmp_path):
    from uavsearch.search.agents import new_agent
    from uavsearch.search.policy import save_search_model
    from uavsearch.search.train import policy as paper, reactive

    config = setting_config(2)
    caches = (synthetic_cache(4, seed=0), synthetic_cache(2, seed=1))
    mark_host(*caches)
    _host_lattices(config)
    torch.manual_seed(0)
    conf = new_agent("learned", config, 16, 6)
    save_search_model(tmp_path / "conf.pt", conf.fusion, conf.policy)
    with HostVsDevice():
        paper.train(paper.Args(fusion="learned", iterations=2, scenes_per_batch=2, episodes_per_scene=2, eval_every=2,
                               eval_episodes=1, runs_dir=str(tmp_path / "paper"), progress=False, plot=False,
                               device="cpu"), caches=caches)
        reactive.train(reactive.Args(confidence=str(tmp_path / "conf.pt"), dagger_iterations=1, dagger_episodes=4,
                                     dagger_epochs=1, batch_size=8, pg_iterations=1, scenes_per_batch=2,
                                     episodes_per_scene=2, eval_every=1, channels=4, hidden=8,
                                     runs_dir=str(tmp_path / "reactive"), progress=False, plot=False, device="cpu"),
                       caches=caches)


def test_the_envs_take_a_device_and_refuse_cuda_without_one():
    import gymnasium as gym

    import uavsearch.envs  # noqa: F401 - registers the ids

    cache = synthetic_wide_cache(2)
    mark_host(cache)
    _host_lattices(WIDE)
    with HostVsDevice():
        env = gym.make("uavsearch/WideSearch-v0", cache=cache, device="cpu", progress=False, budget="240")
        _, info = env.reset(seed=0)
        for _ in range(3):
            env.step(int(np.flatnonzero(info["action_mask"])[0]))
    assert env.unwrapped.device == torch.device("cpu")
    vec = gym.make_vec("uavsearch/WideSearch-v0", num_envs=2, vectorization_mode="vector_entry_point", cache=cache,
                       device="cpu", progress=False)
    assert vec.unwrapped.device == torch.device("cpu")
    if NO_CUDA:
        with pytest.raises(UavsearchError, match="sees no CUDA GPU"):
            gym.make("uavsearch/WideSearch-v0", cache=cache, device="cuda", progress=False)


def test_table2_and_table3_keep_every_tensor_on_the_runs_device(tmp_path):
    from types import SimpleNamespace

    from test_eval_search import _models
    from uavsearch.search.config import config_to_dict
    from uavsearch.search.evaluate.search import EvalArgs, eval_search
    from uavsearch.search.evaluate.wide import eval_wide
    from uavsearch.search.fusion import FUSIONS
    from uavsearch.search.map_policy import MapPolicyConfig, MapPolicyNet, wide_checkpoint
    from uavsearch.search.policy import save_search_model

    paper = synthetic_cache(3)
    wide = {"test": synthetic_wide_cache(2, 1), "val": synthetic_wide_cache(2, 2), "train": synthetic_wide_cache(2, 3)}
    mark_host(paper, *wide.values())
    _host_lattices(setting_config(2), WIDE, *wide_budgets(WIDE).values())
    models = _models(tmp_path / "models")
    save_search_model(wide_checkpoint("240", models), FUSIONS["average"](),
                      MapPolicyNet(MapPolicyConfig(config_to_dict(TIMED))), {"args": {"family": "wide"}})
    with HostVsDevice():
        eval_search(EvalArgs(setting="2", out=str(tmp_path / "t2"), models_dir=str(models), episodes=1, seeds=1,
                             bootstrap=50, progress=False, device="cpu"), caches={2: paper})
        eval_wide(SimpleNamespace(out=str(tmp_path / "t3"), wide_fusion="average", episodes=1, seeds=1, bootstrap=50,
                                  bootstrap_seed=0, perception="models/perception.pt", progress=False,
                                  wide_policy_dir=str(models), device="cpu"), ["wide"], {"wide": wide})


@pytest.mark.slow  # renders two scenes' lattice views and trains (about 40 s)
def test_perception_training_keeps_every_tensor_on_the_runs_device(tmp_path):
    from uavsearch.search.train.perception import Args, prepare_data, train

    args = Args(exp_name="p", seed=3, settings="2", train_scenes=1, val_scenes=1, data_dir=str(tmp_path / "cache"),
                workers=1, steps=2, batch_size=4, eval_every=2, runs_dir=str(tmp_path / "runs"), progress=False,
                device="cpu")
    views = prepare_data(args)
    with HostVsDevice():
        train(args, views=views)


# --------------------------------------------------------------------------------------------------
# tools/gpu_check.py


ROW = re.compile(r"^\| (?P<what>[^|]+) \| (?P<device>[^|]+) \| (?P<rate>[\d,.]+) (?P<unit>[\w/]+)[^|]* \| "
                 r"(?P<seconds>[\d.]+) \|$")


def test_gpu_check_quick_on_the_cpu_prints_one_row_per_code_path(tmp_path):
    r = subprocess.run([sys.executable, str(REPO / "tools" / "gpu_check.py"), "--device", "cpu", "--quick",
                        "--data-dir", str(tmp_path / "cache")], cwd=tmp_path, env=clean_env(),
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    table = r.stdout[r.stdout.index("| what | device | rate | seconds |"):].strip().splitlines()
    rows = [ROW.match(line) for line in table[2:]]
    assert all(rows) and len(rows) == 4, table
    assert [m["what"] for m in rows] == ["perception training (stage 1)", "map-policy training (DAgger + REINFORCE)",
                                         "vector-env rollout (WideSearch)", "evaluation (map policy, evaluate_agent)"]
    assert {m["device"] for m in rows} == {"cpu"}
    assert [m["unit"] for m in rows] == ["views/s", "states/s", "steps/s", "steps/s"]
    assert all(float(m["rate"].replace(",", "")) > 0 and float(m["seconds"]) > 0 for m in rows)


@pytest.mark.skipif(not NO_CUDA, reason="this machine has CUDA")
def test_gpu_check_says_in_one_line_that_there_is_no_cuda():
    r = subprocess.run([sys.executable, str(REPO / "tools" / "gpu_check.py"), "--device", "cuda", "--quick"],
                       env=clean_env(), capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and r.stdout == ""
    assert len(r.stderr.strip().splitlines()) == 1 and "sees no CUDA GPU" in r.stderr
