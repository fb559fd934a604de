"""How reactive is a policy: the number of distinct routes its most likely moves fly over the test scenes.

A policy that has learned one route flies it everywhere (1-3 distinct routes); one that reacts to what
it sees flies many. Writes a table (settings x policies) to --out and prints it.

    .venv/bin/python tools/route_diversity.py [--split large] [--out results/search_large/routes.md]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from uavsearch.search.agents import build_agent
from uavsearch.search.config import SearchConfig
from uavsearch.search.evaluate.search import policy_checkpoint
from uavsearch.search.perception import load_perception
from uavsearch.search.policy import load_search_model
from uavsearch.search.search_loop import CachedViews, run_search
from uavsearch.search.data.view_cache import get_view_cache
from uavsearch.world.settings import SETTINGS

POLICIES = ("learned", "reactive", "greedy", "coverage")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--split", default="large")
    ap.add_argument("--perception", default="models/perception.pt")
    ap.add_argument("--models-dir", default="models")
    ap.add_argument("--out", default="results/search_large/routes.md")
    args = ap.parse_args()
    torch.set_num_threads(1)
    net, _ = load_perception(args.perception)
    config = SearchConfig()
    lines = [f"# Distinct routes flown (most likely moves), {args.split} split, test scenes", "",
             "| setting | " + " | ".join(POLICIES) + " |", "|---|" + "---|" * len(POLICIES)]
    for s in sorted(SETTINGS):
        cache = get_view_cache(net, s, args.split, "test", progress=False)
        confidence = load_search_model(Path(args.models_dir) / f"search_s{s}_learned.pt").fusion.scorer
        cells = []
        for policy in POLICIES:
            agent = build_agent("learned", policy, config, checkpoint=policy_checkpoint(s, "learned", policy, args.models_dir),
                                confidence_checkpoint=Path(args.models_dir) / f"search_s{s}_learned.pt",
                                greedy=True).agent
            with torch.no_grad():
                ep = run_search(CachedViews(cache, np.arange(cache.num_scenes), config, confidence), agent,
                                generator=torch.Generator().manual_seed(0))
            cells.append(f"{len({tuple(r) for r in ep.lattice_idx.tolist()})} / {cache.num_scenes}")
        lines.append(f"| {s} ({SETTINGS[s]} cells) | " + " | ".join(cells) + " |")
    lines += ["", "learned: the paper's policy; reactive: the reactive policy; greedy: greedy uncertainty; "
              "coverage: the fixed coverage route. Learned confidence fusion in every column."]
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
