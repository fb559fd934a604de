"""Seeded MAVLink fuzzer: hostile and malformed packets at a real `uavsearch sitl` flying a hold.

The script users run; its logic lives in uavsearch/research/fuzz_mavlink.py (`--help` says how to call it).
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from uavsearch.research.fuzz_mavlink import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
