"""The learned neighbour fusion over seeds: validation AF1, fit time, cost per view.

The script users run; its logic lives in uavsearch/research/wide_fusion_seeds.py (`--help` says how to call it).
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from uavsearch.research.wide_fusion_seeds import cli  # noqa: E402

if __name__ == "__main__":
    sys.exit(cli())
