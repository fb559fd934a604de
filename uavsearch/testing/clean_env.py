"""The environment a test gives every process it starts: built from scratch, never a copy of the caller's.

A test that inherits the pytest process's environment passes or fails by what ran before it (pymavlink,
for one, sets MAVLINK20 in its own process on the first MAVLink 2 frame). PATH (this interpreter first),
HOME, unbuffered Python output, and what the caller names.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path


def clean_env(**extra: str) -> dict[str, str]:
    """PATH, HOME, PYTHONUNBUFFERED=1 and `extra`; nothing else."""
    env = {"PATH": f"{Path(sys.executable).parent}:/usr/local/bin:/usr/bin:/bin",
           "HOME": os.environ.get("HOME", "/root"), "PYTHONUNBUFFERED": "1"}
    env.update(extra)
    return env


__all__ = ["clean_env"]
