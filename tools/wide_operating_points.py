"""The wide net's 40 m targets at other decision thresholds.

The script users run; its logic lives in uavsearch/research/wide_operating_points.py (`--help` says how to call it).
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from uavsearch.research.wide_operating_points import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
