"""Does the learned neighbour fusion lift the wide search on validation, fit after fit? Seeds, CPU time, cost.

`uavsearch train fusion` is fitted once per seed (same rollouts, same data; the seed sets the net's initial
weights, its minibatches and their symmetries). A seed's run found finished under --runs-dir is reused, one
stopped mid-way is resumed (train_state.pt), so a rerun of this study continues. Then on the validation scenes
(where nothing here is chosen: each fusion is its last epoch) the rule (Table III's variant, chosen on validation
with the base fusion) and the shipped learned map policy fly with each seed's fusion; each is paired per scene
against the rule on the base fusion (95% bootstrap interval over scenes), and the mean over seeds of each scene's
F1 gives the ensemble-free "any fit" row; the ensemble of the seeds' fits (their shifted log-odds averaged,
`neighbour:A.pt,B.pt,...`) is flown too, with the rule's variant also chosen on validation with the ensemble
itself, and with `--start CKPT` (a second map policy, say the one the shipped policy was fine-tuned from). A second
column pairs every row against the shipped stack (the shipped map policy on its own fusion): would the ensemble,
with either policy, be worth shipping? Also timed: the fusion's update per view during a flight (one episode,
the process's threads), base against learned.

    python tools/wide_fusion_seeds.py --budget 8 --seeds 0 1 2 --out results/wide_study/fusion_seeds_T8.md

With `--features` the fusions read the views' cell features too (`uavsearch train fusion --features`).
"""

from __future__ import annotations

import shlex
import sys
import time
from pathlib import Path

import numpy as np
import torch

from ..errors import UavsearchError, run_command
from ..paths import RUNS_DIR, display_path
from ..search.agents import load_wide_agent
from ..search.map_policy import wide_checkpoint
from ..search.metrics import bootstrap_ci, map_f1
from ..search.neighbour_fusion import NeighbourEnsemble, load_neighbour
from ..search.search_loop import Agent, CachedViews, run_search
from ..search.train.fusion import Args, train
from ..search.train.map_policy import _caches
from ..search.wide_policies import choose_rule, rule_policy
from .wide_policy_probes import probe_parser, write_markdown


def seed_run(args: Args, runs_dir: Path) -> Path:
    """The run directory of args' seed: a finished one reused, a stopped one resumed, else a new fit."""
    runs = sorted(runs_dir.glob(f"{args.name}__{args.seed}__*"))
    done = [r for r in runs if (r / "summary.json").is_file()]
    if done:
        return done[-1]
    stopped = [r for r in runs if (r / "train_state.pt").is_file()]
    args.resume = str(stopped[-1]) if stopped else None
    return train(args).run_dir


def update_ms(fusion, cache, config, views: int) -> float:
    """Milliseconds per view of the fusion's running update over one validation episode of the rule's kind."""
    from ..search.fusion import FusionViews

    rows = torch.arange(1)
    idx = torch.arange(views)[None] % config.lattice.num_positions
    p = cache.log_probs[rows[:, None], idx, :, 1].exp().float()
    f = cache.features_at(rows[:, None], idx).float() if "cell_features" in fusion.needs else None
    fv = FusionViews(p, cache.valid[rows[:, None], idx], cache.cell_area_px[rows[:, None], idx].float(), f,
                     viewpoints=idx)
    with torch.no_grad():
        for _ in range(2):  # warm up, then time
            t0, state = time.perf_counter(), None
            for t in range(views):
                state, _ = fusion.update(state, fv._replace(p=fv.p[:, t:t + 1], valid=fv.valid[:, t:t + 1],
                                                            area_px=fv.area_px[:, t:t + 1],
                                                            cell_features=None if f is None else f[:, t:t + 1],
                                                            viewpoints=idx[:, t:t + 1]))
    return 1000 * (time.perf_counter() - t0) / views


def ci_text(diff: np.ndarray) -> str:
    d, lo, hi = bootstrap_ci(diff)
    return f"{d:+.3f} [{lo:+.3f}, {hi:+.3f}]"


def main(argv=None) -> int:
    ap = probe_parser(__doc__)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--train-scenes", type=int, default=300)
    ap.add_argument("--epochs", type=int, default=20)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--runs-dir", default=str(RUNS_DIR))
    ap.add_argument("--features", action="store_true", help="fusions that read the views' cell features too")
    ap.add_argument("--start", help="a second map policy checkpoint for the budget, flown on the ensemble")
    args = ap.parse_args(argv)
    if args.start and len(args.seeds) < 2:  # before any fit, not after an hour of them
        raise UavsearchError("--start flies on the seeds' ensemble: give two seeds or more")
    if args.start and not Path(args.start).is_file():
        raise UavsearchError(f"--start {args.start}: no such file")
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    name = f"fusion_study_{args.family}_{args.budget}{'_features' if args.features else ''}"
    runs = [seed_run(Args(family=args.family, budget=args.budget, train_scenes=args.train_scenes,
                          epochs=args.epochs, threads=args.threads, runs_dir=args.runs_dir, name=name, seed=s,
                          features=args.features),
                     Path(args.runs_dir)) for s in args.seeds]
    torch.set_num_threads(args.threads)
    import json

    summaries = [json.loads((r / "summary.json").read_text()) for r in runs]
    fusions = [load_neighbour(r / "model.pt") for r in runs]
    _, val = _caches(Args(family=args.family, train_scenes=1, progress=False))
    from ..search.train.map_policy import budget_config

    config = budget_config(val.config, args.budget)
    base = fusions[0].base
    variant, _ = choose_rule(val, config, base)
    rule = rule_policy(config, variant)
    ours = load_wide_agent(wide_checkpoint(args.budget), config)
    labels = val.occupancy.numpy()

    def f1(agent) -> np.ndarray:
        with torch.no_grad():
            ep = run_search(CachedViews(val, np.arange(val.num_scenes), config), agent,
                            generator=torch.Generator().manual_seed(0))
        return map_f1(ep.maps[:, -1].numpy(), labels)

    ref = f1(Agent(base, rule))
    shipped = f1(ours)
    ours_variant, _ = choose_rule(val, config, ours.fusion)
    rows = [("the rule, base fusion", ref), ("the shipped map policy, its fusion", shipped),
            (f"the rule, the shipped policy's fusion, its variant chosen with it ({ours_variant})",
             f1(Agent(ours.fusion, rule_policy(config, ours_variant))))]
    rule_seeds = [f1(Agent(f, rule)) for f in fusions]
    ours_seeds = [f1(Agent(f, ours.policy)) for f in fusions]
    for s, a, b in zip(args.seeds, rule_seeds, ours_seeds):
        rows += [(f"the rule, neighbour fusion seed {s}", a), (f"the shipped map policy, neighbour fusion seed {s}", b)]
    rows += [("the rule, neighbour fusion, mean over seeds", np.mean(rule_seeds, 0)),
             ("the shipped map policy, neighbour fusion, mean over seeds", np.mean(ours_seeds, 0))]
    ensemble = NeighbourEnsemble.of(fusions) if len(fusions) > 1 else None
    if ensemble is not None:
        own, _ = choose_rule(val, config, ensemble)
        rows += [("the rule, ensemble of the seeds' fusions", f1(Agent(ensemble, rule))),
                 (f"the rule, ensemble, its variant chosen with the ensemble ({own})",
                  f1(Agent(ensemble, rule_policy(config, own)))),
                 ("the shipped map policy, ensemble of the seeds' fusions", f1(Agent(ensemble, ours.policy)))]
        if args.start:
            start = load_wide_agent(args.start, config, where="--start ")
            rows.append((f"{display_path(args.start)}, ensemble of the seeds' fusions",
                         f1(Agent(ensemble, start.policy))))
    steps = min(int(config.budget_T), 20)
    ms_base, ms_nb = update_ms(base, val, config, steps), update_ms(fusions[0], val, config, steps)
    ms_ens = f", the ensemble {update_ms(ensemble, val, config, steps):.2f} ms" if ensemble is not None else ""
    shas = {s: m["weights_sha256"][:16] for s, m in zip(args.seeds, summaries)}
    what = " with cell features" if args.features else ""
    lines = [f"# The learned neighbour fusion{what} over seeds: {args.family}, budget {args.budget}", "",
             f"`uavsearch train fusion --budget {args.budget} --train-scenes {args.train_scenes} --epochs "
             f"{args.epochs}{' --features' if args.features else ''} --seed S` for seeds "
             f"{', '.join(map(str, args.seeds))} (base fusion "
             f"{summaries[0]['base']}, the rule's variant {variant}); {val.num_scenes} validation scenes, each "
             f"fusion its last epoch (nothing chosen on these scenes). Δ: per-scene final AF1 minus the rule's on "
             f"the base fusion, or minus the shipped stack's (the shipped map policy on its own fusion), mean [95% "
             f"bootstrap interval over scenes]. "
             f"`python tools/wide_fusion_seeds.py {shlex.join(sys.argv[1:])}`", "",
             "| agent | AF1 | Δ vs the rule, base fusion [95% CI] | Δ vs the shipped stack [95% CI] |",
             "|---|---|---|---|"]
    for n, f in rows:
        lines.append(f"| {n} | {f.mean():.3f} | {ci_text(f - ref)} | {ci_text(f - shipped)} |")
    lines += ["", f"| seed | fit, s wall ({args.threads} thread(s), on the 2-core machine) | training maps | shift | "
              "weights SHA-256 (first 16) |",
              "|---|---|---|---|---|"]
    lines += [f"| {s} | {m['seconds']:.0f} | {m['scenes']['maps']} | {m['shift']:+.2f} | {shas[s]} |"
              for s, m in zip(args.seeds, summaries)]
    lines += ["", f"Cost in flight: the fusion's update per view over one {steps}-view episode, {args.threads} "
              f"threads: base {ms_base:.2f} ms, neighbour {ms_nb:.2f} ms{ms_ens}.", "",
              f"Runs: {', '.join(display_path(r) for r in runs)}. {time.perf_counter() - t0:.0f} s."]
    write_markdown(args.out, lines)
    return 0


def cli() -> int:
    """The command line: bad input is one line and exit 2."""
    return run_command(main, None, "wide_fusion_seeds.py")


if __name__ == "__main__":
    sys.exit(cli())
