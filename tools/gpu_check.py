"""Runs the project's training, rollout and evaluation on one device and prints how fast each went, as one table.

    python tools/gpu_check.py --device auto|cpu|cuda|cuda:N [--quick] [--data-dir DIR]

Rows, each through the project's own code path on the device asked (devices.resolve_device):
- perception training: a few steps of the stage-1 trainer (search/train/perception.py `train`) on the lattice
  views of one training and one validation scene of setting 2 (rendered first, into --data-dir); views/s is
  the trainer's own charts/views_per_s;
- map-policy training: DAgger and REINFORCE iterations of the wide family's map policy
  (search/train/map_policy.py `train`) on synthetic wide view caches; states/s is the trainer's
  charts/steps_per_s (states rolled out and fitted per second), averaged over its iterations;
- vector-env rollout: the native vector env of WideSearch-v0 (search/envs/vector_env.py) on a synthetic cache,
  random allowed viewpoints, autoreset; steps/s counts env steps (episodes x steps);
- evaluation: `scoring.evaluate_agent` (what every evaluation table runs) with the shipped wide map policy
  (models/search_wide_240s_map.pt; the rule where it is missing) on a synthetic cache; steps/s counts decisions.

`--quick` keeps every row small (about a minute on a 2-core CPU, most of it rendering the 50 views); without it
the rows are sized for a GPU. Where the device cannot be had (`--device cuda` on a machine without CUDA, or a
CPU build of torch) it says so in one line on stderr and exits with 2, the exit of every uavsearch one-line
error; a run that completes exits 0.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import io
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from uavsearch.devices import DEVICES, resolve_device
from uavsearch.errors import run_command
from uavsearch.testing.synthetic_views import synthetic_wide_cache

# (quick, full): sizes of each row
PERCEPTION_STEPS, PERCEPTION_BATCH = (3, 40), (4, 32)
MAP_SCENES, MAP_DAGGER, MAP_PG, MAP_EPISODES = (3, 16), (1, 2), (1, 10), (4, 64)
VEC_ENVS, VEC_STEPS = (8, 256), (16, 32)
EVAL_SCENES, EVAL_EPISODES = (3, 64), (2, 8)


def _metrics(run_dir: Path) -> list[dict]:
    with (Path(run_dir) / "metrics.csv").open() as f:
        return list(csv.DictReader(f))


def _floats(rows: list[dict], key: str) -> list[float]:
    return [float(r[key]) for r in rows if r.get(key) not in (None, "")]


def check_perception(device, q: int, data_dir: Path, runs_dir: Path) -> tuple[str, float, float]:
    from uavsearch.search.train.perception import Args, prepare_data, train

    args = Args(exp_name="gpu_check", seed=1, settings="2", train_scenes=1, val_scenes=1, data_dir=str(data_dir),
                workers=1, steps=PERCEPTION_STEPS[q], batch_size=PERCEPTION_BATCH[q], eval_every=PERCEPTION_STEPS[q],
                calibrate=False, runs_dir=str(runs_dir), progress=False, device=str(device))
    views = prepare_data(args)  # rendered before the clock starts
    t0 = time.perf_counter()
    report = train(args, views=views)
    seconds = time.perf_counter() - t0
    rate = _floats(_metrics(Path(report["run_dir"])), "charts/views_per_s")[-1]
    return f"{rate:,.1f} views/s", rate, seconds


def check_map_policy(device, q: int, runs_dir: Path) -> tuple[str, float, float]:
    from uavsearch.search.config import setting_config
    from uavsearch.search.train.map_policy import Args, train

    config = setting_config("wide")
    caches = (synthetic_wide_cache(MAP_SCENES[q], 1, config),
              synthetic_wide_cache(max(2, MAP_SCENES[q] // 2), 2, config))
    args = Args(family="wide", budget="240", fusion="bayes", teacher="rule", calibration_scenes=2, train_eval_scenes=2,
                val_scenes=2, dagger_iterations=MAP_DAGGER[q], dagger_episodes=MAP_EPISODES[q], dagger_epochs=2,
                pg_iterations=MAP_PG[q], scenes_per_batch=max(2, MAP_EPISODES[q] // 4), episodes_per_scene=4,
                eval_every=max(1, MAP_PG[q]), runs_dir=str(runs_dir), progress=False, plot=False, seed=1,
                device=str(device))
    t0 = time.perf_counter()
    res = train(args, caches=caches)
    seconds = time.perf_counter() - t0
    rate = float(np.mean(_floats(_metrics(res.run_dir), "charts/steps_per_s")))
    return f"{rate:,.0f} states/s", rate, seconds


def check_vector_env(device, q: int) -> tuple[str, float, float]:
    from uavsearch.search.config import setting_config, wide_budgets
    from uavsearch.search.envs.vector_env import SearchVectorEnv

    config = wide_budgets(setting_config("wide"))["240 s"]
    env = SearchVectorEnv(num_envs=VEC_ENVS[q], setting="wide", config=config,
                          cache=synthetic_wide_cache(4, 3, config), device=str(device), progress=False)
    rng = np.random.default_rng(0)
    _, info = env.reset(seed=0)
    t0 = time.perf_counter()
    for _ in range(VEC_STEPS[q]):
        mask = info["action_mask"].astype(bool)
        actions = np.array([rng.choice(np.flatnonzero(m)) if m.any() else 0 for m in mask])
        _, _, _, _, info = env.step(actions)
    seconds = time.perf_counter() - t0
    rate = VEC_ENVS[q] * VEC_STEPS[q] / seconds
    return f"{rate:,.0f} steps/s ({VEC_ENVS[q]} envs)", rate, seconds


def check_evaluation(device, q: int) -> tuple[str, float, float]:
    from uavsearch.devices import to_device
    from uavsearch.search.agents import load_wide_agent
    from uavsearch.search.config import setting_config, wide_budgets
    from uavsearch.search.fusion import BayesFusion
    from uavsearch.search.map_policy import wide_checkpoint
    from uavsearch.search.scoring import evaluate_agent
    from uavsearch.search.search_loop import Agent
    from uavsearch.search.wide_policies import RULE_VARIANTS, rule_policy

    config = wide_budgets(setting_config("wide"))["240 s"]
    agent = load_wide_agent(wide_checkpoint("240"), config, device=device) or \
        Agent(BayesFusion(), rule_policy(config, next(iter(RULE_VARIANTS))))
    dim = getattr(agent.fusion, "cell_dim", None) or 6  # a learned aggregation reads perception's cell features
    cache = to_device(synthetic_wide_cache(EVAL_SCENES[q], 4, config, cell_dim=dim), device)
    t0 = time.perf_counter()
    scores = evaluate_agent(cache, agent, EVAL_EPISODES[q], config=config)
    seconds = time.perf_counter() - t0
    rate = scores.f1.shape[0] * (scores.f1.shape[1] - 1) / seconds
    return f"{rate:,.0f} steps/s ({scores.f1.shape[0]} episodes)", rate, seconds


ROWS = ("perception training (stage 1)", "map-policy training (DAgger + REINFORCE)", "vector-env rollout (WideSearch)",
        "evaluation (map policy, evaluate_agent)")


def gpu_check(args) -> int:
    device = resolve_device(args.device)  # a device that cannot be had: one line, exit 2
    q = 0 if args.quick else 1
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    print(f"torch {torch.__version__}, device {device} ({name}), {'quick' if args.quick else 'full'} sizes", flush=True)
    with tempfile.TemporaryDirectory(prefix="uavsearch-gpu-check-") as tmp:
        data_dir = Path(args.data_dir) if args.data_dir else Path(tmp) / "cache"
        runs = [lambda: check_perception(device, q, data_dir, Path(tmp) / "runs"),
                lambda: check_map_policy(device, q, Path(tmp) / "runs"),
                lambda: check_vector_env(device, q), lambda: check_evaluation(device, q)]
        rows = []
        for what, run in zip(ROWS, runs):
            with contextlib.redirect_stdout(io.StringIO()):  # the trainers' own reports: only the table is ours
                text, _, seconds = run()
            rows.append((what, str(device), text, seconds))
            print(f"  {what}: {text} in {seconds:.2f} s", flush=True)
    print()
    print("| what | device | rate | seconds |")
    print("|---|---|---|---|")
    for what, dev, text, seconds in rows:
        print(f"| {what} | {dev} | {text} | {seconds:.2f} |")
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="auto", help=f"{' | '.join(DEVICES)} | cuda:N (default auto: CUDA when "
                                                    "available, else the CPU)")
    p.add_argument("--quick", action="store_true", help="small sizes (about a minute on a 2-core CPU)")
    p.add_argument("--data-dir", default=None, help="where the perception row renders its views (default: a "
                                                    "temporary folder)")
    return run_command(gpu_check, p.parse_args(argv), prog="gpu_check")


if __name__ == "__main__":
    sys.exit(main())
