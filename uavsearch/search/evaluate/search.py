"""The paper's Table II and Fig. 6 for our testbed: every method on the TEST scenes of each setting.

Rows (Sec. VII-D; "+ policy" = a policy trained with that fusion, shipped in models/), each built by
agents.build_agent from its (fusion, policy) names:

    single view                          the start view's classification alone
    oracle fusion + random policy        evaluation bound with random moves
    learned confidence fusion + random   the paper's fusion, uniform random moves
    average + policy / bayes rule + policy / by grid size + policy
    learned confidence fusion + policy   the paper's method
    ours, reactive                       learned fusion + the reactive conv policy (reactive.py: a map-shaped
                                         state, DAgger from a label-peeking teacher, then REINFORCE)
    oracle fusion + policy
    learned fusion + coverage route      beyond the paper: a fixed geometric route (policy.CoverageRoute)
    learned fusion + greedy uncertainty  beyond the paper: toward the most uncertain cells
    PPO (external)                       beyond the paper: learned fusion + a PPO actor trained on the gymnasium
                                         env's cells observations (search_s<K>_learned_external.pt, written by
                                         examples/sb3_ppo.py or examples/cleanrl_ppo.py; argmax moves)

Each stochastic method runs `episodes` episodes per test scene for each of `seeds` evaluation seeds
(the seeds drive the policies' action sampling); the table gives the mean over seeds and, after ±, the
standard deviation over seeds of the per-seed means. Deterministic methods (single view, coverage,
greedy) give the same number for every seed.

A row whose checkpoint is missing from `models_dir` (a user may have trained only some) is left out
with a one-line notice. Beside the table (bounds.py):

- paired comparison: every row minus the coverage route and minus the greedy route, per test scene, with
  a 95% bootstrap interval over scenes and the scenes won / tied / lost (table2_paired.csv);
- the share of the single-view -> oracle fusion + policy AF1 gap each row closes;
- bounds and difficulty per setting: single-view AF1, the occupied cells hidden from the start view
  (and from every view), the hindsight-best route (the best of all move sequences per scene, learned
  fusion), the best single fixed route, hindsight-best minus coverage, and the label-peeking greedy
  (table2_bounds.csv).

Everything goes through search_loop.run_search over cached perception outputs (view_cache.py); the same
loop flies a vehicle (search_loop.LiveViews), and agents.build_agent builds the agents of both.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from uavsearch.cli_args import add_dataclass_args, dataclass_from_args, opt
from uavsearch.devices import resolve_device, to_device
from uavsearch.errors import UavsearchError, run_command
from uavsearch.parallel import Executor, ScaleOutArgs
from uavsearch.paths import MODELS_DIR, display_path
from uavsearch.viz import pyplot, save_figure
from uavsearch.world.settings import parse_settings, setting_params

from ..agents import POLICIES, build_agent, checkpoint_path, trained_fusion
from ..config import SearchConfig
from ..data.view_cache import get_view_cache
from ..perception import load_perception, shipped_perception
from ..policy import load_search_model
from ..scoring import evaluate_agent
from ..search_loop import Agent
from ..metrics import RESAMPLES, bootstrap_ci
from .bounds import hidden_shares, label_greedy_af1, paired_differences, route_bounds
from .tables import write_csv

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
    ("learned_reactive", "ours, reactive: learned confidence fusion + reactive policy", "learned", "reactive"),
    ("oracle_policy", "oracle fusion + policy", "oracle", "learned"),
    ("learned_coverage", "learned confidence fusion + coverage route", "learned", "coverage"),
    ("learned_greedy", "learned confidence fusion + greedy uncertainty", "learned", "greedy"),
    ("external_ppo", "PPO (external): learned confidence fusion + PPO actor", "learned", "external"),
)
NON_ORACLE = [r[0] for r in ROWS if r[2] != "oracle"]
LABELS = {key: label for key, label, _, _ in ROWS}
# The reactive policy is trained to act on its most likely move (DAgger, then checkpoints chosen by their argmax
# moves), so it is evaluated that way; the paper's policy samples, as in the paper (or --argmax for all).
# A PPO actor trained outside (the "external" policy) is scored by its most likely move too, as SB3's
# predict(deterministic=True) does.
ARGMAX_POLICIES = ("reactive", "external")
REFERENCES = ("learned_coverage", "learned_greedy")  # the fixed baselines every row is paired with
model_path = checkpoint_path  # where the shipped policy trained with a fusion for a setting lives


def policy_checkpoint(setting: int, fusion: str, policy: str, models_dir=None) -> Path | None:
    """The checkpoint a row's policy loads (None for a policy built from the config)."""
    if POLICIES[policy].build is not None:
        return None
    return checkpoint_path(setting, fusion, models_dir, policy=policy)


def row_checkpoints(setting: int, fusion: str, policy: str, models_dir=None) -> list[Path]:
    """Every file a row needs: its policy's checkpoint, and the confidence net's for learned fusion."""
    need = [policy_checkpoint(setting, fusion, policy, models_dir)]
    if trained_fusion(fusion):
        need.append(checkpoint_path(setting, "learned", models_dir))
    return [p for p in need if p is not None]


def available_rows(setting: int, models_dir=None) -> tuple[list[str], list[str]]:
    """(keys of the rows whose checkpoints exist, one notice per row left out)."""
    keys, notices = [], []
    for key, label, fusion, policy in ROWS:
        missing = [p for p in row_checkpoints(setting, fusion, policy, models_dir) if not Path(p).is_file()]
        if missing:
            notices.append(f"setting {setting}: {label!r} left out: {display_path(missing[0])} not found")
        else:
            keys.append(key)
    return keys, notices


def methods(setting: int, config: SearchConfig, models_dir=None, argmax: bool = False,
            keys=None, device="cpu") -> dict[str, Agent]:
    """Every Table II row (plus coverage and greedy; only `keys` when given) as an Agent, from the checkpoints
    in `models_dir`, its nets on `device`."""
    return {key: build_agent(fusion, policy, config, checkpoint=policy_checkpoint(setting, fusion, policy, models_dir),
                             confidence_checkpoint=checkpoint_path(setting, "learned", models_dir),
                             greedy=argmax or policy in ARGMAX_POLICIES, device=device).agent
            for key, _, fusion, policy in ROWS if keys is None or key in keys}


@dataclass
class EvalArgs(ScaleOutArgs):
    setting: str = opt("all", "paper setting 1 | 2 | 3 (2, 5, 10 occupied cells) | all (Table II), or a scene family "
                              "wide | wide-uniform (Table III: evaluate/wide.py)")
    split: str | None = opt(None, "scene split (paper: 10 test scenes per setting; large: 100); default: the "
                                  "setting's own (paper for 1-3, large for the families)")
    out: str = opt("eval_search", "output folder: table2.md, table2.csv, fig6.png", required=True)
    perception: str | None = opt(None, "frozen perception checkpoint (default: models/perception.pt; a scene "
                                       "family's own models/perception_<family>.pt)")
    models_dir: str = opt(str(MODELS_DIR), "where search_s<K>_<fusion>.pt live")
    episodes: int = opt(10, "episodes per test scene per seed")
    seeds: int = opt(5, "evaluation seeds (0..seeds-1): the spread over seeds")
    argmax: bool = opt(False, "trained policies take their most likely action instead of sampling (paper: sample)")
    cache_dir: str | None = opt(None, "view caches: a folder or an fsspec URL (default cache/)")
    bootstrap: int = opt(RESAMPLES, "bootstrap resamples over scenes for the paired intervals")
    bootstrap_seed: int = opt(0, "seed of the bootstrap resamples")
    bounds: bool = opt(True, "the hindsight-best route and label-peeking greedy bounds (every route on every scene)")
    progress: bool = opt(True, "progress bars")
    wide_fusion: str = opt("auto", "Table III: the fusion of every row but the oracle ones, as name or name:prior "
                                   "(e.g. bayes:0.05; the prior is also the p of a cell no view measured), "
                                   "calibrated:GAMMA (fitted on the training scenes), or auto: chosen on the "
                                   "validation scenes per family and budget (evaluate/wide.py)")
    wide_train_scenes: int = opt(500, "Table III: training scenes the fixed view sets are searched on (the first N)")
    wide_val_scenes: int | None = opt(None, "Table III: validation scenes choosing the best fixed route (first N; all)")
    wide_test_scenes: int | None = opt(None, "Table III: test scenes (the first N; default all 100)")
    wide_policy_dir: str | None = opt(None, "Table III: where the learned wide-area policies are "
                                            "(search_wide_T8_map.pt, search_wide_240s_map.pt; default models/); a "
                                            "budget without one has no learned row")


def evaluate_setting(setting: int, cache, args: EvalArgs, keys=None) -> dict[str, dict]:
    """{row key: {"acc": (seeds, E, T), "f1": ..., "revisit": (seeds,), "scenes": S}} on one setting's cache,
    for the rows `keys` (default every row)."""
    config = cache.config
    agents = methods(setting, config, args.models_dir, args.argmax, keys, device=cache.occupancy.device)
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
    """Table rows: final-step Aacc (%) and AF1, mean and std over seeds, per setting (NaN where a setting lacks
    the row); rows no setting evaluated are left out. `s<K>_gap`: the share of the AF1 gap closed."""
    rows = []
    for key, label, fusion, kind in ROWS:
        if not any(key in res for res in results.values()):
            continue
        row = {"method": label, "key": key}
        for setting, res in results.items():
            if key not in res:
                row.update({f"s{setting}_{f}": float("nan") for f in ("aacc", "aacc_std", "af1", "af1_std", "revisit")})
                row.update({f"s{setting}_scenes": 0, f"s{setting}_episodes": 0})
                continue
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
    for row in rows:
        for setting in results:
            row[f"s{setting}_gap"] = gap_closure(rows, setting, row["key"])
    return rows


def gap_closure(rows: list[dict], setting: int, key: str = "learned_policy") -> float:
    """Share of the single-view -> oracle fusion + policy AF1 gap a row (default the paper's method) closes;
    NaN where a row is missing or the gap is zero."""
    by = {r["key"]: r for r in rows}
    if not all(k in by for k in ("single_view", key, "oracle_policy")):
        return float("nan")
    sv, ours, orc = (by[k][f"s{setting}_af1"] for k in ("single_view", key, "oracle_policy"))
    return (ours - sv) / (orc - sv) if orc != sv else float("nan")


def _num(x: float, fmt: str) -> str:
    return "—" if x is None or not np.isfinite(x) else format(x, fmt)


def setting_bounds(setting: int, cache, res: dict[str, dict], args: EvalArgs) -> dict:
    """Difficulty and upper bounds of one setting (module docstring); `notes` says what was skipped and why."""
    config = cache.config
    nan = float("nan")
    b = {"setting": setting, "scenes": cache.num_scenes, "single_view_af1": nan, "hidden_start": nan,
         "hidden_all": nan, "coverage_af1": nan, "best_fixed_af1": nan, "best_fixed_route": "",
         "hindsight_best_af1": nan, "hindsight_minus_coverage": nan, "ci_low": nan, "ci_high": nan,
         "label_greedy_af1": nan, "notes": []}
    if "single_view" in res:
        b["single_view_af1"] = float(res["single_view"]["f1"][:, :, -1].mean())
    hidden = hidden_shares(cache, config)
    if hidden is None:
        b["notes"].append("hidden cells skipped: this view cache was written before it kept person_px (delete its "
                          ".npz under cache/search_views/ and run again to rebuild it)")
    else:
        b["hidden_start"], b["hidden_all"] = hidden
    conf_path = checkpoint_path(setting, "learned", args.models_dir)
    confidence = load_search_model(conf_path, cache.occupancy.device).fusion if args.bounds and conf_path.is_file() \
        else None
    if not args.bounds:
        b["notes"].append("route bounds not computed (--bounds false)")
    elif confidence is None:
        b["notes"].append(f"route bounds skipped: no learned fusion checkpoint ({display_path(conf_path)})")
    else:
        rb = route_bounds(cache, confidence, config)
        m, lo, hi = bootstrap_ci(rb.best - rb.coverage, args.bootstrap, args.bootstrap_seed)
        b.update(coverage_af1=float(rb.coverage.mean()), best_fixed_af1=rb.best_fixed,
                 best_fixed_route=" ".join(config.actions[a].removeprefix("Move") for a in rb.best_fixed_route),
                 hindsight_best_af1=float(rb.best.mean()), hindsight_minus_coverage=m, ci_low=lo, ci_high=hi)
        b["label_greedy_af1"] = float(label_greedy_af1(cache, confidence, config).mean())
    return b


def _paired_lines(paired: list[dict], settings: list[int], meta: dict) -> list[str]:
    lines = ["## Paired with the fixed routes (per test scene)", "",
             f"Each row's per-scene mean final AF1 (over its episodes and seeds) minus the reference route's on the "
             f"same scenes; mean over scenes [95% bootstrap interval over scenes, {meta['bootstrap']} resamples, "
             f"seed {meta['bootstrap_seed']}]; W/T/L: scenes the row wins / ties / loses. An interval that "
             "holds 0 cannot tell the two apart.", ""]
    for s in settings:
        here = [p for p in paired if p["setting"] == s]
        refs = [r for r in REFERENCES if any(p["reference"] == r for p in here)]
        if not refs:
            lines += [f"- setting {s}: no paired comparison (neither fixed route was evaluated)", ""]
            continue
        first = here[0]
        lines += [f"Setting {s} ({setting_params(s).k} cells): paired over {first['scenes']} test scenes, "
                  f"{first['episodes_per_scene']} episodes per scene x {first['seeds']} seeds per row (a fixed "
                  "route scores the same on each).", "",
                  "| method | AF1 | " + " | ".join(f"Δ AF1 vs {LABELS[r].split(' + ')[-1]} [95% CI] | W/T/L"
                                                     for r in refs) + " |",
                  "|---|---|" + "---|---|" * len(refs)]
        keys = list(dict.fromkeys(p["key"] for p in here))
        for key in keys:
            cells = []
            for r in refs:
                q = next((p for p in here if p["key"] == key and p["reference"] == r), None)
                cells += (["—", "—"] if q is None else
                          [f"{q['diff']:+.3f} [{q['ci_low']:+.3f}, {q['ci_high']:+.3f}]",
                           f"{q['wins']}/{q['ties']}/{q['losses']}"])
            af1 = next(p["af1"] for p in here if p["key"] == key)
            lines.append(f"| {LABELS[key]} | {af1:.3f} | " + " | ".join(cells) + " |")
        lines.append("")
    return lines


def _bounds_lines(bounds: dict[int, dict], settings: list[int]) -> list[str]:
    def row(name, f):
        return f"| {name} | " + " | ".join(f(bounds[s]) for s in settings) + " |"

    pct = lambda x: _num(100 * x, ".0f") + ("%" if np.isfinite(x) else "")  # noqa: E731
    lines = ["## Difficulty and upper bounds (learned confidence fusion)", "",
             "| | " + " | ".join(f"setting {s} ({setting_params(s).k} cells)" for s in settings) + " |",
             "|---|" + "---|" * len(settings),
             row("single-view AF1", lambda b: _num(b["single_view_af1"], ".3f")),
             row("occupied cells hidden from the start view (no person pixel)", lambda b: pct(b["hidden_start"])),
             row("occupied cells hidden from every lattice view", lambda b: pct(b["hidden_all"])),
             row("coverage route AF1", lambda b: _num(b["coverage_af1"], ".3f")),
             row("best single fixed route AF1 (route)", lambda b: _num(b["best_fixed_af1"], ".3f") + (
                 f" ({b['best_fixed_route']})" if b["best_fixed_route"] else "")),
             row("hindsight-best route AF1 (ceiling of any route)", lambda b: _num(b["hindsight_best_af1"], ".3f")),
             row("hindsight-best − coverage [95% CI]", lambda b: _num(b["hindsight_minus_coverage"], "+.3f") + (
                 f" [{b['ci_low']:+.3f}, {b['ci_high']:+.3f}]" if np.isfinite(b["ci_low"]) else "")),
             row("label-peeking greedy AF1", lambda b: _num(b["label_greedy_af1"], ".3f")), "",
             "Hindsight-best: per scene the best final AF1 over all 4^(T-1) move sequences from the start. The best "
             "single fixed route is the one best on average over these same test scenes, so it is a bound too, not "
             "a baseline.", ""]
    for s in settings:
        lines += [f"- setting {s}: {n}" for n in bounds[s]["notes"]]
    return lines + [""]


def write_table(rows: list[dict], settings: list[int], out: Path, meta: dict, paired: list[dict] | None = None,
                bounds: dict[int, dict] | None = None) -> tuple[Path, Path]:
    """table2.md and table2.csv (and table2_paired.csv / table2_bounds.csv when given) into `out`."""
    out.mkdir(parents=True, exist_ok=True)
    csv_path = write_csv(out / "table2.csv", rows)
    best = {}
    for s in settings:
        cand = [r for r in rows if r["key"] in NON_ORACLE and np.isfinite(r[f"s{s}_af1"])]
        best[s] = (max(cand, key=lambda r: r[f"s{s}_aacc"])["key"] if cand else None,
                   max(cand, key=lambda r: r[f"s{s}_af1"])["key"] if cand else None)
    head = " | ".join(f"{setting_params(s).k} cells Aacc (%) ↑ | {setting_params(s).k} cells AF1 ↑" for s in settings)
    lines = [f"# Table II (our testbed): T = {meta['T']}, {meta['split']} split, test scenes only", "",
             f"| method | {head} |", "|---|" + "---|---|" * len(settings)]
    for r in rows:
        cells = []
        for s in settings:
            a = "—" if not np.isfinite(r[f"s{s}_aacc"]) else f"{r[f's{s}_aacc']:.2f} ± {r[f's{s}_aacc_std']:.2f}"
            f1 = "—" if not np.isfinite(r[f"s{s}_af1"]) else f"{r[f's{s}_af1']:.3f} ± {r[f's{s}_af1_std']:.3f}"
            if r["key"] == best[s][0]:
                a = f"**{a}**"
            if r["key"] == best[s][1]:
                f1 = f"**{f1}**"
            cells += [a, f1]
        lines.append(f"| {r['method']} | " + " | ".join(cells) + " |")
    lines += ["", "Bold: best non-oracle row. ± : standard deviation over evaluation seeds (action sampling). "
              "—: left out (checkpoint not found).", ""]
    for s in settings:
        r0 = next((r for r in rows if r[f"s{s}_scenes"]), rows[0])
        lines.append(f"- setting {s} ({setting_params(s).k} cells): {r0[f's{s}_scenes']} test scenes, "
                     f"{r0[f's{s}_episodes']} episodes per method ({meta['episodes']} per scene x {meta['seeds']} "
                     f"seeds); single view -> oracle fusion + policy AF1 gap closed by ours: "
                     f"{_num(100 * gap_closure(rows, s), '.0f')}% (paper: 37% / 52% / 41%)")
    lines += [f"- {n}" for n in meta.get("notices", [])]
    gap_rows = [r for r in rows if r["key"] not in ("single_view", "oracle_policy")]
    if any(np.isfinite(r[f"s{s}_gap"]) for r in gap_rows for s in settings):
        lines += ["", "## Share of the single view -> oracle fusion + policy AF1 gap closed", "",
                  "| method | " + " | ".join(f"setting {s}" for s in settings) + " |", "|---|" + "---|" * len(settings)]
        lines += [f"| {r['method']} | " + " | ".join(_num(100 * r[f"s{s}_gap"], ".0f") + "%" * bool(
            np.isfinite(r[f"s{s}_gap"])) for s in settings) + " |" for r in gap_rows]
    lines.append("")
    if paired is not None:
        lines += _paired_lines(paired, settings, meta)
        if paired:
            write_csv(out / "table2_paired.csv", paired)
    if bounds is not None:
        lines += _bounds_lines(bounds, settings)
        write_csv(out / "table2_bounds.csv", [{k: ("; ".join(v) if k == "notes" else v) for k, v in b.items()}
                                         for b in bounds.values()])
    lines += [f"perception {meta['perception']} (tag {meta['tag']}); policies {meta['models_dir']}; "
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
    styles = {"single_view": ":", "oracle_random": "--", "oracle_policy": "--", "learned_policy": "-",
              "learned_reactive": "-"}
    for j, s in enumerate(settings):
        for key, r in results[s].items():
            T = r["acc"].shape[-1]
            x = np.arange(1, T + 1)
            lw = 2.6 if key in ("learned_policy", "learned_reactive") else 1.3
            for i, (name, scale) in enumerate((("acc", 100.0), ("f1", 1.0))):
                axes[i, j].plot(x, r[name].mean((0, 1)) * scale, styles.get(key, "-"), marker="o", ms=3, lw=lw,
                                label=labels[key])
        axes[0, j].set_title(f"setting {s}: {setting_params(s).k} occupied cells")
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
    """Table II + Fig. 6 into args.out (Table III for scene families: evaluate/wide.py); `caches`
    ({setting: ViewCache}) skips perception and rendering."""
    chosen = parse_settings(args.setting, families=True)
    families = [s for s in chosen if setting_params(s).task.mission == "team"]  # Table III's kind of task
    if families and len(families) != len(chosen):
        raise UavsearchError("--setting: evaluate the paper's settings and the scene families in separate runs")
    if families:
        from .wide import eval_wide

        return eval_wide(args, families, caches)
    settings = chosen
    split = args.split or "paper"
    if args.episodes < 1 or args.seeds < 1:
        raise UavsearchError("--episodes and --seeds must be at least 1")
    if args.bootstrap < 1:
        raise UavsearchError("--bootstrap must be at least 1")
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    keys, notices = {}, []
    for s in settings:
        keys[s], left_out = available_rows(s, args.models_dir)
        notices += left_out
    for n in notices:
        print(f"uavsearch: {n}")
    args = dataclasses.replace(args, perception=args.perception or str(shipped_perception()))
    if caches is None:
        net, _ = load_perception(args.perception)
        caches = {s: get_view_cache(net, s, split, "test", cache_dir=args.cache_dir, progress=args.progress,
                                    executor=Executor.from_args(args))
                  for s in settings}
    device = resolve_device(getattr(args, "device", "auto"))
    caches = {s: to_device(caches[s], device) for s in settings}
    results = {s: evaluate_setting(s, caches[s], args, keys[s]) for s in settings}
    rows = summarise(results, args.episodes)
    paired = [{"setting": s, **p} for s in settings
              for p in paired_differences(results[s], REFERENCES, LABELS, args.bootstrap, args.bootstrap_seed)]
    bounds = {s: setting_bounds(s, caches[s], results[s], args) for s in settings}
    out = Path(args.out)
    meta = {"T": caches[settings[0]].config.budget_T, "split": split, "episodes": args.episodes, "seeds": args.seeds,
            "perception": display_path(args.perception), "tag": caches[settings[0]].perception_tag,
            "models_dir": display_path(args.models_dir), "argmax": args.argmax, "notices": notices,
            "bootstrap": args.bootstrap, "bootstrap_seed": args.bootstrap_seed, "seconds": time.perf_counter() - t0}
    md, csv_path = write_table(rows, settings, out, meta, paired, bounds)
    fig = plot_fig6(results, out / "fig6.png")
    print(md.read_text())
    extra = [out / n for n in ("table2_paired.csv", "table2_bounds.csv") if (out / n).is_file()]
    print(f"wrote {md}, {csv_path}, " + "".join(f"{p}, " for p in extra) + f"{fig}")
    return {"rows": rows, "results": results, "paired": paired, "bounds": bounds, "notices": notices,
            "table": md, "figure": fig}


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


if __name__ == "__main__":  # python -m uavsearch.search.evaluate.search [flags] = uavsearch eval search [flags]
    raise SystemExit(run_command(cmd_eval_search, add_dataclass_args(argparse.ArgumentParser(
        prog="python -m uavsearch.search.evaluate.search"), EvalArgs).parse_args()))
