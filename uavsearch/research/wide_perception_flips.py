"""Does seeing each view four ways (test-time flips) make the wide family's perception find more people?

A nadir view has no preferred side: the image and its mirror images (left-right, up-down, both), each with its
cell label image mirrored along, are views the shipped perception could have been shown. `flips:PATH`
(search/perception.py) averages the per-cell probabilities and features of the four. This probe builds the
validation caches (and the first 20 training scenes', which the calibrated fusion is fitted on) with the flipped
perception from the same renders, lets the rule (its variant chosen on validation, per perception) search both,
and pairs the final AF1 per validation scene (95% bootstrap interval over scenes), at T = 8 views and at 240 s.
It also times perception per view, plain and flipped, on this machine.

    python tools/wide_perception_flips.py --out results/wide_study/perception_flips.md
"""

from __future__ import annotations

import shlex
import sys
import time

import numpy as np
import torch

from ..search.agents import make_fusion
from ..search.data.view_cache import get_view_cache
from ..search.metrics import bootstrap_ci
from ..search.perception import FLIPS_PREFIX, load_perception, shipped_perception
from ..search.scoring import evaluate_agent
from ..search.search_loop import Agent
from ..search.train.map_policy import budget_config
from ..search.wide_policies import choose_rule, rule_policy
from .wide_policy_probes import FUSION, probe_parser, write_markdown


def rule_af1(net, family: str, budget: str) -> tuple[np.ndarray, str]:
    """(the rule's final F1 per validation scene, its variant chosen on validation) with perception `net`."""
    train = get_view_cache(net, family, "large", "train", features=False, limit=20)
    val = get_view_cache(net, family, "large", "val", features=False)
    config = budget_config(val.config, budget)
    fusion = make_fusion(FUSION[budget], train)
    variant, _ = choose_rule(val, config, fusion)
    f1 = evaluate_agent(val, Agent(fusion, rule_policy(config, variant)), 1, config=config).f1[:, -1]
    return np.asarray(f1, dtype=float).reshape(val.num_scenes, -1).mean(1), variant


def time_per_view(net, views: int = 64) -> float:
    """Milliseconds of perception per 224 px view (batch of 16, this process's threads)."""
    x = torch.rand(16, 3, 224, 224)
    lab = torch.randint(-1, net.num_cells, (16, 224, 224))
    with torch.no_grad():
        net.forward_all(x, lab, altitude_m=70.0)
        t0 = time.perf_counter()
        for _ in range(views // 16):
            net.forward_all(x, lab, altitude_m=70.0)
    return 1000 * (time.perf_counter() - t0) / views


def main() -> int:
    ap = probe_parser(__doc__)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    path = str(shipped_perception(args.family))
    plain, _ = load_perception(path)
    flipped, _ = load_perception(FLIPS_PREFIX + path)
    t0 = time.perf_counter()
    ms = {"plain": time_per_view(plain), "flips": time_per_view(flipped)}
    rows = []
    for budget in ("8", "240"):
        base, v0 = rule_af1(plain, args.family, budget)
        flip, v1 = rule_af1(flipped, args.family, budget)
        mean, lo, hi = bootstrap_ci(flip - base)
        rows.append(f"| {'T = 8' if budget == '8' else '240 s'} ({FUSION[budget]}) | {base.mean():.3f} ({v0}) | "
                    f"{flip.mean():.3f} ({v1}) | {mean:+.3f} [{lo:+.3f}, {hi:+.3f}] |")
    cmd = "python tools/wide_perception_flips.py " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    lines = [f"# Test-time flips of the {args.family} perception, validation only (`{cmd}`)", "",
             f"The rule on the {args.family} family's 50 validation scenes (one episode each: the rule is "
             "deterministic), its variant chosen on validation for each perception, the calibrated fusion fitted on "
             "the first 20 training scenes of each perception's caches. Paired difference, 95% bootstrap interval "
             "over the 50 scenes.", "",
             "| budget (fusion) | shipped perception AF1 (rule variant) | flipped x4 AF1 (rule variant) | "
             "flipped - shipped |", "|---|---|---|---|", *rows, "",
             f"Perception per 224 px view on this machine ({args.threads} threads, batches of 16): shipped "
             f"{ms['plain']:.1f} ms, flipped x4 {ms['flips']:.1f} ms.", "",
             f"{time.perf_counter() - t0:.0f} s, caches built where missing."]
    write_markdown(args.out, lines)
    return 0
