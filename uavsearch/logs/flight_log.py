"""A flight log is one run directory, written as the flight goes so a flight killed mid-air stays readable:

    telemetry.tlog   every MAVLink packet both ways (8-byte big-endian UNIX microseconds + raw packet),
                     readable by pymavlink's mavlogdump.py, MAVProxy and QGroundControl; stamped on the
                     vehicle's simulated clock from the wall time the flight started (see tlog.py)
    search.jsonl     line 1: {"type": "header", mission, scene, ground truth, grid, ...};
                     then one {"type": "step", ...} per view (sim time, commanded waypoint, reported and
                     true pose, image file, per-cell p(occupied), confidence scores, cells in view, cell
                     areas, fused map, action, reward, metrics); a {"type": "failure"} line if a step failed
    images/          the PNGs the camera wrote (img_NNNN.png)
    captures.jsonl   the simulated camera's own record (true and estimated pose per image)
    summary.json     the result: a provisional one (status "running", what is kept so far) from the header on,
                     rewritten after each view and at the end; a fault's summary says what was kept

Every line is flushed and fsync'ed when written; a reader skips a torn last line with a warning. summary.json is
replaced atomically (a temporary file in the folder, fsync, rename), so the last good one survives a full disk,
and a reserve file holds the room for the final one until it is written.
"""

from __future__ import annotations

import json
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import LogError
from .step_record import StepRecord, dumps_line, jsonable
from .tlog import TlogWriter

FORMAT = "uavsearch-flight-log/1"
RESERVE = ".summary.reserve"  # room kept for the final summary.json while the flight fills the disk


def _reserve_bytes(cells: int) -> int:
    """Room for a summary: its fused map and labels take about 40 bytes a cell (indented JSON)."""
    return 16384 + 48 * int(cells)


def write_atomic(path: Path, text: str) -> None:
    """Replace `path` with `text` so a reader sees the old file or the new one, never half of one."""
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with open(tmp, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except OSError:
        tmp.unlink(missing_ok=True)  # a full disk: leave no half-written file beside the log
        raise
    try:
        fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(fd)  # the rename itself
        finally:
            os.close(fd)
    except OSError:
        pass


class FlightLogWriter:
    """Appends the search records of one run directory; owns its telemetry tlog."""

    def __init__(self, run_dir, tlog: bool = True):
        self.run_dir = Path(run_dir)
        self.run_dir.mkdir(parents=True, exist_ok=True)
        (self.run_dir / "images").mkdir(exist_ok=True)
        self.tlog = TlogWriter(self.run_dir / "telemetry.tlog", clock="sim") if tlog else None
        self._f = open(self.run_dir / "search.jsonl", "a")
        self.views = 0  # step records written
        self._known: dict = {}  # the provisional summary's fields from the header
        self._final = False  # the final summary is written: no provisional one replaces it
        self._header_fields = None  # header_later's callable, until the header is written

    def _write(self, record: dict | str) -> None:
        self._f.write((record if isinstance(record, str) else dumps_line(record)) + "\n")
        self._f.flush()
        os.fsync(self._f.fileno())
        if self.tlog is not None:
            self.tlog.flush()

    def header(self, **fields) -> None:
        self._write({"type": "header", "format": FORMAT, **fields})
        scene = fields.get("scene") or {}
        self._known = {k: v for k, v in (("mission", (fields.get("mission") or {}).get("name")),
                                         ("scene_seed", scene.get("seed")),
                                         ("started_utc", fields.get("started_utc"))) if v is not None}
        try:
            with open(self.run_dir / RESERVE, "wb") as f:
                f.write(bytes(_reserve_bytes(np.size(fields.get("labels", ())))))
                f.flush()
                os.fsync(f.fileno())
        except OSError:
            (self.run_dir / RESERVE).unlink(missing_ok=True)
        self._provisional()

    def header_later(self, fields) -> None:
        """The header from `fields()`, written by `write_header()` or else just before the first record after it:
        a flight arms while its models load, and the header names them (nothing that follows a header comes
        before it)."""
        self._header_fields = fields

    def write_header(self) -> None:
        """header_later's header, now (once; nothing if there is none pending)."""
        if self._header_fields is not None:
            fields, self._header_fields = self._header_fields, None
            self.header(**fields())

    def step(self, record: StepRecord) -> None:
        self.write_header()
        self._write(record.to_json())
        self.views += 1
        self._provisional()

    def failure(self, **fields) -> None:
        self.write_header()
        self._write({"type": "failure", **fields})

    def kept(self) -> dict:
        """What the run folder holds now: views recorded, photos on disk, telemetry bytes."""
        if self.tlog is not None:
            self.tlog.flush()
        tlog = self.run_dir / "telemetry.tlog"
        photos = sum(1 for p in self.run_dir.glob("**/images/*.png") if p.stat().st_size > 0)
        return {"views": self.views, "photos": photos, "tlog_bytes": tlog.stat().st_size if tlog.is_file() else 0}

    def _provisional(self) -> None:
        """summary.json while flying: replaced at the end; one still "running" is a flight that was killed. A
        disk too full for it keeps the last good one (the flight goes on)."""
        if self._final:
            return
        try:
            write_atomic(self.run_dir / "summary.json", json.dumps(
                {"status": "running", **self._known, "kept": self.kept()}, indent=2) + "\n")
        except OSError:
            pass

    def summary(self, summary: dict) -> Path:
        """The final summary; one of a flight that did not complete says what was kept. On a full disk the
        reserve makes room for it."""
        self.write_header()
        if summary.get("status") != "completed":
            summary = {**summary, "kept": self.kept()}
        path = self.run_dir / "summary.json"
        text = json.dumps(jsonable(summary), indent=2) + "\n"
        try:
            write_atomic(path, text)
        except OSError:
            if not (self.run_dir / RESERVE).is_file():
                raise
            (self.run_dir / RESERVE).unlink()
            write_atomic(path, text)
        self._final = True
        (self.run_dir / RESERVE).unlink(missing_ok=True)
        return path

    def close(self) -> None:
        if self._f is not None:
            try:
                self._f.close()
            except OSError:  # a record the disk had no room for already failed its write (and said so)
                pass
            self._f = None
        if self.tlog is not None:
            self.tlog.close()
        (self.run_dir / RESERVE).unlink(missing_ok=True)


@dataclass
class FlightLog:
    """A run directory read back: header, step records (in order), optional failure and summary."""

    run_dir: Path
    header: dict
    steps: list[StepRecord]
    failure: dict | None
    summary: dict | None
    warning: str | None  # set when the file was damaged (read up to the damage)

    @property
    def labels(self) -> np.ndarray:
        return np.asarray(self.header["labels"], dtype=bool)

    def array(self, key: str) -> np.ndarray:
        """A per-step field stacked over steps, e.g. array('p_occ') -> (T, N)."""
        return np.asarray([getattr(s, key) for s in self.steps], dtype=float)


def read_header(run_dir) -> dict:
    """search.jsonl's header line alone (what the flight recorded before its first view), or a one-line
    LogError."""
    path = Path(run_dir) / "search.jsonl"
    if not path.is_file():
        raise LogError(f"{run_dir} is not a flight log: no search.jsonl")
    try:
        with open(path, "rb") as f:
            rec = json.loads(f.readline().decode("utf-8"))
    except OSError as e:
        raise LogError(f"{run_dir} is not a flight log: {e.strerror or e}") from None
    except (ValueError, UnicodeDecodeError):
        rec = None
    if not isinstance(rec, dict) or rec.get("type") != "header":
        raise LogError(f"{path}: no header line (not a uavsearch flight log, or damaged at the start)")
    if rec.get("format") != FORMAT:
        raise LogError(f"{path}: unknown format {rec.get('format')!r} (expected {FORMAT})")
    return rec


def read_flight_log(run_dir) -> FlightLog:
    """Read search.jsonl (and summary.json); a torn or corrupt line ends the read with a warning, a whole
    JSON line that is no valid step record raises a one-line LogError."""
    run_dir = Path(run_dir)
    path = run_dir / "search.jsonl"
    if not path.is_file():
        raise LogError(f"{run_dir} is not a flight log: no search.jsonl")
    header, steps, failure, warning = None, [], None, None
    with open(path, "rb") as f:
        for n, raw in enumerate(f, 1):
            try:
                rec = json.loads(raw.decode("utf-8"))
                if not isinstance(rec, dict) or "type" not in rec:
                    raise ValueError("not a record")
            except (ValueError, UnicodeDecodeError):
                warning = f"{path}: damaged at line {n}; read the {len(steps)} step(s) before it"
                break
            if rec["type"] == "header":
                header = rec
            elif header is None:
                break  # not a flight log (no header first): said below
            elif rec["type"] == "step":
                try:
                    steps.append(StepRecord.from_json(rec))
                except LogError as e:
                    raise LogError(f"{path}: line {n}: {e}") from None
            elif rec["type"] == "failure":
                failure = rec
    if header is None:
        raise LogError(f"{path}: no header line (not a uavsearch flight log, or damaged at the start)")
    if header.get("format") != FORMAT:
        raise LogError(f"{path}: unknown format {header.get('format')!r} (expected {FORMAT})")
    summary = None
    sp = run_dir / "summary.json"
    if sp.is_file():
        try:
            summary = json.loads(sp.read_text())
        except ValueError:
            warning = warning or f"{sp}: damaged; ignored"
    if warning:
        warnings.warn(warning, stacklevel=2)
    return FlightLog(run_dir, header, steps, failure, summary, warning)


__all__ = ["FORMAT", "FlightLog", "FlightLogWriter", "StepRecord", "read_flight_log", "read_header"]
