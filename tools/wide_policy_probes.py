"""Other ways of choosing the wide rule's descents, shorter surveys and label bounds, against the rule.

The script users run; its logic lives in uavsearch/research/wide_policy_probes.py (`--help` says how to call it).
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from uavsearch.research.wide_policy_probes import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
