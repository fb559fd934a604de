"""Table III: the wide-area search (scene families "wide" and "wide-uniform") on its test scenes.

Two budgets, each its own table: T = 8 views (no time limit) and 240 s of simulated flight (views until
no unvisited viewpoint is affordable; search_loop's time budget). Every row fuses with one non-learned
fusion over the view cache of the family's shipped perception (models/perception_wide.pt), except the
oracle rows: `--wide-fusion NAME[:PRIOR]`, `calibrated:GAMMA`, or `auto` (the default): per family and budget,
the candidate of FUSION_CANDIDATES and the calibrated fusions (fitted on the training scenes, one per
CALIBRATED_GAMMAS) with the best mean validation AF1 over the hand-made fixed routes and the rule. The rows:

    fixed routes       lawnmower at 70 m / at 40 m; survey (4 inner or 4 covering 70 m views) then the 40 m
                       lawnmower; the view set chosen greedily on training scenes (AF1 gain, or AF1 gain per
                       second of flight); the best of these on the validation scenes is "the best fixed route"
    the rule           survey at 70 m, then descend over the highest fused p (wide_policies.DescendRule); its
                       survey (RULE_SURVEYS: 4 covering views, or those and 4 inner ones), the fused p below
                       which it keeps surveying instead (RULE_RESURVEY_BELOW, 0: never) and whether it weighs
                       a descent per second of flight, chosen on validation (RULE_VARIANTS)
    the learned stack  the learned wide-area policy with the fusion its checkpoint carries (the learned
                       aggregation, search/neighbour_fusion.py, where it was trained on one), and the rule on that
                       same fusion (its variant chosen on validation with it): what the learned selection adds
    entropy per second greedy expected information per second of flight
    random             uniform over the allowed viewpoints (`episodes` per scene x `seeds`)
    bounds             the rule with oracle perception (a view detects an occupied cell iff its person shows a
                       pixel; oracle fusion); label-peeking greedy and hindsight-best (a beam search over routes
                       by the AF1 the labels give, the better of the two per scene): no policy that reads no
                       labels is expected to reach them

Every row is paired per test scene against the best fixed route, the rule (the hand-made stack: hand-made fusion,
hand-made selection) and the learned stack (final AF1; mean over scenes with a 95% scene-bootstrap interval,
metrics.bootstrap_ci, bounds.paired_differences).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from uavsearch.devices import make_generator, resolve_device, to_device
from uavsearch.errors import UavsearchError
from uavsearch.parallel import Executor
from uavsearch.paths import display_path
from uavsearch.viz import pyplot, save_figure
from uavsearch.world.settings import setting_params

from ..agents import build_agent, load_wide_agent, make_fusion
from ..config import SearchConfig, wide_budgets
from ..data.view_cache import ViewCache, get_view_cache
from ..fusion import Fusion, OracleFusion, calibrated_candidates, calibrated_gamma, fusion_name
from ..map_policy import BUDGETS, wide_checkpoint
from ..perception import load_perception, shipped_perception
from ..policy import load_search_model
from ..scoring import score_episode
from ..search_loop import Agent, CachedViews, run_search
from ..wide_policies import RoutePolicy, choose_rule, greedy_view_set, label_routes, rule_policy
from .bounds import paired_differences, scene_af1
from .tables import write_csv

FIXED = ("lawnmower_high", "lawnmower_low", "survey_inner", "survey_outer", "viewset", "viewset_per_s")
LABELS = {
    "lawnmower_high": "lawnmower at 70 m", "lawnmower_low": "lawnmower at 40 m",
    "survey_inner": "survey (4 inner 70 m views), then 40 m lawnmower",
    "survey_outer": "survey (4 covering 70 m views), then 40 m lawnmower",
    "viewset": "view set optimised on training scenes (AF1 gain)",
    "viewset_per_s": "view set optimised on training scenes (AF1 gain per second)",
    "descend_rule": "the rule: survey at 70 m, then descend over the highest fused p",
    "map_policy": "ours: learned wide-area policy (its own fusion)",
    "rule_learned": "the rule on the learned aggregation",
    "entropy_per_s": "greedy expected information per second",
    "random": "random viewpoints",
    "rule_oracle": "the rule, oracle perception (bound)",
    "label_greedy": "label-peeking greedy (bound)",
    "hindsight": "hindsight-best route search (bound)",
}
BOUNDS = ("rule_oracle", "label_greedy", "hindsight")
RULE = "descend_rule"
HINDSIGHT_BEAM = 4


def oracle_perception(cache: ViewCache) -> ViewCache:
    """The cache as a perfect detector of visible people would give it: p = 1 - 1e-3 where the cell is
    occupied and its person shows a pixel in the view, else 1e-3."""
    if cache.person_px is None:
        raise UavsearchError("oracle perception needs person_px in the view cache (rebuild it)")
    seen = cache.occupancy[:, None, :] & (cache.person_px > 0)
    p = torch.where(seen, 1 - 1e-3, 1e-3)
    return cache._replace(log_probs=torch.stack([(1 - p).log(), p.log()], -1).float())


@torch.no_grad()
def run_rows(cache: ViewCache, config: SearchConfig, agents: dict[str, tuple[Agent, int]],
             seeds: int = 1) -> dict[str, dict]:
    """{key: {"acc", "f1": (seeds, S*E, T'), "views": (S*E*seeds,), "flight_s", "scenes": S}}; agents map to
    (agent, episodes per scene); stochastic rows (episodes > 1) run `seeds` seeds."""
    out = {}
    for key, (agent, episodes) in agents.items():
        rows = np.repeat(np.arange(cache.num_scenes), episodes)
        acc, f1, views, flight, by_view, by_s = [], [], [], [], [], []
        for s in range(seeds if episodes > 1 else 1):
            ep = run_search(CachedViews(cache, rows, config), agent, generator=make_generator(s, cache.occupancy.device))
            sc = score_episode(ep)
            acc.append(sc.acc[:, -1:])
            f1.append(sc.f1[:, -1:])
            views.append(ep.taken.sum(1).cpu().numpy() if ep.taken is not None else np.full(len(rows), ep.maps.shape[1]))
            flight.append(ep.flight_s.cpu().numpy() if ep.flight_s is not None else flight_seconds(config, ep.lattice_idx))
            by_view.append(sc.f1.mean(0))
            by_s.append(f1_by_seconds(config, ep.lattice_idx, sc.f1, curve_seconds(config)).mean(0))
        out[key] = {"acc": np.stack(acc), "f1": np.stack(f1), "views": np.concatenate(views),
                    "flight_s": np.concatenate(flight), "scenes": cache.num_scenes,
                    "f1_by_view": np.mean(_pad_last(by_view), 0), "f1_by_s": np.mean(by_s, 0)}
    return out


def _pad_last(curves: list[np.ndarray]) -> list[np.ndarray]:
    """Seeds whose longest episode took fewer views hold their final F1 to the longest seed's length (under a
    time budget each seed's episodes may end after a different number of views)."""
    n = max(len(c) for c in curves)
    return [np.concatenate([c, np.repeat(c[-1:], n - len(c))]) for c in curves]


CURVE_STEP_S = 5.0  # Fig. 6's time axis: the map's F1 every 5 s of flight


def curve_seconds(config: SearchConfig) -> np.ndarray:
    """Fig. 6's time axis: 0 to the time budget (or 300 s of flight without one)."""
    return np.arange(0.0, float(config.budget_s or 300.0) + 1e-9, CURVE_STEP_S)


def arrival_seconds(config: SearchConfig, lattice_idx) -> np.ndarray:
    """(B, T') seconds of flight before each view of each episode (0 for the start view; an ended episode's
    later columns repeat its last viewpoint, so its clock stops there)."""
    idx = lattice_idx.cpu().numpy() if isinstance(lattice_idx, torch.Tensor) else np.asarray(lattice_idx)
    legs = config.lattice.flight_time_s[idx[:, :-1], idx[:, 1:]]
    return np.concatenate([np.zeros((len(idx), 1)), legs.cumsum(1)], 1)


def f1_by_seconds(config: SearchConfig, lattice_idx: torch.Tensor, f1: np.ndarray, seconds: np.ndarray) -> np.ndarray:
    """(B, len(seconds)) each episode's F1 after the views it had taken by each time."""
    arrive = arrival_seconds(config, lattice_idx)
    last = (arrive[:, None, :] <= seconds[None, :, None] + 1e-9).sum(-1) - 1  # (B, len(seconds)), >= 0: view 0 at 0 s
    return np.take_along_axis(f1, last, 1)


def flight_seconds(config: SearchConfig, lattice_idx) -> np.ndarray:
    """(B,) seconds of flight of each episode's views."""
    return arrival_seconds(config, lattice_idx)[:, -1]


# What `--wide-fusion auto` chooses among on the validation scenes. Bayes' prior is the p a view must exceed to
# count as evidence for a person, so it decides how fast a cell's mild false alarms pile up over many views.
FUSION_CANDIDATES = ("bayes:0.05", "bayes:0.1", "bayes:0.2", "bayes:0.3", "bayes:0.5", "average")
def choose_fusion(val: ViewCache, config: SearchConfig, candidates=FUSION_CANDIDATES) -> tuple[Fusion, dict[str, float]]:
    """The candidate (a spec or a Fusion) with the best mean validation AF1 over the hand-made fixed routes and
    the rule (the rows that need no training scenes), and every candidate's score: chosen on validation, the
    same for every row."""
    fusions = [c if isinstance(c, Fusion) else make_fusion(c) for c in candidates]
    scores = {}
    for fusion in fusions:
        agents = {k: (_agent(fusion, k, config), 1) for k in (*FIXED[:4], RULE)}
        res = run_rows(val, config, agents)
        scores[fusion_name(fusion)] = float(np.mean([r["f1"][:, :, -1].mean() for r in res.values()]))
    names = list(scores)
    best = max(range(len(fusions)), key=lambda i: (scores[names[i]], -i))
    return fusions[best], scores


def _agent(fusion: Fusion, policy: str, config: SearchConfig) -> Agent:
    """`policy` with `fusion` (built under a fusion any name builds: these policies do not depend on it)."""
    return build_agent("average", policy, config).agent._replace(fusion=fusion)


def _route_agent(fusion: Fusion, routes) -> Agent:
    return Agent(fusion, RoutePolicy(routes))


def fixed_agents(config: SearchConfig, fusion: Fusion, train: ViewCache) -> tuple[dict[str, Agent], dict[str, list]]:
    """The fixed-route rows and their routes (the view sets searched on the training cache)."""
    agents = {k: _agent(fusion, k, config) for k in FIXED[:4]}
    routes = {k: a.policy.routes[0].tolist() for k, a in agents.items()}
    for key, per_s in (("viewset", False), ("viewset_per_s", True)):
        routes[key] = greedy_view_set(train, fusion, config, per_second=per_s)
        agents[key] = _route_agent(fusion, routes[key])
    return agents, routes


def rule_agent(fusion: Fusion, config: SearchConfig, variant: str) -> Agent:
    return Agent(fusion, rule_policy(config, variant))


def evaluate_condition(caches: dict[str, ViewCache], config: SearchConfig, fusion: Fusion, episodes: int,
                       seeds: int, resamples: int = 10_000, bootstrap_seed: int = 0,
                       learned: Agent | None = None) -> dict:
    """Every row of one budget: routes fixed on train, the best fixed route and the rule's variant chosen on
    val, all scored on test; `learned`: the learned policy's row too."""
    fixed, routes = fixed_agents(config, fusion, caches["train"])
    val = run_rows(caches["val"], config, {k: (a, 1) for k, a in fixed.items()})
    val_af1 = {k: float(r["f1"][:, :, -1].mean()) for k, r in val.items()}
    best = max(FIXED, key=lambda k: (val_af1[k], -FIXED.index(k)))
    variant, variant_af1 = choose_rule(caches["val"], config, fusion)
    test = caches["test"]
    agents = {**{k: (a, 1) for k, a in fixed.items()},
              RULE: (rule_agent(fusion, config, variant), 1),
              "entropy_per_s": (_agent(fusion, "entropy_per_s", config), 1),
              "random": (_agent(fusion, "random", config), episodes)}
    rule_learned = None
    if learned is not None:
        agents[LEARNED] = (learned, 1)
        if learned.fusion.trainable:  # the learned aggregation: the rule on it too, its variant chosen on val
            rule_learned = choose_rule(caches["val"], config, learned.fusion)
            agents[RULE_LEARNED] = (rule_agent(learned.fusion, config, rule_learned[0]), 1)
    res = run_rows(test, config, agents, seeds)
    res.update({"rule_oracle": run_rows(oracle_perception(test), config,
                                        {"rule_oracle": (rule_agent(OracleFusion(), config, variant), 1)})["rule_oracle"]})
    greedy = label_routes(test, fusion, config, beam=1)
    beam = label_routes(test, fusion, config, beam=HINDSIGHT_BEAM)
    both = run_rows(test, config, {"g": (_route_agent(fusion, greedy), 1), "b": (_route_agent(fusion, beam), 1)})
    res["label_greedy"] = both["g"]
    pick = torch.as_tensor(scene_af1(both["b"]) >= scene_af1(both["g"]))
    L = max(greedy.shape[1], beam.shape[1])
    pad = lambda r: torch.nn.functional.pad(r, (0, L - r.shape[1]), value=-1)  # noqa: E731
    res["hindsight"] = run_rows(test, config, {"h": (_route_agent(fusion, torch.where(
        pick[:, None], pad(beam), pad(greedy))), 1)})["h"]
    paired = paired_differences(res, (best, RULE, LEARNED), labels_of(res), resamples, bootstrap_seed)
    return {"results": res, "paired": paired, "best_fixed": best, "val_af1": val_af1, "routes": routes,
            "rule_variant": variant, "rule_variant_af1": variant_af1,
            "rule_learned_variant": rule_learned[0] if rule_learned else None,
            "rule_learned_variant_af1": rule_learned[1] if rule_learned else None,
            "scenes": {k: c.num_scenes for k, c in caches.items()}}


LEARNED = "map_policy"
RULE_LEARNED = "rule_learned"
STACK_LABELS = {RULE: "the hand-made stack: the rule (survey at 70 m, then descend over the highest fused p) on the "
                      "hand-made fusion",
                LEARNED: "the learned stack: learned wide-area policy on its learned aggregation"}


def labels_of(results: dict) -> dict[str, str]:
    """The rows' names: where the learned policy carries a learned aggregation (the rule on it is then a row),
    the rule's and the learned policy's rows are the two stacks."""
    return {**LABELS, **(STACK_LABELS if RULE_LEARNED in results else {})}


def row_order(results: dict | None = None) -> list[str]:
    """Table III's rows in order (the learned policy's, and the rule on its learned aggregation, where `results`
    has them)."""
    learned = [k for k in (LEARNED, RULE_LEARNED) if results is None or k in results]
    return [*FIXED, RULE, *learned, "entropy_per_s", "random", *BOUNDS]


def _trained_family(path) -> str | None:
    """The scene family a learned wide-area policy's checkpoint was trained on, as `wide`'s (None: not said)."""
    fam = (load_search_model(path)[2].get("args") or {}).get("family")
    return f"`{fam}`'s" if fam else None


def table_rows(family: str, name: str, cond: dict) -> list[dict]:
    """table3.csv rows of one family and budget."""
    out = []
    res, best = cond["results"], cond["best_fixed"]
    labels = labels_of(res)
    for key in row_order(res):
        r = res[key]
        row = {"setting": family, "budget": name, "fusion": cond.get("fusion", ""), "key": key, "method": labels[key],
               "aacc": float(r["acc"][:, :, -1].mean() * 100), "af1": float(r["f1"][:, :, -1].mean()),
               "views": float(r["views"].mean()), "flight_s": float(r["flight_s"].mean()),
               "scenes": int(r["scenes"]), "best_fixed": key == best, "val_af1": cond["val_af1"].get(key, float("nan"))}
        for ref, tag in ((best, "vs_best_fixed"), (RULE, "vs_rule"), (LEARNED, "vs_learned")):
            q = next((p for p in cond["paired"] if p["key"] == key and p["reference"] == ref), None)
            nan = float("nan")
            row.update({f"{tag}": q["diff"] if q else nan, f"{tag}_low": q["ci_low"] if q else nan,
                        f"{tag}_high": q["ci_high"] if q else nan})
        out.append(row)
    return out


def _ci(row: dict, tag: str) -> str:
    if not np.isfinite(row[tag]):
        return "(reference)"
    return f"{row[tag]:+.3f} [{row[f'{tag}_low']:+.3f}, {row[f'{tag}_high']:+.3f}]"


def table_lines(family: str, name: str, cond: dict, rows: list[dict]) -> list[str]:
    sc = cond["scenes"]
    chosen = ""
    if cond.get("fusion_scores"):
        chosen = (f" Fusion **{cond['fusion']}**, chosen on the validation scenes by the mean AF1 of the hand-made "
                  "fixed routes and the rule: " + ", ".join(f"{k} {v:.3f}" for k, v in cond["fusion_scores"].items())
                  + ".")
    elif cond.get("fusion"):
        chosen = f" Fusion {cond['fusion']}."
    if cond.get("rule_variant_af1"):
        chosen += (f" The rule's survey (70 m views), the fused p below which it keeps surveying and whether it "
                   f"weighs descents per second of flight, chosen on the validation scenes: **{cond['rule_variant']}** ("
                   + ", ".join(f"{k} {v:.3f}" for k, v in cond["rule_variant_af1"].items()) + ").")
    if cond.get("learned"):
        chosen += f" The learned policy: {cond['learned']}, trained on {cond.get('learned_on') or 'its'} training scenes."
    if cond.get("rule_learned_variant"):
        chosen += (f" The rule on the learned aggregation flies its variant chosen on the validation scenes with that "
                   f"fusion, {cond['rule_learned_variant']} ("
                   + ", ".join(f"{k} {v:.3f}" for k, v in cond["rule_learned_variant_af1"].items()) + ").")
    learned = LEARNED in cond["results"]
    lines = [f"### {family}, {name}", "",
             f"{sc['test']} test scenes; fixed view sets searched on {sc['train']} training scenes, the best fixed route "
             f"chosen on {sc['val']} validation scenes: **{LABELS[cond['best_fixed']]}**.{chosen}", "",
             "| method | Aacc (%) | AF1 | views | flight (s) | Δ AF1 vs best fixed [95% CI] | Δ AF1 vs the rule [95% CI] |"
             + (" Δ AF1 vs the learned policy [95% CI] |" if learned else ""),
             "|---|---|---|---|---|---|---|" + ("---|" if learned else "")]
    for r in rows:
        name_ = r["method"] + (" (best fixed)" if r["best_fixed"] else "")
        lines.append(f"| {name_} | {r['aacc']:.2f} | {r['af1']:.3f} | {r['views']:.1f} | {r['flight_s']:.0f} | "
                     f"{_ci(r, 'vs_best_fixed')} | {_ci(r, 'vs_rule')} |" + (f" {_ci(r, 'vs_learned')} |" if learned
                                                                            else ""))
    return lines + [""]


def write_table3(out: Path, rows: list[dict], paired: list[dict], lines: list[str], meta: dict) -> Path:

    out.mkdir(parents=True, exist_ok=True)
    write_csv(out / "table3.csv", rows)
    if paired:
        write_csv(out / "table3_paired.csv", paired)
    head = ["# Table III (our testbed): the wide-area search, test scenes", "",
            f"Fusion {meta['fusion']} for every row but the oracle ones; perception {meta['perception']} (tag "
            f"{meta['tag']}, {meta['altitudes']}); random: {meta['episodes']} episodes per scene x {meta['seeds']} "
            f"seeds. Δ: per-scene final AF1 minus the reference's, mean over scenes [95% bootstrap interval over "
            f"scenes]. Views and flight: means per episode (the start view is free). Fig. 6 (`fig6.png` beside this "
            "file): mean AF1 against views under the view budget and against seconds of flight under the time "
            "budget, for the best fixed route, the rule, ours, entropy per second, random and the hindsight bound.",
            ""]
    md = out / "table3.md"
    md.write_text("\n".join(head + lines + [f"{meta['seconds']:.0f} s"]) + "\n")
    return md


FIG6_ROWS = ("best_fixed", RULE, LEARNED, RULE_LEARNED, "entropy_per_s", "random", "hindsight")
FIG6_SHORT = {RULE: "the rule (hand-made stack)", LEARNED: "ours (learned stack)",
              RULE_LEARNED: "the rule on the learned aggregation",
              "entropy_per_s": "entropy per second", "random": "random", "hindsight": "hindsight-best (bound)"}


def fig6(conds: dict, out: Path) -> Path:
    """Fig. 6 for the wide families: mean test AF1 against views under the view budget and against seconds of
    flight under the time budget, one row of panels per family (the curves run_rows keeps)."""
    plt = pyplot()
    fams = list(dict.fromkeys(f for f, _ in conds))
    fig, axes = plt.subplots(len(fams), 2, figsize=(11, 6.2 * len(fams)), squeeze=False, layout="constrained")
    colours = dict(zip(FIG6_ROWS, ("tab:gray", "tab:blue", "tab:red", "tab:purple", "tab:green", "tab:olive",
                                   "black")))
    for i, fam in enumerate(fams):
        for j, (name, cond) in enumerate((n, c) for (f, n), c in conds.items() if f == fam):
            ax, res = axes[i, j], cond["results"]
            timed = cond["config"].budget_s is not None
            for key in FIG6_ROWS:
                row = cond["best_fixed"] if key == "best_fixed" else key
                if row not in res:
                    continue
                y = res[row]["f1_by_s"] if timed else res[row]["f1_by_view"]
                x = curve_seconds(cond["config"]) if timed else np.arange(1, len(y) + 1)
                label = f"best fixed: {LABELS[row]}" if key == "best_fixed" else FIG6_SHORT[key]
                ax.plot(x, y, "--" if key == "hindsight" else "-", color=colours[key], lw=2.2 if key in (RULE, LEARNED)
                        else 1.4, marker=None if timed else "o", ms=4, label=label)
            ax.set_xlabel("seconds of flight" if timed else "views (the first is the start view)")
            ax.set_ylabel("AF1 (mean over test scenes)")
            ax.set_title(f"{fam}, {name}: {cond['scenes']['test']} test scenes", fontsize=10)
            ax.set_ylim(0, 1)
            ax.grid(alpha=0.3)
            # below the panel: inside it the legend hid the bound's and the learned rows' curves
            ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.14), frameon=False)
    return save_figure(fig, Path(out) / "fig6.png")


def perception_of(args, family: str) -> str:
    """The net a family is evaluated with: --perception, else the family's shipped one."""
    return args.perception or str(shipped_perception(family))


def family_caches(args, family: str) -> dict[str, ViewCache]:
    """test, val and train caches of a family (the first args.wide_<part>_scenes scenes of each)."""
    net, _ = load_perception(perception_of(args, family))
    split = args.split or setting_params(family).split
    ex = Executor.from_args(args)
    limits = {"test": args.wide_test_scenes, "val": args.wide_val_scenes, "train": args.wide_train_scenes}
    return {part: get_view_cache(net, family, split, part, cache_dir=args.cache_dir, progress=args.progress,
                                 executor=ex, features=False, limit=limits[part])
            for part in ("test", "val", "train")}


def eval_wide(args, families: list[str], caches: dict | None = None) -> dict:
    """Table III for the families into args.out; `caches` ({family: {part: ViewCache}}) skips building them."""
    auto = args.wide_fusion == "auto"
    if not auto and calibrated_gamma(args.wide_fusion) is None:  # a bad spec fails before any cache is built
        make_fusion(args.wide_fusion)
    t0 = time.perf_counter()
    rows, paired, lines, conds = [], [], [], {}
    tag = ""
    for fam in families:
        cs = caches[fam] if caches is not None else family_caches(args, fam)
        cs = {part: to_device(c, resolve_device(getattr(args, "device", "auto"))) for part, c in cs.items()}
        tag = cs["test"].perception_tag
        config = cs["test"].config
        for name, cfg in wide_budgets(config).items():
            if auto:
                candidates = (*FUSION_CANDIDATES, *calibrated_candidates(cs["train"]))
                chosen, scores = choose_fusion(cs["val"], cfg, candidates)
            else:
                chosen, scores = make_fusion(args.wide_fusion, cs["train"]), {}
            path = wide_checkpoint(BUDGETS[list(wide_budgets(config)).index(name)], getattr(args, "wide_policy_dir", None))
            learned = load_wide_agent(path, cfg, device=cs["test"].occupancy.device)
            cond = evaluate_condition(cs, cfg, chosen, args.episodes, args.seeds, args.bootstrap,
                                      args.bootstrap_seed, learned)
            cond.update(fusion=fusion_name(chosen), fusion_scores=scores,
                        learned=f"{display_path(path)} ({fusion_name(learned.fusion)})" if learned else None,
                        learned_on=_trained_family(path) if learned else None)
            conds[(fam, name)] = {**cond, "config": cfg}
            r = table_rows(fam, name, cond)
            rows += r
            paired += [{"setting": fam, "budget": name, **p} for p in cond["paired"]]
            lines += table_lines(fam, name, cond, r)
            print(f"uavsearch: {fam}, {name}: done ({time.perf_counter() - t0:.0f} s)", flush=True)
    net_path = perception_of(args, families[0])
    net = load_perception(net_path)[0]
    altitudes = ("trained across altitudes" if net.reads_altitude else "a detector: boxes, no altitude input"
                 if getattr(net, "kind", "") == "detector" else "trained at 70 m only")
    meta = {"altitudes": altitudes, "fusion": "chosen on validation per family and budget" if auto
            else args.wide_fusion, "perception": display_path(net_path), "tag": tag,
            "episodes": args.episodes, "seeds": args.seeds, "seconds": time.perf_counter() - t0}
    md = write_table3(Path(args.out), rows, paired, lines, meta)
    fig = fig6(conds, Path(args.out))
    print(md.read_text())
    print(f"wrote {display_path(md)} and {display_path(fig)}")
    return {"rows": rows, "paired": paired, "conditions": conds, "table": md, "figure": fig}


__all__ = ["eval_wide", "evaluate_condition", "oracle_perception", "run_rows", "table_rows"]
