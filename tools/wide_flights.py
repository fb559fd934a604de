"""Flown wide-area missions against teleport on the first test scenes of their family.

The script users run; its logic lives in uavsearch/research/wide_flights.py (`--help` says how to call it).
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from uavsearch.research.wide_flights import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
