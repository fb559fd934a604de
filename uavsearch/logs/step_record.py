"""One step of a flight log: what the search saw and did at one view, as a typed record.

`StepRecord` is the one definition of a `{"type": "step", ...}` line of search.jsonl: the mission controller
writes it, replay, the flight review page and `.plan` writing read it. `to_json()` and `from_json()` keep the
line format exactly (key order, floats rounded to 6 decimals, NaN as null), so a log written before this
type existed reads back and writes out byte for byte.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, fields
from typing import NamedTuple

import numpy as np

from ..errors import LogError


def jsonable(x):
    """`x` as plain JSON values the log's way: arrays as lists, floats rounded to 6 decimals, NaN / inf as null."""
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return round(v, 6) if np.isfinite(v) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.bool_,)):
        return bool(x)
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if hasattr(x, "_asdict"):  # a NamedTuple is an object, not a list
        return jsonable(x._asdict())
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if hasattr(x, "tolist"):
        return jsonable(x.tolist())
    return x


def dumps_line(record: dict) -> str:
    """One compact JSON line of the log (no newline)."""
    return json.dumps(jsonable(record), separators=(",", ":"))


class TruePose(NamedTuple):
    """The camera's true pose, from the simulated camera's own record (None parts: it did not say)."""

    position_enu: list | None  # (3,) metres, scene ENU
    rpy_rad: list | None  # (3,) roll, pitch, yaw


def _int(v):
    if isinstance(v, bool) or not isinstance(v, int):
        raise TypeError(f"{v!r} is not an integer")
    return v


def _num(v):
    """A JSON number as it was written (an int stays an int, so the line writes back the same)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise TypeError(f"{v!r} is not a number")
    return v


def _bool(v):
    if not isinstance(v, bool):
        raise TypeError(f"{v!r} is not true/false")
    return v


def _str(v):
    if not isinstance(v, str):
        raise TypeError(f"{v!r} is not a string")
    return v


def _opt(read):
    return lambda v: None if v is None else read(v)


def _list(read):
    def conv(v):
        if not isinstance(v, list):
            raise TypeError(f"{str(v)[:40]!r} is not a list")
        return [None if x is None else read(x) for x in v]
    return conv


def _cells(read, dtype):
    """A per-cell list as an (N,) array (null, a NaN when written, back to NaN)."""
    def conv(v):
        return np.asarray([np.nan if x is None else x for x in _list(read)(v)], dtype=dtype)
    return conv


def _true_pose(v):
    if not isinstance(v, dict):
        raise TypeError(f"{str(v)[:40]!r} is not an object")
    return TruePose(*(_opt(_list(_num))(v.get(k)) for k in TruePose._fields))


@dataclass(frozen=True, kw_only=True, eq=False)
class StepRecord:
    """One view of a flown search. Field order is the line's key order; per-cell arrays are (N,)."""

    t: int  # view index, 0 for the start view
    sim_time_s: float | None = None  # vehicle clock at the capture
    wall_s: float | None = None  # wall seconds this step took (clock-dependent)
    flight_time_s: float | None = None  # simulated seconds flown to reach the view
    lattice_idx: int | None = None  # viewpoint on the search lattice
    waypoint_enu: list  # (3,) commanded position, metres
    reported_position_enu: list  # (3,) the pose the vehicle reported with the image
    reported_rpy_rad: list
    true_pose: TruePose | None = None
    image_index: int | None = None
    image: str  # the PNG, relative to the run directory
    p_occ: np.ndarray  # per-cell p(occupied) of this view
    scores: np.ndarray | None = None  # confidence scores, when a confidence net was loaded
    valid: np.ndarray  # bool, the view measured the cell (c^t)
    cell_area_px: np.ndarray  # F_size
    fused: np.ndarray  # the fused map after this view
    action: int | None = None  # the move chosen after this view (None after the last)
    action_name: str | None = None
    revisit: bool = False
    reward: float | None = None  # this view's share of R_cls + R_re (search_loop.step_rewards)
    acc: float | None = None  # of the fused map against the ground truth
    f1: float | None = None
    vehicle: int | None = None  # a team's flight: the system id that took the view (written only then)

    def to_json(self) -> str:
        """The search.jsonl line (without the newline)."""
        return dumps_line({"type": "step", **{f.name: getattr(self, f.name) for f in fields(self)
                                              if f.name not in OPTIONAL or getattr(self, f.name) is not None}})

    @classmethod
    def from_json(cls, line: str | dict) -> StepRecord:
        """A step line (text, or already parsed); a malformed one raises a one-line LogError."""
        try:
            rec = json.loads(line) if isinstance(line, (str, bytes)) else line
            if not isinstance(rec, dict) or rec.get("type") != "step":
                raise LogError("not a step record")
            missing = [f.name for f in fields(cls) if f.name not in rec and f.name not in OPTIONAL]
            if missing:
                raise LogError(f"step record lacks {', '.join(missing)}")
        except ValueError as e:
            raise LogError(f"not a JSON line ({str(e).splitlines()[0][:80]})") from None
        values = {}
        for f in fields(cls):
            if f.name in OPTIONAL and f.name not in rec:
                continue
            try:
                values[f.name] = _READ[f.name](rec[f.name])
            except (ValueError, TypeError) as e:
                raise LogError(f"step record field {f.name}: {str(e).splitlines()[0][:80]}") from None
        return cls(**values)


# how each field is read back from JSON
_READ = dict(
    t=_int, sim_time_s=_opt(_num), wall_s=_opt(_num), flight_time_s=_opt(_num), lattice_idx=_opt(_int),
    waypoint_enu=_list(_num), reported_position_enu=_list(_num), reported_rpy_rad=_list(_num),
    true_pose=_opt(_true_pose), image_index=_opt(_int), image=_str, p_occ=_cells(_num, float),
    scores=_opt(_cells(_num, float)), valid=_cells(_bool, bool), cell_area_px=_cells(_num, float),
    fused=_cells(_num, float), action=_opt(_int), action_name=_opt(_str), revisit=_bool, reward=_opt(_num),
    acc=_opt(_num), f1=_opt(_num), vehicle=_opt(_int),
)
OPTIONAL = ("vehicle",)  # fields a line may lack (older logs, one-vehicle flights): absent, not null

__all__ = ["StepRecord", "TruePose", "dumps_line", "jsonable"]
