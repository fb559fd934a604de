"""How hard the wide family is to see: generation and render times, visible person pixels per occupied cell.

The script users run; its logic lives in uavsearch/research/wide_difficulty.py (`--help` says how to call it).
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from uavsearch.research.wide_difficulty import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
