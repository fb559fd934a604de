"""Reading a mission or plan file the user named, so that no file can hang, exhaust memory or traceback.

A mission file is small: it is read only if it is a regular file (never a device, FIFO or socket, which
could block or never end), with a size bound, as strict UTF-8, and its parsed document must stay within a
nesting depth and a number of values (a YAML alias repeats a whole subtree: a few lines could otherwise
expand to billions). Every refusal is one MissionError line naming the file.
"""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path

import yaml

from ..errors import MissionError

MIB = 1 << 20
MISSION_MAX_BYTES = 1 * MIB
PLAN_MAX_BYTES = 16 * MIB  # room for a plan past the mission protocol's 65,535 items, so the count is what is said
MAX_DEPTH = 32  # a mission nests 3 deep, a QGC survey plan about 7
MISSION_MAX_VALUES = 100_000


def _size_text(n: int) -> str:
    return f"{n // MIB} MiB" if n % MIB == 0 else f"{n} bytes"


def read_bounded_text(path, kind: str = "mission", max_bytes: int = MISSION_MAX_BYTES) -> str:
    """The file's text, or one line saying why not (missing, not a regular file, too large, not UTF-8)."""
    path = Path(path)
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):
            raise MissionError(f"{kind} {path}: not a regular file")
        # O_NONBLOCK: a FIFO swapped in since the check must not block the open; fstat refuses it below
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
        with os.fdopen(fd, "rb") as f:
            if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
                raise MissionError(f"{kind} {path}: not a regular file")
            data = f.read(max_bytes + 1)
    except OSError as e:
        raise MissionError(f"{kind} {path}: cannot read ({e.strerror or e})") from None
    if len(data) > max_bytes:
        raise MissionError(f"{kind} {path}: larger than {_size_text(max_bytes)}; not a {kind} file")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise MissionError(f"{kind} {path}: not UTF-8 text (byte 0x{data[e.start]:02x} at offset {e.start})") from None


def check_shape(doc, source: str, kind: str = "mission", max_depth: int = MAX_DEPTH,
                max_values: int | None = MISSION_MAX_VALUES) -> None:
    """One line if the parsed document nests deeper than `max_depth` or holds more than `max_values` values
    (a value repeated through an alias counts each time; the walk stops at the bound, so it is quick)."""
    stack = [(doc, 1)]
    seen = 0
    while stack:
        node, depth = stack.pop()
        seen += 1
        if max_values is not None and seen > max_values:
            raise MissionError(f"{kind} {source}: more than {max_values} values; not a {kind} file")
        if isinstance(node, (dict, list, tuple)):
            if depth > max_depth:
                raise MissionError(f"{kind} {source}: nested deeper than {max_depth} levels")
            children = [*node.keys(), *node.values()] if isinstance(node, dict) else node
            stack.extend((c, depth + 1) for c in children)


def parse_yaml(text: str, source: str, kind: str = "mission"):
    """The YAML document (safe types only), or one line with the line and column of the first problem."""
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(e, "problem", None) or str(e)
        raise MissionError(f"{kind} {source}: not valid YAML{where}: {_first_line(problem)}") from None
    except RecursionError:
        raise MissionError(f"{kind} {source}: nested deeper than {MAX_DEPTH} levels") from None
    except (ValueError, OverflowError) as e:  # a timestamp such as 2001-13-45, an integer of 5,000 digits
        raise MissionError(f"{kind} {source}: not valid YAML: {_first_line(str(e))}") from None
    check_shape(doc, source, kind)
    return doc


def _no_constant(name: str):
    raise ValueError(f"{name} is not a number a plan holds (QGroundControl writes null)")


def parse_json(text: str, source: str, kind: str = "plan"):
    """The JSON document (NaN and Infinity refused), or one line saying where it is not JSON. JSON has no
    aliases: the size bound bounds its number of values."""
    try:
        doc = json.loads(text, parse_constant=_no_constant)
    except RecursionError:
        raise MissionError(f"{kind} {source}: nested deeper than {MAX_DEPTH} levels") from None
    except ValueError as e:
        raise MissionError(f"{kind} {source}: not JSON ({_first_line(str(e))})") from None
    check_shape(doc, source, kind, max_values=None)
    return doc


def _first_line(text: str) -> str:
    return (text.strip().splitlines() or [""])[0]


__all__ = ["MAX_DEPTH", "MISSION_MAX_BYTES", "PLAN_MAX_BYTES", "check_shape", "parse_json", "parse_yaml",
           "read_bounded_text"]
