"""The camera component (MAVLink compid 100): renders at the TRUE pose, reports the ESTIMATED pose.

A capture renders the scene from `camera_pose_from_vehicle(true position, attitude)` at that
simulation instant, writes `images/img_NNNN.png` in the run directory and returns a CaptureRecord
with the estimated pose the vehicle believed it had (what CAMERA_IMAGE_CAPTURED carries), so that
downstream perception sees the same estimate-vs-truth gap a real drone has. Every capture is also
appended to `captures.jsonl` with both poses, for evaluation and replay.

Storage faults never stop the vehicle: a render or a write that fails (a full disk, a read-only folder) is a
failed capture whose record says why, and interval capture stops by itself when the run directory's disk has
less than a free-space floor left. No shot is lost in silence: a shot that cannot be queued is refused (the
caller says so), a due interval shot waits for a free slot.
"""

from __future__ import annotations

import json
import logging
import math
import shutil
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
import dataclasses
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import UavsearchError
from ..geometry import CameraIntrinsics, CameraPose, camera_pose_from_vehicle

log = logging.getLogger(__name__)
CAMERA_COMPID = 100
SENSOR_WIDTH_MM = 6.17  # a 1/2.3" sensor, for CAMERA_INFORMATION's focal length in mm


@dataclass(frozen=True)
class CaptureRecord:
    index: int
    time_us: int
    path: str
    ok: bool
    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    alt_rel_home_m: float
    q_wxyz: tuple  # estimated vehicle attitude (as PX4 fills CAMERA_IMAGE_CAPTURED.q)
    true_position_enu_m: tuple
    true_rpy_rad: tuple
    error: str = ""  # why the capture failed (a render or a write), for the operator; "" when ok

    @property
    def file_url(self) -> str:
        return Path(self.path).resolve().as_uri()


class CaptureRejected(ValueError):
    """IMAGE_START_CAPTURE values the camera cannot honour (the endpoint answers DENIED)."""


CAPTURE_MIN_INTERVAL_S = 0.1  # 10 Hz of simulation time for a series
CAPTURE_MAX_COUNT = 10_000  # per IMAGE_START_CAPTURE; 0 = until IMAGE_STOP_CAPTURE
MAX_PENDING = 4  # shots commanded or interval-triggered and not yet reported; a command beyond that is refused
NO_SCENE = "no scene to render"  # the error of every capture of a vehicle started without a camera scene
MAX_QUEUED = 64  # shots a mission may queue (its photo items cannot be refused); beyond: skipped, with a notice
CAPTURE_MIN_FREE_MB = 200.0  # interval capture stops below this much free disk (0.1 s interval: ~13 MB a minute)


@dataclass(frozen=True)
class _Shot:
    """What the vehicle was when the shutter fired: rendered later, reported as of that instant."""

    index: int
    time_us: int
    true_position_enu_m: tuple
    true_rpy_rad: tuple
    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    alt_rel_home_m: float
    q_wxyz: tuple


class Camera:
    """Single shots and interval capture; `render` maps a CameraPose to an RGB uint8 image.

    A trigger records the pose at once and hands the render to the camera's own thread (the renderer
    works in its worker process, so the thread mostly waits on a pipe and the GIL is free): the runner's
    loop keeps flying, heartbeating and answering while images render, whatever was asked. `update()`
    returns the shots finished since the last call, in trigger order. `notices` collects what the operator
    must hear (interval capture stopped, a mission photo skipped); the endpoint sends them as STATUSTEXT.
    `min_free_mb()` is the free-space floor for interval capture.
    """

    def __init__(self, vehicle, intrinsics: CameraIntrinsics, run_dir: Path, render: Callable[[CameraPose], np.ndarray] | None,
                 home_alt_amsl_m: Callable[[], float] | None = None, min_free_mb: Callable[[], float] | None = None):
        self.vehicle = vehicle
        self.min_free_mb = min_free_mb or (lambda: CAPTURE_MIN_FREE_MB)
        self.notices: list[str] = []
        self.home_alt_amsl_m = home_alt_amsl_m  # the autopilot's home, for relative altitudes
        self.intrinsics = intrinsics
        self.run_dir = Path(run_dir)
        self.render = render
        self.image_count = 0
        self.dropped = 0  # mission shots skipped because MAX_QUEUED were waiting (each one noticed)
        self.interval_s = 0.0
        self.remaining = 0  # interval captures left; -1 = until stopped
        self._next_us: int | None = None
        self._inflight: deque[Future] = deque()
        self._executor: ThreadPoolExecutor | None = None

    @property
    def available(self) -> bool:
        return self.render is not None

    @property
    def focal_length_mm(self) -> float:
        return self.intrinsics.fx * SENSOR_WIDTH_MM / self.intrinsics.width_px

    @property
    def sensor_size_mm(self) -> tuple[float, float]:
        return SENSOR_WIDTH_MM, SENSOR_WIDTH_MM * self.intrinsics.height_px / self.intrinsics.width_px

    @property
    def capturing_interval(self) -> bool:
        return self.remaining != 0

    @property
    def busy(self) -> bool:
        """Interval capture running or shots still rendering: the runner must keep calling update()."""
        return self.remaining != 0 or bool(self._inflight)

    @property
    def queue_full(self) -> bool:
        """A commanded shot now would wait behind MAX_PENDING others: refuse it (TEMPORARILY_REJECTED)."""
        return len(self._inflight) >= MAX_PENDING

    def free_mb(self) -> float:
        """Free space on the run directory's disk, MB (infinite when it cannot be read: never a reason to stop)."""
        try:
            return shutil.disk_usage(self.run_dir).free / 1e6
        except OSError:
            return math.inf

    def low_on_disk(self) -> str | None:
        """Why interval capture must not run (free space below the floor), else None."""
        free, floor = self.free_mb(), float(self.min_free_mb())
        if free >= floor:
            return None
        return f"{free:.0f} MB free on {self.run_dir} (floor {floor:g} MB)"

    @staticmethod
    def check_start(interval_s: float, count: float) -> tuple[float, int]:
        """IMAGE_START_CAPTURE's (interval, total images) as numbers the camera can honour, else CaptureRejected."""
        if not (math.isfinite(count) and count == int(count) and 0 <= count <= CAPTURE_MAX_COUNT):
            raise CaptureRejected(f"image count must be an integer 0..{CAPTURE_MAX_COUNT} (0: until stopped)")
        n = int(count)
        if not math.isfinite(interval_s) or interval_s < 0:
            raise CaptureRejected("capture interval must be a finite number of seconds >= 0")
        if n != 1 and interval_s < CAPTURE_MIN_INTERVAL_S:
            raise CaptureRejected(f"capture interval must be >= {CAPTURE_MIN_INTERVAL_S} s for more than one image")
        return float(interval_s), n

    def start(self, interval_s: float, count: float) -> None:
        """IMAGE_START_CAPTURE: one shot now (count 1) or a series every interval_s; images come from update()."""
        interval_s, n = self.check_start(interval_s, count)
        self.trigger()
        if n != 1:
            self.interval_s = interval_s
            self.remaining = n - 1 if n > 0 else -1
            self._next_us = self.vehicle.time_us + int(interval_s * 1e6)

    def stop(self) -> None:
        self.remaining = 0
        self._next_us = None

    def update(self) -> list[CaptureRecord]:
        """Fire the interval trigger if due and a slot is free (a due shot waits for one; missed ticks are skipped,
        never caught up); stop the series below the free-space floor. The shots rendered since the last call."""
        now = self.vehicle.time_us
        if self.remaining != 0 and self._next_us is not None and now >= self._next_us and not self.queue_full:
            low = self.low_on_disk()
            if low is not None:
                self.stop()
                self.notices.append(f"camera: interval capture stopped: {low}")
            else:
                self.trigger()
                period = int(self.interval_s * 1e6)
                self._next_us += period * max(1, (now - self._next_us) // period + 1)
                if self.remaining > 0:
                    self.remaining -= 1
        out = []
        while self._inflight and self._inflight[0].done():
            out.append(self._inflight.popleft().result())
        return out

    def trigger(self, limit: int = MAX_PENDING) -> bool:
        """The shutter: record the pose now and start its render; False when `limit` shots already wait
        (the caller refuses the shot or says it was skipped)."""
        if len(self._inflight) >= limit:
            return False
        v = self.vehicle
        ts = v.true_state
        gp = v.global_position
        shot = _Shot(
            index=self.image_count,
            time_us=int(v.time_us),
            true_position_enu_m=tuple(float(x) for x in ts.position_enu_m),
            true_rpy_rad=(float(ts.roll_rad), float(ts.pitch_rad), float(ts.yaw_rad)),
            lat_deg=float(gp.lat_deg),
            lon_deg=float(gp.lon_deg),
            alt_amsl_m=float(gp.alt_amsl_m),
            alt_rel_home_m=float(gp.alt_amsl_m - self.home_alt_amsl_m()) if self.home_alt_amsl_m else float(gp.alt_rel_home_m),
            q_wxyz=tuple(float(x) for x in v.attitude.q_wxyz),
        )
        self.image_count += 1
        if self.render is None:  # nothing to render: the failed capture is reported at once
            done: Future = Future()
            done.set_result(self._record(shot))
            self._inflight.append(done)
        else:
            if self._executor is None:
                self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="camera")
            self._inflight.append(self._executor.submit(self._record, shot))
        return True

    def capture(self) -> CaptureRecord | None:
        """Trigger and wait for the image (callers that may block); earlier shots finish first."""
        return self.drain()[-1] if self.trigger() else None

    def drain(self) -> list[CaptureRecord]:
        """Wait for every shot in flight; their records, in trigger order."""
        out = []
        while self._inflight:
            out.append(self._inflight.popleft().result())
        return out

    def close(self) -> list[CaptureRecord]:
        """Finish the shots in flight (no image is lost) and stop the camera thread."""
        out = self.drain()
        if self._executor is not None:
            self._executor.shutdown(wait=True)
            self._executor = None
        return out

    def queue_mission_shot(self) -> None:
        """A mission's photo item: queued even behind MAX_PENDING (it cannot be refused), skipped with a notice
        only beyond MAX_QUEUED."""
        if not self.trigger(limit=MAX_QUEUED):
            self.dropped += 1
            self.notices.append(f"camera: {MAX_QUEUED} photos waiting, mission photo skipped")

    def _record(self, shot: _Shot) -> CaptureRecord:
        """Render (in the camera thread), write the PNG and the captures.jsonl line; never raises: whatever fails
        (render, PNG, the log line, e.g. on a full disk) makes a failed capture saying why."""
        path = self.run_dir / "images" / f"img_{shot.index:04d}.png"
        error = NO_SCENE if self.render is None else ""
        if self.render is not None:
            try:
                r, p, y = shot.true_rpy_rad
                pose = camera_pose_from_vehicle(np.asarray(shot.true_position_enu_m), r, p, y, gimbal_stabilised=True)
                rgb = self.render(pose)
            except Exception as e:  # noqa: BLE001 - a failed render is a failed capture (capture_result 0), not a crash
                log.warning("capture %d failed", shot.index, exc_info=True)
                error = f"render failed: {type(e).__name__}"
            else:
                error = _write_png(path, rgb)
        rec = CaptureRecord(
            index=shot.index, time_us=shot.time_us, path=str(path), ok=not error, lat_deg=shot.lat_deg,
            lon_deg=shot.lon_deg, alt_amsl_m=shot.alt_amsl_m, alt_rel_home_m=shot.alt_rel_home_m, q_wxyz=shot.q_wxyz,
            true_position_enu_m=shot.true_position_enu_m, true_rpy_rad=shot.true_rpy_rad, error=error,
        )
        log_path = self.run_dir / "captures.jsonl"
        try:
            self.run_dir.mkdir(parents=True, exist_ok=True)
            with open(log_path, "a") as f:
                f.write(json.dumps({**asdict(rec), "file_url": rec.file_url if rec.ok else ""}) + "\n")
        except (OSError, ValueError) as e:  # a full disk: the image has no record, so the capture failed
            rec = dataclasses.replace(rec, ok=False, error=error or f"{_why(e)} writing {log_path}")
        return rec


def _why(e: Exception) -> str:
    return getattr(e, "strerror", None) or type(e).__name__


def _write_png(path: Path, rgb: np.ndarray) -> str:
    """Write the image; "" when written, else why not (cv2 reports a failed write as False, or raises)."""
    import cv2  # lazy: ~50 ms on every `uavsearch` command; the renderer has loaded it by now

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        ok, png = cv2.imencode(".png", np.ascontiguousarray(rgb[..., :3][..., ::-1]))
        if not ok:
            return "PNG encoding failed"
        with open(path, "wb") as f:
            f.write(png.tobytes())
        return ""
    except (OSError, cv2.error) as e:
        try:
            path.unlink(missing_ok=True)  # no half image for a reader to trip on
        except OSError:
            pass
        return f"{_why(e)} writing {path}"


SCENE_FILE = "scene.json"  # the vehicle's ground truth, beside its images (evaluation reads it, never the search)


def background_scene_renderer(scene_seed: int, occupied_cells: int, intrinsics: CameraIntrinsics, run_dir: Path,
                              seed: int = 0, spec=None, seeds=None, options=None):
    """scene_renderer's (render, close), built in a thread: the scene is generated (or `spec` taken), written
    to run_dir/scene.json, and its world built in the render worker while the vehicle starts up and takes
    off; the first capture waits for it. The images are the same as scene_renderer's (with the same `options`:
    a scene family's render options, so the flown camera draws what teleport draws).

    `seeds` (one noise seed per camera): a list of renders instead of one, all drawing the one scene (one
    world, one worker: a team of vehicles does not build the city once per vehicle)."""
    from concurrent.futures import ThreadPoolExecutor

    def build():
        nonlocal spec
        from ..world.render import generate_in_worker  # lazy: see scene_renderer
        from ..world.scene import save_scene

        if spec is None:  # in the render worker that then builds its world: beside this process's start-up
            spec = generate_in_worker(scene_seed, occupied_cells)

        tmp = Path(run_dir) / f".{SCENE_FILE}.tmp"
        save_scene(spec, tmp)
        tmp.replace(Path(run_dir) / SCENE_FILE)  # whole or not at all: a client may be waiting for it
        return scene_renderer(scene_seed, occupied_cells, intrinsics, options, seed=seed, spec=spec,
                              seeds=[seed] if seeds is None else seeds)

    pool = ThreadPoolExecutor(1, thread_name_prefix="scene-world")
    world = pool.submit(build)
    pool.shutdown(wait=False)

    def ready():
        try:
            return world.result()
        except UavsearchError:
            raise
        except Exception as e:  # noqa: BLE001 - one line from the sitl, not a thread's traceback
            raise UavsearchError(f"the camera's scene could not be built: {type(e).__name__}: {e}") from None

    def camera(i: int):
        def render(pose: CameraPose) -> np.ndarray:
            return ready()[0][i](pose)

        return render

    def close() -> None:
        if world.exception() is None:
            world.result()[1]()

    renders = [camera(i) for i in range(1 if seeds is None else len(seeds))]
    return (renders[0] if seeds is None else renders), close


def scene_renderer(scene_seed: int, occupied_cells: int, intrinsics: CameraIntrinsics, options=None, seed: int = 0,
                   spec=None, seeds=None):
    """The foundation's renderer for a generated scene as (render(pose) -> RGB, close()).

    Sensor randomisation (if the options enable it) draws from a generator seeded by (seed, shot
    number), so the same flight gives the same pixels. `seeds`: a list of renders sharing the scene's one
    renderer (one per camera, each with its own noise seed and shot count; calls take turns).
    """
    import threading

    # lazy: PyBullet and the scene generator cost ~0.4 s, and `uavsearch` (any command) imports this module
    from ..world.render import RenderOptions, SceneRenderer
    from ..world.scene import generate_scene

    if spec is None:  # a saved spec (uavsearch scene save) is rendered as it is
        spec = generate_scene(scene_seed, occupied_cells)
    renderer = SceneRenderer(spec, intrinsics, options if options is not None else RenderOptions())
    lock = threading.Lock()  # one worker pipe: cameras of a team render in turn

    def camera(cam_seed: int):
        shots = [0]

        def render(pose: CameraPose) -> np.ndarray:
            rng = np.random.default_rng([cam_seed, scene_seed, shots[0]])
            shots[0] += 1
            with lock:
                return np.asarray(renderer.render(pose, rng).rgb)

        return render

    if seeds is None:
        return camera(seed), renderer.close
    return [camera(s) for s in seeds], renderer.close
