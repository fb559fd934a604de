"""COCO box AP of a perception (our person head, our cell footprints, or a detector of your own) on exported views.

The script users run; its logic lives in uavsearch/research/perception_box_ap.py (`--help` says how to call it).
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from uavsearch.research.perception_box_ap import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
