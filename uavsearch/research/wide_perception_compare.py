"""Does another perception make the rule find more people in the wide family? A candidate against the shipped net.

The candidate (`--candidate SPEC`) is any perception spec: a retrained checkpoint (say, the shipped net fine-tuned
on more training scenes), or `flips` (the default), the shipped net seeing each view four ways: a nadir view has
no preferred side, so the image and its mirror images (left-right, up-down, both), each with its cell label image
mirrored along, are views the net could have been shown, and `flips:PATH` (search/perception.py) averages the
per-cell probabilities and features of the four. The probe builds the validation caches (and the first 20
training scenes', which the calibrated fusion is fitted on) with each perception from the same renders, lets the
rule (its variant chosen on validation, per perception) search both, and pairs the final AF1 per validation scene
(95% bootstrap interval over scenes), at T = 8 views and at 240 s. It also times both perceptions per view on
this machine.

    python tools/wide_perception_compare.py --out results/wide_study/perception_flips.md
    python tools/wide_perception_compare.py --candidate runs/perception_wide_500.pt --out runs/perception_500.md
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
    ap.add_argument("--candidate", default="flips",
                    help="the perception to compare: a checkpoint or spec, or flips (the shipped net, flipped x4)")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    path = str(shipped_perception(args.family))
    plain, _ = load_perception(path)
    flips = args.candidate == "flips"
    other, _ = load_perception(FLIPS_PREFIX + path if flips else args.candidate)
    name = "flipped x4" if flips else args.candidate
    t0 = time.perf_counter()
    ms = {"plain": time_per_view(plain), "other": time_per_view(other)}
    rows = []
    for budget in ("8", "240"):
        base, v0 = rule_af1(plain, args.family, budget)
        cand, v1 = rule_af1(other, args.family, budget)
        mean, lo, hi = bootstrap_ci(cand - base)
        rows.append(f"| {'T = 8' if budget == '8' else '240 s'} ({FUSION[budget]}) | {base.mean():.3f} ({v0}) | "
                    f"{cand.mean():.3f} ({v1}) | {mean:+.3f} [{lo:+.3f}, {hi:+.3f}] |")
    cmd = "python tools/wide_perception_compare.py " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    title = "Test-time flips of" if flips else f"{name} against"
    lines = [f"# {title} the {args.family} perception, validation only (`{cmd}`)", "",
             f"The rule on the {args.family} family's 50 validation scenes (one episode each: the rule is "
             "deterministic), its variant chosen on validation for each perception, the calibrated fusion fitted on "
             "the first 20 training scenes of each perception's caches. Paired difference, 95% bootstrap interval "
             "over the 50 scenes.", "",
             f"| budget (fusion) | shipped perception AF1 (rule variant) | {name} AF1 (rule variant) | "
             f"{'flipped' if flips else 'candidate'} - shipped |", "|---|---|---|---|", *rows, "",
             f"Perception per 224 px view on this machine ({args.threads} threads, batches of 16): shipped "
             f"{ms['plain']:.1f} ms, {name} {ms['other']:.1f} ms.", "",
             f"{time.perf_counter() - t0:.0f} s, caches built where missing."]
    write_markdown(args.out, lines)
    return 0
