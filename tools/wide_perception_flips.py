"""Test-time flips of the wide family's perception against the shipped perception, on validation scenes.

The script users run; its logic lives in uavsearch/research/wide_perception_flips.py (`--help` says how to call it).
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from uavsearch.research.wide_perception_flips import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
