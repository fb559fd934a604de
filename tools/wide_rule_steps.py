"""The wide rule's mean F1 after each view, on the validation scenes.

The script users run; its logic lives in uavsearch/research/wide_rule_steps.py (`--help` says how to call it).
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from uavsearch.research.wide_rule_steps import main  # noqa: E402

if __name__ == "__main__":
    sys.exit(main())
