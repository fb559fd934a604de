"""Parameters, PX4 style: each module declares a table (name, type, unit, default, min, max).

One ParamStore holds the union; values are checked on set. MAVLink's PARAM_* protocol and the
mission file both go through it.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Iterable, Literal

from ..errors import UavsearchError


class ParamError(UavsearchError):
    pass


def _float32(v: float) -> float:
    """`v` rounded to float32 (what PARAM_VALUE / PARAM_SET carry); out-of-range values become +-inf."""
    try:
        return struct.unpack("<f", struct.pack("<f", v))[0]
    except OverflowError:
        return float("inf") if v > 0 else float("-inf")


@dataclass(frozen=True)
class ParamDef:
    name: str  # PX4 name, at most 16 characters
    default: float
    min: float
    max: float
    unit: str = ""
    type: Literal["float", "int"] = "float"
    description: str = ""
    readonly: bool = False  # what the vehicle reports about itself: set at start only, PARAM_SET is refused

    def __post_init__(self):
        if len(self.name) > 16:
            raise ValueError(f"param name {self.name!r} is longer than MAVLink's 16 characters")
        if not self.min <= self.default <= self.max:
            raise ValueError(f"param {self.name}: default {self.default} outside [{self.min}, {self.max}]")


class ParamStore:
    """Current values of every declared parameter, in declaration order (MAVLink param_index)."""

    def __init__(self, *tables: Iterable[ParamDef]):
        self._defs: dict[str, ParamDef] = {}
        for table in tables:
            for d in table:
                if d.name in self._defs:
                    raise ValueError(f"param {d.name} declared twice")
                self._defs[d.name] = d
        self._values = {n: (int(d.default) if d.type == "int" else float(d.default)) for n, d in self._defs.items()}
        self._listeners = []

    def __contains__(self, name: str) -> bool:
        return name in self._defs

    def __getitem__(self, name: str) -> float:
        try:
            return self._values[name]
        except KeyError:
            raise ParamError(f"unknown parameter {name}") from None

    def __len__(self) -> int:
        return len(self._defs)

    def names(self) -> list[str]:
        return list(self._defs)

    def definition(self, name: str) -> ParamDef:
        if name not in self._defs:
            raise ParamError(f"unknown parameter {name}")
        return self._defs[name]

    def index(self, name: str) -> int:
        return self.names().index(name)

    def set(self, name: str, value: float, force: bool = False) -> float:
        """Set a value; out-of-range, unknown or read-only (unless `force`, at start) raises ParamError.
        Returns the stored value."""
        d = self.definition(name)
        if d.readonly and not force:
            raise ParamError(f"{name} is read-only")
        v = float(value)
        if d.type == "float":
            # A float parameter travels as float32: 0.01 arrives as 0.00999999977648. Bounds compare at float32
            # (both sides rounded), and a value equal to a bound there is stored as the bound.
            v32, lo, hi = _float32(v), _float32(d.min), _float32(d.max)
            if v32 != v32 or not lo <= v32 <= hi:
                raise ParamError(f"{name}={value} outside [{d.min}, {d.max}] {d.unit}".rstrip())
            stored = d.min if v32 == lo else d.max if v32 == hi else v
        else:
            if v != v or not d.min <= v <= d.max:
                raise ParamError(f"{name}={value} outside [{d.min}, {d.max}] {d.unit}".rstrip())
            stored = int(round(v))
        self._values[name] = stored
        for cb in self._listeners:
            cb(name, stored)
        return stored

    def on_change(self, callback) -> None:
        """callback(name, value) after every successful set."""
        self._listeners.append(callback)
