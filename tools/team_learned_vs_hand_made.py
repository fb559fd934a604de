"""What the learned aggregation adds to a team: the team table's choices against the hand-made table's, paired.

The script users run; its logic lives in uavsearch/research/team_learned_vs_hand_made.py (`--help` says how to call
it).
"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from uavsearch.research.team_learned_vs_hand_made import cli  # noqa: E402

if __name__ == "__main__":
    sys.exit(cli())
