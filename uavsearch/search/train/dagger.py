"""DAgger from a teacher, then REINFORCE: the loop the reactive policy and the map policy share.

A policy's trainer (train/reactive.py, train/map_policy.py) says what is its own in a `DaggerPolicy`: the net
(`state(inp)` -> its input, one tensor or a tuple; `mask(inp)`; `forward(*state, mask)` -> masked logits), the
fusion and the views its episodes run on, the teacher, the imitation loss, the policy-gradient loss with its
baseline, the validation that keeps the best checkpoint, and its metrics' columns. `dagger_reinforce` runs:

1. DAgger (`dagger_iterations`): roll out `DaggerMixture` (per episode and step the teacher with probability
   beta: 1, then times `beta_decay` per iteration; else the net), keep every (state, mask, teacher target),
   fit the net to the whole aggregate with the imitation loss (`dagger_epochs` passes of shuffled minibatches).
2. REINFORCE (`pg_iterations`): `scenes_per_batch` scenes x `episodes_per_scene` episodes sampled from the net,
   the policy's loss minus an entropy bonus decaying linearly from `entropy_start` to `entropy_end`, plus
   `imitation_coef` x the imitation loss on a random minibatch of the aggregate.
3. Validation after DAgger (after each of its iterations where the policy asks) and every `eval_every`
   REINFORCE iterations.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable, NamedTuple

import torch
from torch import nn
from tqdm import tqdm

from uavsearch.errors import UavsearchError

from ..fusion import Fusion
from ..search_loop import Agent, run_search
from .runs import fit_minibatches


class ReinforceLoss(NamedTuple):
    policy: torch.Tensor  # the policy-gradient loss of a batch (before the entropy bonus)
    entropy: torch.Tensor  # the mean entropy it is rewarded for
    charts: dict  # the batch's charts/ columns
    decisions: float  # the decisions it counts (for steps per second)


def _same(state):
    return state


@dataclass
class DaggerPolicy:
    """What one policy's DAgger + REINFORCE run is made of (module docstring)."""

    net: nn.Module
    fusion: Fusion  # fuses the episodes' views
    views: Callable  # episode rows (scene indices) -> their view source (search_loop.CachedViews)
    teacher: Callable  # one DAgger iteration's episode rows -> the teacher that follows them
    imitation_loss: Callable  # (a minibatch of the aggregate: state..., mask, target; generator) -> (loss, agreement)
    reinforce_loss: Callable  # (episodes, their rows) -> ReinforceLoss
    validate: Callable  # (metrics row, iteration) -> the progress bar's postfix; fills eval/, keeps the best
    blank: Callable  # (iteration, phase) -> a metrics row with every column (the loop fills those it has)
    gains: bool = False  # DAgger records the teacher's gain of every action and rolls the net out by its argmax
    keep: Callable | None = None  # (inp, mask, teacher's move) -> the decisions worth recording
    pack: Callable = _same  # how the aggregate stores a state (a tuple of tensors)
    on_aggregate: Callable | None = None  # sees the aggregate before each fit
    validate_each_dagger: bool = True  # False: after the last DAgger iteration only (unless there is no REINFORCE)


class DaggerMixture:
    """DAgger's rollout policy: per episode the teacher with probability beta, else the net (sampled; with
    `gains`, its argmax); records each decision's (state..., mask, target): the teacher's move, or (`gains`) its
    gain of every action (the teacher's `gains(inp)` and `choose(gains, inp)`)."""

    def __init__(self, net: nn.Module, teacher, beta: float, generator: torch.Generator, gains: bool = False,
                 keep: Callable | None = None, pack: Callable = _same):
        self.net, self.teacher, self.beta, self.gen = net, teacher, beta, generator
        self.fit_gains, self.keep, self.pack = gains, keep, pack
        self.records: list[tuple[torch.Tensor, ...]] = []

    @torch.no_grad()
    def act(self, inp, generator=None):
        state = self.net.state(inp)
        state = state if isinstance(state, tuple) else (state,)
        mask = self.net.mask(inp)
        logits = self.net(*state, mask)
        if self.fit_gains:
            target = self.teacher.gains(inp)
            a_teacher, a_net = self.teacher.choose(target, inp), logits.argmax(-1)
        else:
            a_teacher = target = self.teacher.act(inp)[0]
            a_net = torch.multinomial(torch.softmax(logits, -1), 1, generator=self.gen).squeeze(-1)
        use_teacher = torch.rand(len(a_net), generator=self.gen, device=a_net.device) < self.beta
        record = (*self.pack(state), mask, target)
        if self.keep is not None:
            live = self.keep(inp, mask, a_teacher)
            record = tuple(x[live] for x in record)
        self.records.append(record)
        return torch.where(use_teacher, a_teacher, a_net), None, None

    def aggregate(self) -> tuple[torch.Tensor, ...]:
        """(state..., masks, targets) of every recorded decision."""
        return concat(self.records)

    @property
    def decisions(self) -> int:
        return sum(len(r[-1]) for r in self.records)


def concat(records: list[tuple[torch.Tensor, ...]]) -> tuple[torch.Tensor, ...]:
    """Tuples of tensors concatenated field by field."""
    return tuple(torch.cat(field) for field in zip(*records))


def check_dagger_args(args, *positive: str) -> None:
    """One-line errors for the loop's arguments and the trainer's `positive` ones."""
    names = ("dagger_episodes", "dagger_epochs", "batch_size", "scenes_per_batch", "eval_every", *positive)
    bad = [n for n in names if getattr(args, n) < 1]
    if bad:
        raise UavsearchError(f"{', '.join('--' + n.replace('_', '-') for n in bad)} must be positive")
    if min(args.dagger_iterations, args.pg_iterations) < 0 or args.dagger_iterations + args.pg_iterations < 1:
        raise UavsearchError("--dagger-iterations and --pg-iterations must not be negative, and one must be positive")
    if not 0.0 <= args.beta_decay <= 1.0:
        raise UavsearchError(f"--beta-decay must lie in [0, 1], got {args.beta_decay}")


def dagger_reinforce(p: DaggerPolicy, args, num_scenes: int, generator: torch.Generator, log: Callable,
                     name: str) -> None:
    """The run (module docstring) on training scenes 0..num_scenes-1, every draw from `generator`; `log` gets
    each iteration's metrics row."""
    net, gen, dev = p.net, generator, generator.device
    opt_il = torch.optim.Adam(net.parameters(), lr=args.lr, weight_decay=args.weight_decay)
    opt_pg = torch.optim.Adam(net.parameters(), lr=args.lr_pg, weight_decay=args.weight_decay)
    agg: list[tuple[torch.Tensor, ...]] = []

    def fill(row: dict, values: dict) -> dict:
        row.update({k: v for k, v in values.items() if k in row})
        return row

    bar = tqdm(total=args.dagger_iterations + args.pg_iterations, desc=name, disable=not args.progress, unit="it")
    it = 0
    for i in range(args.dagger_iterations):  # 1. DAgger
        it += 1
        beta = args.beta_decay ** i
        rows_b = torch.randint(num_scenes, (args.dagger_episodes,), generator=gen, device=dev)
        mix = DaggerMixture(net, p.teacher(rows_b), beta, gen, gains=p.gains, keep=p.keep, pack=p.pack)
        t0 = time.perf_counter()
        with torch.no_grad():
            run_search(p.views(rows_b), Agent(p.fusion, mix), generator=gen)
        steps_s = mix.decisions / (time.perf_counter() - t0)
        agg.append(mix.aggregate())
        data = concat(agg)
        if p.on_aggregate is not None:
            p.on_aggregate(data)
        loss, agree = fit_minibatches(opt_il, len(data[-1]), args.dagger_epochs, args.batch_size, gen,
                                      lambda b: p.imitation_loss(tuple(x[b] for x in data), gen))
        row = fill(p.blank(it, "dagger"), {"losses/imitation": loss, "charts/teacher_agreement": agree,
                                           "charts/beta": beta, "charts/aggregate": len(data[-1]),
                                           "charts/steps_per_s": steps_s})
        if p.validate_each_dagger or i == args.dagger_iterations - 1 or args.pg_iterations == 0:
            p.validate(row, it)
        log(row)
        bar.update()
        bar.set_postfix(il_loss=f"{row['losses/imitation']:.3f}")

    data = concat(agg) if agg else None
    E = args.episodes_per_scene
    for k in range(args.pg_iterations):  # 2. REINFORCE
        it += 1
        coef = args.entropy_start + (args.entropy_end - args.entropy_start) * k / max(args.pg_iterations - 1, 1)
        rows_b = torch.randint(num_scenes, (args.scenes_per_batch,), generator=gen, device=dev).repeat_interleave(E)
        t0 = time.perf_counter()
        ep = run_search(p.views(rows_b), Agent(p.fusion, net), generator=gen)
        pg = p.reinforce_loss(ep, rows_b)
        loss = pg.policy - coef * pg.entropy
        loss_il = agreement = None
        if data is not None and args.imitation_coef > 0:
            b = torch.randint(len(data[-1]), (args.batch_size,), generator=gen, device=dev)
            loss_il, agreement = p.imitation_loss(tuple(x[b] for x in data), gen)
            loss = loss + args.imitation_coef * loss_il
        opt_pg.zero_grad()
        loss.backward()
        opt_pg.step()
        row = fill(p.blank(it, "pg"), {"losses/policy": float(pg.policy.detach()), **pg.charts,
                                       "charts/entropy": float(pg.entropy.detach()), "charts/entropy_coef": coef,
                                       "charts/steps_per_s": pg.decisions / (time.perf_counter() - t0)})
        if loss_il is not None:
            row["losses/imitation"], row["charts/teacher_agreement"] = float(loss_il.detach()), float(agreement)
        if (k + 1) % args.eval_every == 0 or k == args.pg_iterations - 1:
            bar.set_postfix(**p.validate(row, it))
        log(row)
        bar.update()
    bar.close()


__all__ = ["DaggerMixture", "DaggerPolicy", "ReinforceLoss", "check_dagger_args", "concat", "dagger_reinforce"]
