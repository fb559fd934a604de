"""One way to turn an Args dataclass into command-line flags: each field is a flag, its `help` its --help.

    @dataclass
    class Args:
        steps: int = opt(800, "optimiser steps")
        out: str | None = opt(None, "copy the best checkpoint here", required=True)

    add_dataclass_args(parser, Args)       # --steps N, --out OUT
    args = dataclass_from_args(Args, ns)   # Args(steps=..., out=...)

Flags are the field names with dashes. Booleans take `--flag` (true), `--flag false` or `--no-flag`;
tuples and lists take several values. Field metadata: `help`, `flag` (more names, e.g. a short old
spelling), `required`, `choices`, `cli=False` (not a flag).
"""

from __future__ import annotations

import argparse
import dataclasses
import types
import typing
from typing import Any

_MISSING = dataclasses.MISSING


def opt(default: Any = _MISSING, help: str = "", *, factory=None, flag: str | tuple[str, ...] = (),
        required: bool = False, choices=None, cli: bool = True):
    """A dataclass field that is also a command-line flag."""
    md = {"help": help, "flag": (flag,) if isinstance(flag, str) else tuple(flag), "required": required,
          "choices": choices, "cli": cli}
    if factory is not None:
        return dataclasses.field(default_factory=factory, metadata=md)
    return dataclasses.field(default=default, metadata=md)


def parse_bool(text: str) -> bool:
    t = str(text).strip().lower()
    if t in ("1", "true", "yes", "on"):
        return True
    if t in ("0", "false", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(f"expected true or false, got {text!r}")


def _base_type(hint):
    """int | None -> int; tuple[int, ...] -> (tuple, int)."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        return _base_type(args[0]) if len(args) == 1 else (None, str)
    if origin in (tuple, list):
        inner = [a for a in typing.get_args(hint) if a is not Ellipsis]
        return origin, (inner[0] if inner and isinstance(inner[0], type) else str)
    return None, hint if isinstance(hint, type) else str


def add_dataclass_args(parser: argparse.ArgumentParser, cls) -> argparse.ArgumentParser:
    """One flag per field of the dataclass `cls` (fields with metadata cli=False are left out)."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        md = f.metadata
        if not md.get("cli", True):
            continue
        default = f.default if f.default is not _MISSING else (
            f.default_factory() if f.default_factory is not _MISSING else None)
        names = ["--" + f.name.replace("_", "-"), *md.get("flag", ())]
        required = bool(md.get("required"))
        text = md.get("help", "")
        if not required:
            text = f"{text} (default {default})" if text else f"default {default}"
        kw = dict(dest=f.name, help=text.replace("%", "%%"), required=required, choices=md.get("choices"))
        if not required:
            kw["default"] = default
        container, typ = _base_type(hints[f.name])
        if typ is bool:
            parser.add_argument(*names, nargs="?", const=True, type=parse_bool, metavar="BOOL", **kw)
            parser.add_argument("--no-" + f.name.replace("_", "-"), dest=f.name, action="store_false",
                                help=argparse.SUPPRESS)
        elif container is not None:
            parser.add_argument(*names, nargs="+", type=typ, **kw)
        else:
            parser.add_argument(*names, type=typ, **kw)
    return parser


def dataclass_from_args(cls, ns: argparse.Namespace):
    """The dataclass from parsed flags (fields without a flag keep their defaults)."""
    hints = typing.get_type_hints(cls)
    kw = {}
    for f in dataclasses.fields(cls):
        if f.metadata.get("cli", True) and hasattr(ns, f.name):
            v = getattr(ns, f.name)
            container, _ = _base_type(hints[f.name])
            kw[f.name] = container(v) if container is not None and v is not None else v
        # fields left out of the CLI keep their defaults
    return cls(**kw)


__all__ = ["add_dataclass_args", "dataclass_from_args", "opt", "parse_bool"]
