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


def display_path(path) -> str:
    """`path` relative to the repository (or the working directory) when inside it, for files we commit."""
    p = Path(path).resolve()
    for base in (REPO_ROOT.resolve(), Path.cwd().resolve()):
        if base != Path(base.anchor) and p.is_relative_to(base):
            return p.relative_to(base).as_posix()
    return Path(path).as_posix() if not Path(path).is_absolute() else p.name
