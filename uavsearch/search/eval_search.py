"""The paper's Table II and Fig. 6 for our testbed: every method on the TEST scenes of each setting.

Rows (Sec. VII-D; "+ policy" = a policy trained with that fusion, shipped in models/), each built by
agents.build_agent from its (fusion, policy) names:

    single view                          the start view's classification alone
    oracle fusion + random policy        evaluation bound with random moves
    learned confidence fusion + random   the paper's fusion, uniform random moves
    average + policy / bayes rule + policy / by grid size + policy
    learned confidence fusion + policy   the paper's method
    oracle fusion + policy
    learned fusion + coverage route      beyond the paper: a fixed geometric route (policy.CoverageRoute)
    learned fusion + greedy uncertainty  beyond the paper: toward the most uncertain cells

Each stochastic method runs `episodes` episodes per test scene for each of `seeds` evaluation seeds
(the seeds drive the policies' action sampling); the table gives the mean over seeds and, after ±, the
standard deviation over seeds of the per-seed means. Deterministic methods (single view, coverage,
greedy) give the same number for every seed.

Everything goes through search_loop.run_search over cached perception outputs (view_cache.py); the same
loop flies a vehicle (search_loop.LiveViews), and agents.build_agent builds the agents of both.
"""

from __future__ import annotations

import argparse
import csv
import time
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from tqdm import tqdm

from uavsearch.cli_args import add_dataclass_args, dataclass_from_args, opt
from uavsearch.errors import UavsearchError, run_command
from uavsearch.parallel import Executor, ScaleOutArgs
from uavsearch.paths import MODELS_DIR, display_path
from uavsearch.world.settings import SETTINGS
from uavsearch.viz import pyplot, save_figure

from .agents import build_agent, checkpoint_path, needs_confidence
from .config import SearchConfig
from .metrics import map_accuracy, map_f1
from .perception import load_perception
from .search_loop import Agent, CachedViews, Episode, run_search
from .view_cache import get_view_cache

# (key, Table II label, fusion, policy): names from the agent registry (agents.py). The single-view row is
# the start view alone (budget 1), so its policy never moves.
ROWS: tuple[tuple[str, str, str, str], ...] = (
    ("single_view", "single view", "average", "random"),
    ("oracle_random", "oracle fusion + random policy", "oracle", "random"),
    ("learned_random", "learned confidence fusion + random policy", "learned", "random"),
    ("average_policy", "average + policy", "average", "learned"),
    ("bayes_policy", "bayes rule + policy", "bayes", "learned"),
    ("size_policy", "by grid size + policy", "size", "learned"),
    ("learned_policy", "(ours) learned confidence fusion + policy", "learned", "learned"),
    ("oracle_policy", "oracle fusion + policy", "oracle", "learned"),
    ("learned_coverage", "learned confidence fusion + coverage route", "learned", "coverage"),
    ("learned_greedy", "learned confidence fusion + greedy uncertainty", "learned", "greedy"),
)
NON_ORACLE = [r[0] for r in ROWS if r[2] != "oracle"]
model_path = checkpoint_path  # where the shipped policy trained with a fusion for a setting lives


class EpisodeScores(NamedTuple):
    """Per-episode, per-step map metrics of one method: (E, T) each."""
    acc: np.ndarray
    f1: np.ndarray
    revisit_rate: float


def score_episode(ep: Episode) -> EpisodeScores:
    maps = ep.maps.detach().numpy()
    y = ep.labels.numpy()
    T = maps.shape[1]
    acc = np.stack([map_accuracy(maps[:, t], y) for t in range(T)], 1)
    f1 = np.stack([map_f1(maps[:, t], y) for t in range(T)], 1)
    return EpisodeScores(acc, f1, float(ep.revisit[:, 1:].float().mean()) if T > 1 else 0.0)


@torch.no_grad()
def evaluate_agent(cache, agent: Agent, episodes_per_scene: int = 10, seed: int = 0, config: SearchConfig | None = None,
                   budget_T: int | None = None, single_view: bool = False) -> EpisodeScores:
    """Run `episodes_per_scene` episodes on every scene of the cache; the generator is seeded by `seed`."""
    for m in (agent.confidence, getattr(agent.policy, "net", agent.policy)):
        if isinstance(m, torch.nn.Module):
            m.eval()
    rows = np.repeat(np.arange(cache.num_scenes), episodes_per_scene)
    gen = torch.Generator().manual_seed(int(seed))
    conf = agent.confidence if needs_confidence(agent.fusion) else None
    ep = run_search(CachedViews(cache, rows, config, conf), agent, 1 if single_view else budget_T, generator=gen)
    return score_episode(ep)


# --------------------------------------------------------------------------------------------------


def methods(setting: int, config: SearchConfig, models_dir=None, argmax: bool = False) -> dict[str, Agent]:
    """Every Table II row (plus coverage and greedy) as an Agent, from the checkpoints in `models_dir`."""
    return {key: build_agent(fusion, policy, config, checkpoint=checkpoint_path(setting, fusion, models_dir),
                             confidence_checkpoint=checkpoint_path(setting, "learned", models_dir),
                             greedy=argmax).agent
            for key, _, fusion, policy in ROWS}


@dataclass
class EvalArgs(ScaleOutArgs):
    setting: str = opt("all", "paper setting 1 | 2 | 3 (2, 5, 10 occupied cells) | all")
    split: str = opt("paper", "scene split (paper: 10 test scenes per setting; large: 100)")
    out: str = opt("eval_search", "output folder: table2.md, table2.csv, fig6.png", required=True)
    perception: str = opt(str(MODELS_DIR / "perception.pt"), "frozen perception checkpoint")
    models_dir: str = opt(str(MODELS_DIR), "where search_s<K>_<fusion>.pt live")
    episodes: int = opt(10, "episodes per test scene per seed")
    seeds: int = opt(5, "evaluation seeds (0..seeds-1): the spread over seeds")
    argmax: bool = opt(False, "trained policies take their most likely action instead of sampling (paper: sample)")
    cache_dir: str | None = opt(None, "view caches: a folder or an fsspec URL (default cache/)")
    progress: bool = opt(True, "progress bars")


def evaluate_setting(setting: int, cache, args: EvalArgs) -> dict[str, dict]:
    """{row key: {"acc": (seeds, E, T), "f1": ..., "revisit": (seeds,), "scenes": S}} on one setting's cache."""
    config = SearchConfig()
    agents = methods(setting, config, args.models_dir, args.argmax)
    res: dict[str, dict] = {}
    for key, agent in tqdm(agents.items(), desc=f"eval setting {setting}", disable=not args.progress, leave=False):
        single = key == "single_view"
        per_seed = [evaluate_agent(cache, agent, args.episodes, seed=s, config=config, single_view=single)
                    for s in range(args.seeds)]
        acc, f1 = np.stack([p.acc for p in per_seed]), np.stack([p.f1 for p in per_seed])
        if single:  # the start view is the whole "episode": every step shows it
            acc, f1 = np.repeat(acc, config.budget_T, -1), np.repeat(f1, config.budget_T, -1)
        res[key] = {"acc": acc, "f1": f1, "revisit": np.array([p.revisit_rate for p in per_seed]),
                    "scenes": cache.num_scenes}
    return res


def summarise(results: dict[int, dict[str, dict]], episodes: int) -> list[dict]:
    """Table rows: final-step Aacc (%) and AF1, mean and std over seeds, per setting."""
    rows = []
    for key, label, fusion, kind in ROWS:
        row = {"method": label, "key": key}
        for setting, res in results.items():
            r = res[key]
            acc_seed = r["acc"][:, :, -1].mean(1) * 100.0  # (seeds,)
            f1_seed = r["f1"][:, :, -1].mean(1)
            row[f"s{setting}_aacc"] = float(acc_seed.mean())
            row[f"s{setting}_aacc_std"] = float(acc_seed.std())
            row[f"s{setting}_af1"] = float(f1_seed.mean())
            row[f"s{setting}_af1_std"] = float(f1_seed.std())
            row[f"s{setting}_revisit"] = float(r["revisit"].mean())
            row[f"s{setting}_scenes"] = int(r["scenes"])
            row[f"s{setting}_episodes"] = int(r["acc"].shape[1] * r["acc"].shape[0])
        rows.append(row)
    return rows


def gap_closure(rows: list[dict], setting: int) -> float:
    """Share of the single-view -> oracle fusion + policy AF1 gap the paper's method closes."""
    by = {r["key"]: r for r in rows}
    sv, ours, orc = (by[k][f"s{setting}_af1"] for k in ("single_view", "learned_policy", "oracle_policy"))
    return (ours - sv) / (orc - sv) if orc != sv else float("nan")


def write_table(rows: list[dict], settings: list[int], out: Path, meta: dict) -> tuple[Path, Path]:

    out.mkdir(parents=True, exist_ok=True)
    csv_path = out / "table2.csv"
    with csv_path.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0].keys()))
        w.writeheader()
        w.writerows(rows)
    best = {}
    for s in settings:
        cand = [r for r in rows if r["key"] in NON_ORACLE]
        best[s] = (max(cand, key=lambda r: r[f"s{s}_aacc"])["key"], max(cand, key=lambda r: r[f"s{s}_af1"])["key"])
    head = " | ".join(f"{SETTINGS[s]} cells Aacc (%) ↑ | {SETTINGS[s]} cells AF1 ↑" for s in settings)
    lines = [f"# Table II (our testbed): T = {meta['T']}, {meta['split']} split, test scenes only", "",
             f"| method | {head} |", "|---|" + "---|---|" * len(settings)]
    for r in rows:
        cells = []
        for s in settings:
            a = f"{r[f's{s}_aacc']:.2f} ± {r[f's{s}_aacc_std']:.2f}"
            f1 = f"{r[f's{s}_af1']:.3f} ± {r[f's{s}_af1_std']:.3f}"
            if r["key"] == best[s][0]:
                a = f"**{a}**"
            if r["key"] == best[s][1]:
                f1 = f"**{f1}**"
            cells += [a, f1]
        lines.append(f"| {r['method']} | " + " | ".join(cells) + " |")
    lines += ["", "Bold: best non-oracle row. ± : standard deviation over evaluation seeds (action sampling).", ""]
    for s in settings:
        r0 = rows[0]
        lines.append(f"- setting {s} ({SETTINGS[s]} cells): {r0[f's{s}_scenes']} test scenes, "
                     f"{r0[f's{s}_episodes']} episodes per method ({meta['episodes']} per scene x {meta['seeds']} "
                     f"seeds); single view -> oracle fusion + policy AF1 gap closed by ours: "
                     f"{100 * gap_closure(rows, s):.0f}% (paper: 37% / 52% / 41%)")
    lines += ["", f"perception {meta['perception']} (tag {meta['tag']}); policies {meta['models_dir']}; "
              f"trained policies {'take argmax actions' if meta['argmax'] else 'sample their actions'}; "
              f"{meta['seconds']:.0f} s"]
    md_path = out / "table2.md"
    md_path.write_text("\n".join(lines) + "\n")
    return md_path, csv_path


def fig6_figure(results: dict[int, dict[str, dict]]):
    """Metric vs. time step per setting; the legend below the panels (one column per 2 settings it spans)."""
    settings = list(results)
    fig, axes = pyplot().subplots(2, len(settings), figsize=(max(4.6 * len(settings), 8.0), 7.8), squeeze=False,
                                  layout="constrained")
    labels = {k: lab for k, lab, _, _ in ROWS}
    styles = {"single_view": ":", "oracle_random": "--", "oracle_policy": "--", "learned_policy": "-"}
    for j, s in enumerate(settings):
        for key, r in results[s].items():
            T = r["acc"].shape[-1]
            x = np.arange(1, T + 1)
            lw = 2.6 if key == "learned_policy" else 1.3
            for i, (name, scale) in enumerate((("acc", 100.0), ("f1", 1.0))):
                axes[i, j].plot(x, r[name].mean((0, 1)) * scale, styles.get(key, "-"), marker="o", ms=3, lw=lw,
                                label=labels[key])
        axes[0, j].set_title(f"setting {s}: {SETTINGS[s]} occupied cells")
        axes[0, j].set_ylabel("Aacc (%)")
        axes[1, j].set_ylabel("AF1")
        for i in range(2):
            axes[i, j].set_xlabel("time step (views)")
            axes[i, j].set_xticks(x)
            axes[i, j].grid(alpha=0.3)
    handles, labs = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labs, loc="outside lower center", ncol=2 if len(settings) < 3 else 3, fontsize=8,
               frameon=False)
    fig.suptitle("Fig. 6 (our testbed): performance vs. time step, test scenes")
    return fig


def plot_fig6(results: dict[int, dict[str, dict]], path: Path) -> Path:
    return save_figure(fig6_figure(results), path)


def eval_search(args: EvalArgs, caches: dict | None = None) -> dict:
    """Table II + Fig. 6 into args.out; `caches` ({setting: ViewCache}) skips perception and rendering."""

    if args.setting == "all":
        settings = sorted(SETTINGS)
    else:
        try:
            settings = [int(args.setting)]
        except ValueError:
            raise UavsearchError(f"--setting must be 1, 2, 3 or all, not {args.setting!r}") from None
        if settings[0] not in SETTINGS:
            raise UavsearchError(f"unknown setting {settings[0]}; valid: {sorted(SETTINGS)} or all")
    if args.episodes < 1 or args.seeds < 1:
        raise UavsearchError("--episodes and --seeds must be at least 1")
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    if caches is None:
        net, _ = load_perception(args.perception)
        caches = {s: get_view_cache(net, s, args.split, "test", cache_dir=args.cache_dir, progress=args.progress,
                                    executor=Executor.from_args(args))
                  for s in settings}
    results = {s: evaluate_setting(s, caches[s], args) for s in settings}
    rows = summarise(results, args.episodes)
    out = Path(args.out)
    meta = {"T": SearchConfig().budget_T, "split": args.split, "episodes": args.episodes, "seeds": args.seeds,
            "perception": display_path(args.perception), "tag": caches[settings[0]].perception_tag, "models_dir": display_path(args.models_dir),
            "argmax": args.argmax, "seconds": time.perf_counter() - t0}
    md, csv_path = write_table(rows, settings, out, meta)
    fig = plot_fig6(results, out / "fig6.png")
    print(md.read_text())
    print(f"wrote {md}, {csv_path}, {fig}")
    return {"rows": rows, "results": results, "table": md, "figure": fig}


# --------------------------------------------------------------------------------------------------
# CLI


def add_eval_search_parser(subparsers) -> None:
    """`uavsearch eval search ...` (subparsers: the `eval` command's); one flag per EvalArgs field."""
    p = subparsers.add_parser("search", help="Table II and Fig. 6: every fusion/policy method on the test scenes")
    add_dataclass_args(p, EvalArgs)
    p.set_defaults(func=cmd_eval_search)


def cmd_eval_search(args) -> int:
    eval_search(dataclass_from_args(EvalArgs, args))
    return 0


if __name__ == "__main__":  # python -m uavsearch.search.eval_search [flags] = uavsearch eval search [flags]
    raise SystemExit(run_command(cmd_eval_search, add_dataclass_args(argparse.ArgumentParser(
        prog="python -m uavsearch.search.eval_search"), EvalArgs).parse_args()))
