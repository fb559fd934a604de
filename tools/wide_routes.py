"""The learned wide-area policy's routes against the rule's, on the wide test scenes.

The script users run; its logic lives in uavsearch/research/wide_routes.py (`--help` says how to call it).
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from uavsearch.research.wide_routes import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
