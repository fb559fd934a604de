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


def prepare_output(path, kind: str = "dir") -> Path:
    """Make sure an output folder (kind 'dir') or file (kind 'file') can be written, before any work starts
    (checked at its nearest existing folder; nothing is created, so a run that fails later leaves no folder).

    Any problem (a file where a folder is wanted, no permission, a read-only or missing parent) is one
    UavsearchError line naming the path and the reason, never a traceback half-way through a run.
    """
    import tempfile

    from .errors import UavsearchError

    path = Path(path).expanduser()
    folder = path if kind == "dir" else path.parent
    if kind == "file" and path.is_dir():
        raise UavsearchError(f"cannot write {path}: it is a folder, a file is needed")
    if kind == "dir" and path.exists() and not path.is_dir():
        raise UavsearchError(f"cannot write to {path}: it is a file, a folder is needed")
    existing = next(p for p in [folder, *folder.parents] if p.exists())  # nothing is created here
    if not existing.is_dir():
        raise UavsearchError(f"cannot write to {folder}: {existing} is a file")
    try:
        with tempfile.TemporaryFile(dir=existing):
            pass
    except OSError as e:
        raise UavsearchError(f"cannot write to {folder}: {e.strerror or e}") from None
    return path
