"""A candidate perception (a retrained net, or the shipped one seen four ways) against the shipped one: the rule
on the wide family's validation scenes.

The script users run; its logic lives in uavsearch/research/wide_perception_compare.py (`--help` says how to call it).
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from uavsearch.research.wide_perception_compare import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
