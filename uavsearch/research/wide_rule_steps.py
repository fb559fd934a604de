"""The rule's mean F1 after each view of the wide family's episodes, on the validation scenes: where in an
episode its gain comes from (the survey, the first descents, the later ones). Fusions are Table III's
calibrated ones, fitted on the training scenes; one line per (fusion, rule variant: survey and resurvey
threshold), and a PNG of F1 against views.

    python tools/wide_rule_steps.py --budget 240 --out results/search_wide/rule_steps.png
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from ..search.data.view_cache import get_view_cache
from ..search.config import wide_budgets
from ..search.evaluate.wide import rule_agent
from ..search.fusion import calibrated_candidates
from ..search.wide_policies import RULE_VARIANTS
from ..search.perception import load_perception, shipped_perception
from ..search.scoring import score_episode
from ..search.search_loop import CachedViews, run_search
from ..viz import pyplot


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--family", default="wide")
    ap.add_argument("--budget", choices=("8", "240"), default="240", help="T = 8 views, or 240 s of flight")
    ap.add_argument("--gammas", default="0.75", help="calibrated fusions' discounts")
    ap.add_argument("--resurvey", default="0,0.6", help="the fused p below which the rule keeps surveying (0: never)")
    ap.add_argument("--train-scenes", type=int, default=20)
    ap.add_argument("--out", required=True, help="PNG to write (the same lines, printed, go beside it as .md)")
    args = ap.parse_args()
    net, _ = load_perception(str(shipped_perception(args.family)))
    train = get_view_cache(net, args.family, "large", "train", features=False, limit=args.train_scenes, progress=False)
    val = get_view_cache(net, args.family, "large", "val", features=False, progress=False)
    cfg = list(wide_budgets(val.config).values())[0 if args.budget == "8" else 1]
    gammas = [float(g) for g in args.gammas.split(",")]
    below = {float(t) for t in args.resurvey.split(",")}
    variants = [k for k, (_, t, _) in RULE_VARIANTS.items() if t in below]
    fig, ax = pyplot().subplots(figsize=(7, 4))
    lines = [f"{args.family}, {'T = 8 views' if args.budget == '8' else '240 s'}, {val.num_scenes} validation scenes: "
             "mean F1 after each view (the start view is view 1; `python tools/wide_rule_steps.py`)", ""]
    for fusion in calibrated_candidates(train, gammas):
        for variant in variants:
            with torch.no_grad():
                ep = run_search(CachedViews(val, np.arange(val.num_scenes), cfg), rule_agent(fusion, cfg, variant))
            f1 = score_episode(ep).f1.mean(0)
            lines.append(f"- {fusion.spec}, {variant}: " + " ".join(f"{x:.3f}" for x in f1)
                         + f" | peak {f1.max():.3f} after view {int(f1.argmax()) + 1}, end {f1[-1]:.3f}")
            ax.plot(np.arange(1, len(f1) + 1), f1, marker=".", label=f"{fusion.spec}, {variant}")
    ax.set_xlabel("views taken")
    ax.set_ylabel("mean F1 of the fused map")
    ax.set_title(f"the rule on {val.num_scenes} {args.family} validation scenes")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines) + f"\nwrote {out} and {out.with_suffix('.md')}")


if __name__ == "__main__":
    main()
