"""The wide-area search's learned policy (map_policy.MapPolicyNet): DAgger from a label-peeking teacher, then
REINFORCE, one net per budget of Table III (T = 8 views, or the family's seconds of flight).

CleanRL-style: `Args`, then `train(args)` does everything (the loop is train/dagger.py's, shared with the
reactive policy). Perception is FROZEN (its view caches), and so is the
fusion: the calibrated fusion (`--fusion calibrated:GAMMA`, fitted on the first `calibration_scenes` training
scenes, as Table III fits it) or any fusion a name builds. Every episode is a few gathers (run_search on
CachedViews).

1. DAgger (`dagger_iterations`): roll out a mixture, per episode and step the teacher (`--teacher labels`:
   `LabelLookahead`, for each viewpoint it may take, the fused map after that view, scored on the labels: the
   change of N_tp - N_fp plus a tenth of the change of the summed p of the occupied cells, which breaks the ties
   of views that flip no cell; per second of flight under a time budget. `--teacher rule`: the rule's variant
   chosen on validation, a warm start at the rule) with probability beta (1, then times `beta_decay`), else
   the net (sampled); keep every (state, teacher move); fit the net by cross-entropy on the aggregate.
   `--imitate gains` (label teacher only) fits instead the net's score of every allowed viewpoint to the
   teacher's gain for it (least squares on both less their mean over the state's viewpoints, the gains over
   their spread on the first aggregate), and the net rolls out its argmax: the label teacher's move hangs on
   labels no state shows, so its argmax is hard to imitate (13% agreement), but the gain's mean given the
   state is what least squares learns, and the argmax of that expected gain is the greedy policy that does
   not peek.
2. REINFORCE (`pg_iterations`), reward per view: the change of N_tp - N_fp of the fused map (its sum is the
   final map's N_tp - N_fp, what F1 counts). Each move's return to go is baselined by the mean return to go of
   the OTHER episodes of the same scene in the batch at the same step (leave-one-out: scenes differ far more
   than moves, and a fixed route's return would not know how this episode got here). Advantages normalised;
   an entropy bonus decays linearly; an imitation term keeps the teacher's lessons.
3. Selection: after every DAgger iteration and every `eval_every` REINFORCE iterations, the net's argmax
   viewpoints on the validation scenes; the checkpoint kept has the best AF1 minus the rule's
   (wide_policies.DescendRule, its variant chosen on the same validation scenes as Table III chooses it). The
   same margin on `train_eval_scenes` training scenes is logged beside it: a net that memorises its scenes
   shows a training margin its validation one lacks. With `--init CHECKPOINT` the run starts from that map
   policy's net (say, one trained on another fusion) and validates it before any step: a fine-tune keeps the
   start where no step beats it.

Output: runs/<name>__<seed>__<unix time>/ with args.json, metrics.csv, learning_curve.png, model.pt (the net and
its fusion) and summary.json. `--out PATH` or `--ship` (models/search_wide_<budget>_map.pt) copies it.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch.nn import functional as F

from uavsearch.cli_args import add_dataclass_args, dataclass_from_args, opt
from uavsearch.devices import resolve_device, to_device
from uavsearch.errors import UavsearchError, run_command
from uavsearch.paths import display_path
from uavsearch.viz import pyplot

from ..config import SearchConfig, config_to_dict, wide_budgets
from ..data.view_cache import ViewCache, get_view_cache
from ..agents import load_wide_agent, make_fusion
from ..fusion import Fusion
from ..checkpoints import shipped_perception, wide_checkpoint
from ..map_policy import BUDGETS, MASKED, MapPolicyConfig, MapPolicyNet
from ..perception import load_perception
from ..policy import ArgmaxPolicy, save_search_model
from ..search_loop import Agent, CachedViews, PolicyInput, classification_reward
from ..scoring import evaluate_agent
from ..wide_policies import argmax_allowed, candidates, choose_rule, route_views, rule_policy
from .dagger import DaggerPolicy, ReinforceLoss, check_dagger_args, dagger_reinforce
from .runs import (MetricsCsv, RunArgs, copy_checkpoint, finish_curves, imitation_panel, returns_to_go, start_run,
                   start_training)

IMITATE = ("moves", "gains")


def budget_config(config: SearchConfig, budget: str) -> SearchConfig:
    """The family's config under one of Table III's budgets (evaluate.wide.conditions, by its short name)."""
    return list(wide_budgets(config).values())[BUDGETS.index(budget)]


@dataclass
class Args(RunArgs):
    family: str = opt("wide", "scene family (wide | wide-uniform)")
    budget: str = opt("240", "Table III's budget: 8 (views) or 240 (seconds of flight)", choices=BUDGETS)
    perception: str | None = opt(None, "frozen perception (default the family's shipped net)")
    fusion: str = opt("calibrated:0.75", "fusion: calibrated:GAMMA (fitted on the calibration scenes) or a name")
    train_scenes: int = opt(500, "training scenes, the first N of the part (views are rendered where missing, resumable)")
    val_scenes: int = opt(50, "validation scenes (selection)")
    calibration_scenes: int = opt(20, "training scenes the calibrated fusion is fitted on (Table III's)")
    train_eval_scenes: int = opt(50, "training scenes the training margin is measured on")
    out: str | None = opt(None, "also copy the best checkpoint here (it always stays in the run directory)")
    ship: bool = opt(False, "copy the best checkpoint over the shipped models/search_wide_<budget>_map.pt")
    init: str | None = opt(None, "start from this map policy checkpoint's net (its architecture too) instead of a fresh "
                                 "one, validated before any step, so a fine-tune on another fusion keeps the start "
                                 "where no step beats it")
    name: str | None = opt(None, "run name (default map_<family>_<budget>)")
    seed: int = opt(0, "seeds random, numpy, torch and the episode sampling")
    # 1. DAgger
    teacher: str = opt("rule", "DAgger's teacher: labels (LabelLookahead: peeks at the labels) or rule (the rule's "
                                 "variant chosen on validation: a warm start at the rule for REINFORCE to improve)",
                       choices=("labels", "rule"))
    imitate: str = opt("moves", "what DAgger fits: moves (cross-entropy on the teacher's viewpoint) or gains (the "
                                "label teacher's gain of every viewpoint, least squares; --teacher labels)",
                       choices=IMITATE)
    dagger_iterations: int = opt(4, "DAgger iterations (rollout, aggregate, fit)")
    dagger_episodes: int = opt(128, "episodes rolled out per DAgger iteration (scenes drawn with replacement)")
    beta_decay: float = opt(0.5, "teacher probability: 1 in the first iteration, times this per iteration")
    dagger_epochs: int = opt(8, "passes over the aggregate per DAgger iteration")
    batch_size: int = opt(64, "states per cross-entropy minibatch")
    lr: float = opt(1e-3, "Adam, imitation")
    # 2. REINFORCE
    pg_iterations: int = opt(150, "policy-gradient iterations after DAgger")
    scenes_per_batch: int = opt(16, "training scenes per policy-gradient batch (drawn with replacement)")
    episodes_per_scene: int = opt(4, "episodes per scene per policy-gradient batch (>= 2: the baseline)")
    lr_pg: float = opt(3e-4, "Adam, policy gradient")
    weight_decay: float = opt(1e-5, "Adam L2")
    entropy_start: float = opt(0.01, "entropy bonus at the first policy-gradient iteration")
    entropy_end: float = opt(0.0, "entropy bonus at the last (linear in between)")
    imitation_coef: float = opt(0.1, "weight of the cross-entropy on the DAgger aggregate during REINFORCE")
    # architecture (map_policy.MapPolicyConfig)
    channels: int = opt(32, "conv channels")
    conv_layers: int = opt(4, "3x3 conv layers")
    hidden: int = opt(64, "per-viewpoint head width")
    eval_every: int = opt(15, "policy-gradient iterations between validations")


class TrainResult(NamedTuple):
    run_dir: Path
    checkpoint: Path
    best: dict  # validation metrics of the saved checkpoint
    table: list[dict]  # validation rows: the rule, the policy, the teacher
    seconds: float


def check_args(args: Args) -> None:
    check_dagger_args(args, "channels", "conv_layers", "hidden", "val_scenes", "calibration_scenes",
                      "train_eval_scenes")
    if args.episodes_per_scene < 2:
        raise UavsearchError("--episodes-per-scene must be at least 2 (each episode's baseline is the others')")
    if args.teacher not in ("labels", "rule"):
        raise UavsearchError(f"--teacher must be labels or rule, got {args.teacher!r}")
    if args.imitate not in IMITATE:
        raise UavsearchError(f"--imitate must be one of {', '.join(IMITATE)}, got {args.imitate!r}")
    if args.imitate == "gains" and args.teacher != "labels":
        raise UavsearchError("--imitate gains fits the label teacher's gains: it needs --teacher labels")
    if args.budget not in BUDGETS:
        raise UavsearchError(f"--budget must be one of {', '.join(BUDGETS)}")


# --------------------------------------------------------------------------------------------------
# The teacher


def repeat_state(x, k: int):
    """A fusion state (tensors, tuples or NamedTuples of them, None) with each batch row repeated k times."""
    if x is None:
        return None
    if isinstance(x, torch.Tensor):
        return x.repeat_interleave(k, 0)
    if isinstance(x, tuple):
        parts = (repeat_state(f, k) for f in x)
        return type(x)(*parts) if hasattr(x, "_fields") else tuple(parts)
    return x


class LabelLookahead:
    """DAgger's teacher: the allowed viewpoint whose view most improves the fused map on the labels (module
    docstring), per second of flight under a time budget; ties: the nearer. Follows one batch of episodes step
    by step (it keeps the fusion state of each episode's views, so a step costs one view per candidate)."""

    def __init__(self, cache: ViewCache, rows, fusion: Fusion, config: SearchConfig, chunk: int = 8):
        self.cache, self.fusion, self.config, self.chunk = cache, fusion, config, chunk
        dev = cache.occupancy.device
        self.rows = torch.as_tensor(rows if isinstance(rows, torch.Tensor) else np.asarray(rows), dtype=torch.long,
                                    device=dev).reshape(-1)
        self.labels = cache.occupancy[self.rows]
        self.cost = config.lattice.flight_time_t.float().to(dev)
        self.timed = config.budget_s is not None
        self.state, self.fused, self.seen = None, None, 0
        self.features = "cell_features" in fusion.needs  # a fusion that reads them gets the views' cell features

    def _follow(self, inp: PolicyInput) -> None:
        """Bring the kept fusion state up to the episode's views so far."""
        t = inp.view_positions.shape[1]
        if t < self.seen:
            raise UavsearchError("the teacher follows one batch of episodes forward; build a new one per batch")
        for j in range(self.seen, t):
            self.state, self.fused = self.fusion.update(self.state, route_views(
                self.cache, self.rows, inp.view_positions[:, j:j + 1], self.features))
        self.seen = t

    @torch.no_grad()
    def gains(self, inp: PolicyInput) -> torch.Tensor:
        """(B, P) what each viewpoint's view would add (-inf where it may not be taken)."""
        self._follow(inp)
        allowed = candidates(inp)
        B, P = allowed.shape
        occ = self.labels.float()
        now = classification_reward(self.fused, self.labels).float() + 0.1 * (self.fused * occ).sum(-1)
        out = torch.full((B, P), -np.inf, device=occ.device)
        for c0 in range(0, P, self.chunk):
            cs = [c for c in range(c0, min(c0 + self.chunk, P)) if bool(allowed[:, c].any())]
            if not cs:
                continue
            k = len(cs)
            pos = torch.tensor(cs, device=occ.device).repeat(B)  # (B*k,) episode-major
            rows = self.rows.repeat_interleave(k)
            _, fused = self.fusion.update(repeat_state(self.state, k), route_views(self.cache, rows, pos[:, None],
                                                                                   self.features))
            lab = self.labels.repeat_interleave(k, 0)
            after = classification_reward(fused, lab).float() + 0.1 * (fused * lab.float()).sum(-1)
            out[:, cs] = after.reshape(B, k) - now[:, None]
        gain = out
        if self.timed:
            gain = gain / self.cost[inp.lattice_idx].clamp(min=1.0)
        return torch.where(allowed, gain, torch.full_like(gain, -np.inf))

    def choose(self, gains: torch.Tensor, inp: PolicyInput) -> torch.Tensor:
        """The teacher's move given its gains: the highest, ties to the nearer."""
        return argmax_allowed(gains - 1e-6 * self.cost[inp.lattice_idx], candidates(inp))

    @torch.no_grad()
    def act(self, inp: PolicyInput, generator=None):
        return self.choose(self.gains(inp), inp), None, None


def rollout_worth_learning(inp: PolicyInput, mask: torch.Tensor, a_teacher: torch.Tensor) -> torch.Tensor:
    """(B,) bool: the decisions DAgger keeps. An episode with nothing left to take has ended, and a teacher's move
    the net may not make (the rule flies its survey by step, also over a viewpoint the net visited): nothing to
    learn there."""
    return candidates(inp).any(1) & mask.gather(1, a_teacher[:, None])[:, 0]


def half_planes(state: tuple[torch.Tensor, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """The aggregate keeps the map planes in float16 (the viewpoint features as they are)."""
    planes, vp = state
    return planes.half(), vp


def imitation_loss(net: MapPolicyNet, planes, vps, masks, targets, gain_scale: float | None = None
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """The net against its teacher, and their agreement (the same argmax). Targets (B,) the teacher's moves:
    cross-entropy of the masked logits. Targets (B, P) the teacher's gains (-inf: not allowed): mean squared
    error of the allowed viewpoints' scores against the gains / gain_scale, both less their mean over the
    state's allowed viewpoints (what a state is worth as a whole, e.g. late in an episode, decides no move;
    without it the fit spends itself there and ranks the best views no better than chance)."""
    logits = net(planes.float(), vps, masks)
    if targets.dim() == 1:
        return F.cross_entropy(logits, targets), (logits.argmax(-1) == targets).float().mean()
    ok = torch.isfinite(targets)
    n = ok.sum(1, keepdim=True).clamp(min=1)

    def centred(x):
        x = torch.where(ok, x, torch.zeros_like(x))
        return x - x.sum(1, keepdim=True) / n

    loss = F.mse_loss(centred(logits)[ok], centred(targets / gain_scale)[ok])
    agree = logits.masked_fill(~ok, MASKED).argmax(-1) == targets.argmax(-1)
    return loss, agree.float().mean()


def leave_one_out(G: torch.Tensor, per_scene: int) -> torch.Tensor:
    """G (S*E, L) -> each episode's G minus the mean of the other E - 1 episodes of its scene."""
    g = G.reshape(-1, per_scene, G.shape[-1])
    return (g - (g.sum(1, keepdim=True) - g) / (per_scene - 1)).reshape(G.shape)


# --------------------------------------------------------------------------------------------------
# Training


@torch.no_grad()
def scene_f1(cache: ViewCache, config: SearchConfig, agent: Agent) -> np.ndarray:
    """(S,) each scene's final F1 under a deterministic agent, one episode a scene."""
    return evaluate_agent(cache, agent, 1, config=config).f1[:, -1]


def _caches(args: Args):
    net, _ = load_perception(args.perception or str(shipped_perception(args.family)))
    kw = dict(cache_dir=args.cache_dir, progress=args.progress, features=False)
    train = get_view_cache(net, args.family, "large", "train", limit=args.train_scenes, **kw)
    val = get_view_cache(net, args.family, "large", "val", limit=args.val_scenes, **kw)
    return train, val


def _plot(rows: list[dict], path: Path, title: str) -> None:
    plt = pyplot()
    ev = [r for r in rows if r["eval/val_af1"] is not None]
    pg = [r for r in rows if r["phase"] == "pg"]
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.8), layout="constrained")
    imitation_panel(ax[0], rows)
    ax[1].plot([r["iteration"] for r in ev], [r["eval/val_vs_rule"] for r in ev], "o-", label="validation")
    ax[1].plot([r["iteration"] for r in ev], [r["eval/train_vs_rule"] for r in ev], "s--", label="training scenes")
    ax[1].axhline(0.0, color="k", lw=0.6)
    ax[1].set_title("AF1 - the rule's AF1 (argmax)")
    ax[1].legend(fontsize=8)
    ax[2].set_title("REINFORCE")
    if pg:
        its = [r["iteration"] for r in pg]
        ax[2].plot(its, [r["charts/return"] for r in pg], lw=0.8, label="return (N_tp - N_fp)")
        ax[2].plot(its, [r["charts/entropy"] for r in pg], lw=0.8, label="entropy (nats)")
        ax[2].legend(fontsize=8)
    else:
        ax[2].text(0.5, 0.5, "no REINFORCE iterations", ha="center", va="center", transform=ax[2].transAxes)
    finish_curves(fig, ax, title, path)


def _init_net(path, config: SearchConfig) -> MapPolicyNet:
    """The net of a map policy checkpoint made for `config`'s search (load_wide_agent's checks, one line each)."""
    agent = load_wide_agent(path, config, where="--init, a policy for another search: ")
    if agent is None:
        raise UavsearchError(f"--init {path}: no such file")
    return agent.policy.net


def train(args: Args, caches=None) -> TrainResult:
    """Train the map policy; `caches` = (train, val) ViewCaches skips loading perception (tests)."""
    check_args(args)
    t_start = time.perf_counter()
    device = resolve_device(args.device)
    gen = start_training(args.threads, args.seed, device)
    train_cache, val_cache = (to_device(c, device) for c in (caches if caches is not None else _caches(args)))
    if train_cache.config.move_set != "any":
        raise UavsearchError(f"the map policy is the wide family's: {args.family!r} is not a wide family")
    config = budget_config(train_cache.config, args.budget)
    S = train_cache.num_scenes
    fusion = make_fusion(args.fusion, train_cache.subset(np.arange(min(args.calibration_scenes, S))))
    name = args.name or f"map_{args.family}_{args.budget}"
    run_dir = start_run(args, name, args.seed)
    net = MapPolicyNet(MapPolicyConfig(config_to_dict(config), channels=args.channels, conv_layers=args.conv_layers,
                                       hidden=args.hidden)).to(device) if args.init is None else \
        _init_net(args.init, config).to(device).train()
    train_eval = train_cache.subset(np.arange(min(args.train_eval_scenes, S)))
    variant, _ = choose_rule(val_cache, config, fusion)
    rule = Agent(fusion, rule_policy(config, variant))
    rule_val, rule_train = scene_f1(val_cache, config, rule), scene_f1(train_eval, config, rule)
    # the label-peeking teacher's row where it is the teacher (with the rule as teacher, the rule's row is): it
    # re-fuses every candidate view at every step, minutes on a fusion that reads cell features
    teacher_val = scene_f1(val_cache, config, Agent(fusion, LabelLookahead(
        val_cache, torch.arange(val_cache.num_scenes), fusion, config))) if args.teacher == "labels" else None

    gain_scale = None  # --imitate gains: the spread of the first aggregate's gains
    best, best_key = {}, -float("inf")
    ckpt = run_dir / "model.pt"
    metrics = MetricsCsv(run_dir / "metrics.csv")
    rows = metrics.rows
    meta = {"args": asdict(args), "fusion": getattr(fusion, "spec", fusion.name), "rule": variant,
            "perception_tag": train_cache.perception_tag, "search_config": config_to_dict(config)}

    def validate(row: dict, it: int) -> dict:
        nonlocal best, best_key
        net.eval()
        agent = Agent(fusion, ArgmaxPolicy(net))
        v, tr = scene_f1(val_cache, config, agent), scene_f1(train_eval, config, agent)
        net.train()
        row.update({"eval/val_af1": float(v.mean()), "eval/val_vs_rule": float((v - rule_val).mean()),
                    "eval/train_af1": float(tr.mean()), "eval/train_vs_rule": float((tr - rule_train).mean())})
        if row["eval/val_vs_rule"] > best_key:
            best_key = row["eval/val_vs_rule"]
            best = {"iteration": it, "phase": row["phase"], "val_af1": row["eval/val_af1"],
                    "val_vs_rule": row["eval/val_vs_rule"], "train_vs_rule": row["eval/train_vs_rule"]}
            save_search_model(ckpt, fusion, net, {**meta, "best": best})
        return {"val_vs_rule": f"{row['eval/val_vs_rule']:+.3f}", "best": f"{best_key:+.3f}"}

    def blank(it: int, phase: str) -> dict:
        return {"iteration": it, "phase": phase, "seconds": round(time.perf_counter() - t_start, 1),
                "losses/imitation": None, "losses/policy": None, "charts/teacher_agreement": None,
                "charts/beta": None, "charts/aggregate": None, "charts/return": None, "charts/entropy": None,
                "charts/entropy_coef": None, "charts/steps_per_s": None, "eval/val_af1": None,
                "eval/val_vs_rule": None, "eval/train_af1": None, "eval/train_vs_rule": None}

    def on_aggregate(data) -> None:
        nonlocal gain_scale
        Y = data[-1]
        if args.imitate == "gains" and gain_scale is None:
            gain_scale = float(Y[torch.isfinite(Y)].std()) or 1.0  # the scores' unit: the gains' spread
            meta["gain_scale"] = gain_scale

    E = args.episodes_per_scene

    def reinforce_loss(ep, rows_b) -> ReinforceLoss:
        """Leave-one-out baseline per scene; moves after a timed episode ended count for nothing."""
        G = returns_to_go(ep.maps.detach(), ep.labels, ep.revisit, r_re=0.0, shaped=True)
        live = (ep.taken[:, 1:] if ep.taken is not None else torch.ones_like(G, dtype=torch.bool)).float()
        adv = leave_one_out(G, E)
        adv = (adv - (adv * live).sum() / live.sum()) / (adv[live.bool()].std() + 1e-8)
        n = live.sum().clamp(min=1.0)
        return ReinforceLoss(-(ep.log_prob * adv * live).sum() / n, (ep.entropy * live).sum() / n,
                             {"charts/return": float(G[:, 0].mean())}, float(live.sum()))

    def teacher(rows_b):
        return LabelLookahead(train_cache, rows_b, fusion, config) if args.teacher == "labels" else rule.policy

    if args.init is not None:  # the start is a candidate too
        validate(row := blank(0, "init"), 0)
        metrics.log(row)
    dagger_reinforce(DaggerPolicy(
        net, fusion, views=lambda rows_b: CachedViews(train_cache, rows_b, config), teacher=teacher,
        imitation_loss=lambda batch, g: imitation_loss(net, *batch, gain_scale), reinforce_loss=reinforce_loss,
        validate=validate, blank=blank, gains=args.imitate == "gains", keep=rollout_worth_learning,
        pack=half_planes, on_aggregate=on_aggregate), args, S, gen, metrics.log, name)
    metrics.close()
    if args.plot:
        _plot(rows, run_dir / "learning_curve.png", f"{name}, seed {args.seed}")
    out = copy_checkpoint(ckpt, args.out, args.ship, wide_checkpoint(args.budget))
    seconds = time.perf_counter() - t_start
    table = [{"method": f"the rule ({variant})", "af1": float(rule_val.mean()), "vs_rule": 0.0},
             {"method": f"learned map policy (iteration {best.get('iteration')})", "af1": best.get("val_af1"),
              "vs_rule": best.get("val_vs_rule")}]
    if teacher_val is not None:
        table.append({"method": "label-peeking teacher (reads the labels)", "af1": float(teacher_val.mean()),
                      "vs_rule": float((teacher_val - rule_val).mean())})
    summary = {"best": best, "validation": table, "seconds": seconds, "checkpoint": display_path(out or ckpt),
               "scenes": {"train": S, "val": val_cache.num_scenes, "train_eval": train_eval.num_scenes}}
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=1))
    return TrainResult(run_dir, out or ckpt, best, table, seconds)


def format_table(table: list[dict], scenes: str) -> str:
    lines = [f"| method ({scenes}, argmax viewpoints) | AF1 | − the rule |", "|---|---|---|"]
    lines += [f"| {r['method']} | {r['af1']:.3f} | {r['vs_rule']:+.3f} |" for r in table]
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------------
# CLI


def add_train_map_parser(subparsers) -> None:
    """`uavsearch train map ...` (subparsers: the `train` command's); one flag per Args field."""
    p = subparsers.add_parser("map", help="the wide-area search's learned policy: DAgger + REINFORCE",
                              description="A conv net on the fused map scoring every viewpoint, imitating a "
                                          "label-peeking teacher, then REINFORCE; see "
                                          "uavsearch/search/train/map_policy.py.")
    add_dataclass_args(p, Args)
    p.set_defaults(func=cmd_train_map)


def cmd_train_map(args) -> int:
    a = dataclass_from_args(Args, args)
    res = train(a)
    print(format_table(res.table, "validation scenes"))
    print(f"best validation: {json.dumps(res.best)}")
    print(f"{res.seconds:.0f} s; run {res.run_dir}; checkpoint {res.checkpoint}")
    return 0


if __name__ == "__main__":  # python -m uavsearch.search.train.map_policy [flags] = uavsearch train map [flags]
    raise SystemExit(run_command(cmd_train_map, add_dataclass_args(argparse.ArgumentParser(
        prog="python -m uavsearch.search.train.map_policy"), Args).parse_args()))
