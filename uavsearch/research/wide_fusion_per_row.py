"""Table III's headline with every method on its own fusion: is the rule's lead over the best fixed route a
property of the one fusion chosen for all rows?

Table III gives every row one fusion, chosen on validation by the mean AF1 of the hand-made fixed routes and
the rule; a fusion that suits the rule may hurt a fixed route. Here each fixed route and the rule take the
fusion with the best validation AF1 for themselves (among Table III's candidates, the calibrated ones fitted on
the same training scenes), the best fixed route is the fixed route with the best validation AF1 on its own
fusion, and the rule (its variant chosen on validation as in Table III, under its own fusion) is paired
against it on the test scenes (95% scene-bootstrap interval). Writes a markdown table and prints it.

    python tools/wide_fusion_per_row.py --out results/search_wide/per_row_fusion.md
    python tools/wide_fusion_per_row.py --family wide-uniform --test-scenes 50 --val-scenes 20 \
        --out results/search_wide_uniform/per_row_fusion.md
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from tqdm import tqdm

from ..search.data.view_cache import get_view_cache
from ..search.evaluate.bounds import scene_af1
from ..search.metrics import bootstrap_ci
from ..search.config import wide_budgets
from ..search.evaluate.wide import FIXED, FUSION_CANDIDATES, LABELS, RULE, fixed_agents, rule_agent, run_rows
from ..search.fusion import fusion_name
from ..search.agents import make_fusion
from ..search.fusion import calibrated_candidates
from ..search.wide_policies import choose_rule
from ..search.perception import load_perception, shipped_perception


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--family", default="wide")
    ap.add_argument("--train-scenes", type=int, default=20, help="training scenes (view sets, calibration)")
    ap.add_argument("--val-scenes", type=int, default=None, help="validation scenes (default all)")
    ap.add_argument("--test-scenes", type=int, default=None, help="test scenes (default all)")
    ap.add_argument("--out", required=True, help="markdown file to write")
    args = ap.parse_args()
    t0 = time.perf_counter()
    net, _ = load_perception(str(shipped_perception(args.family)))
    limits = {"train": args.train_scenes, "val": args.val_scenes, "test": args.test_scenes}
    caches = {p: get_view_cache(net, args.family, "large", p, features=False, limit=limits[p], progress=False)
              for p in ("train", "val", "test")}
    fusions = [make_fusion(s) for s in FUSION_CANDIDATES] + calibrated_candidates(caches["train"])
    lines = [f"# {args.family}: every method on its own fusion (chosen on validation)", "",
             f"{caches['test'].num_scenes} test scenes, {caches['val'].num_scenes} validation, "
             f"{caches['train'].num_scenes} training (view sets, calibration); `python tools/wide_fusion_per_row.py`.",
             "", "| budget | best fixed route (its fusion), test AF1 | the rule (its fusion, variant), test AF1 | "
             "rule − best fixed [95% CI] |", "|---|---|---|---|"]
    for name, cfg in wide_budgets(caches["test"].config).items():
        best: dict[str, tuple] = {}  # row -> (val AF1, fusion, agent, the rule's variant)
        for fusion in tqdm(fusions, desc=f"{args.family}, {name}", unit="fusion"):
            fixed, _ = fixed_agents(cfg, fusion, caches["train"])
            variant, variant_af1 = choose_rule(caches["val"], cfg, fusion)  # the rule's validation runs
            val = run_rows(caches["val"], cfg, {k: (a, 1) for k, a in fixed.items()})
            candidates = {**{k: (float(r["f1"][:, :, -1].mean()), fixed[k]) for k, r in val.items()},
                          RULE: (variant_af1[variant], rule_agent(fusion, cfg, variant))}
            for k, (af1, agent) in candidates.items():
                if k not in best or af1 > best[k][0]:
                    best[k] = (af1, fusion, agent, variant)
        top = max(FIXED, key=lambda k: (best[k][0], -FIXED.index(k)))
        test = run_rows(caches["test"], cfg, {k: (best[k][2], 1) for k in (top, RULE)})
        d = scene_af1(test[RULE]) - scene_af1(test[top])
        mean, lo, hi = bootstrap_ci(d, 10_000, 0)
        lines.append(f"| {name} | {LABELS[top]} ({fusion_name(best[top][1])}), {scene_af1(test[top]).mean():.3f} | "
                     f"{fusion_name(best[RULE][1])}, {best[RULE][3]}, {scene_af1(test[RULE]).mean():.3f} | "
                     f"{mean:+.3f} [{lo:+.3f}, {hi:+.3f}] |")
    lines += ["", f"{time.perf_counter() - t0:.0f} s"]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    print(out.read_text())


if __name__ == "__main__":
    main()
