"""Where the repository's data folders (aircraft/, scenes/, missions/, models/) live.

The package is installed editable from the repository, so they sit beside it; UAVSEARCH_HOME overrides.
"""

import os
from pathlib import Path

REPO_ROOT = Path(os.environ.get("UAVSEARCH_HOME", Path(__file__).resolve().parent.parent))
AIRCRAFT_DIR = REPO_ROOT / "aircraft"
SCENES_DIR = REPO_ROOT / "scenes"
MISSIONS_DIR = REPO_ROOT / "missions"
MODELS_DIR = REPO_ROOT / "models"
RUNS_DIR = Path(os.environ.get("UAVSEARCH_RUNS", Path.cwd() / "runs"))
