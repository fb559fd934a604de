"""The camera component (MAVLink compid 100): renders at the TRUE pose, reports the ESTIMATED pose.

A capture renders the scene from `camera_pose_from_vehicle(true position, attitude)` at that
simulation instant, writes `images/img_NNNN.png` in the run directory and returns a CaptureRecord
with the estimated pose the vehicle believed it had (what CAMERA_IMAGE_CAPTURED carries), so that
downstream perception sees the same estimate-vs-truth gap a real drone has. Every capture is also
appended to `captures.jsonl` with both poses, for evaluation and replay.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import UavsearchError
from ..geometry import CameraIntrinsics, CameraPose, camera_pose_from_vehicle

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

    @property
    def file_url(self) -> str:
        return Path(self.path).resolve().as_uri()


class Camera:
    """Single shots and interval capture; `render` maps a CameraPose to an RGB uint8 image."""

    def __init__(self, vehicle, intrinsics: CameraIntrinsics, run_dir: Path, render: Callable[[CameraPose], np.ndarray] | None,
                 home_alt_amsl_m: Callable[[], float] | None = None):
        self.vehicle = vehicle
        self.home_alt_amsl_m = home_alt_amsl_m  # the autopilot's home, for relative altitudes
        self.intrinsics = intrinsics
        self.run_dir = Path(run_dir)
        self.render = render
        self.image_count = 0
        self.interval_s = 0.0
        self.remaining = 0  # interval captures left; -1 = until stopped
        self._next_us: int | None = None

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

    def start(self, interval_s: float, count: int) -> list[CaptureRecord]:
        """IMAGE_START_CAPTURE: one shot now (count 1, interval 0) or a series every interval_s."""
        if count == 1 or interval_s <= 0.0:
            return [self.capture() for _ in range(max(count, 1))]
        self.interval_s = interval_s
        self.remaining = count - 1 if count > 0 else -1
        self._next_us = self.vehicle.time_us + int(interval_s * 1e6)
        return [self.capture()]

    def stop(self) -> None:
        self.remaining = 0
        self._next_us = None

    def update(self) -> list[CaptureRecord]:
        """Interval captures due at the current simulation time."""
        out = []
        while self.remaining != 0 and self._next_us is not None and self.vehicle.time_us >= self._next_us:
            out.append(self.capture())
            self._next_us += int(self.interval_s * 1e6)
            if self.remaining > 0:
                self.remaining -= 1
        return out

    def capture(self) -> CaptureRecord:
        v = self.vehicle
        ts = v.true_state
        gp = v.global_position
        q = tuple(float(x) for x in v.attitude.q_wxyz)
        index = self.image_count
        self.image_count += 1
        path = self.run_dir / "images" / f"img_{index:04d}.png"
        ok = False
        if self.render is not None:
            pose = camera_pose_from_vehicle(ts.position_enu_m, ts.roll_rad, ts.pitch_rad, ts.yaw_rad, gimbal_stabilised=True)
            rgb = self.render(pose)
            path.parent.mkdir(parents=True, exist_ok=True)
            import cv2  # lazy: ~50 ms on every `uavsearch` command; the renderer has loaded it by now

            ok = bool(cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., :3][..., ::-1])))
        rec = CaptureRecord(
            index=index,
            time_us=int(v.time_us),
            path=str(path),
            ok=ok,
            lat_deg=float(gp.lat_deg),
            lon_deg=float(gp.lon_deg),
            alt_amsl_m=float(gp.alt_amsl_m),
            alt_rel_home_m=float(gp.alt_amsl_m - self.home_alt_amsl_m()) if self.home_alt_amsl_m else float(gp.alt_rel_home_m),
            q_wxyz=q,
            true_position_enu_m=tuple(float(x) for x in ts.position_enu_m),
            true_rpy_rad=(float(ts.roll_rad), float(ts.pitch_rad), float(ts.yaw_rad)),
        )
        self.run_dir.mkdir(parents=True, exist_ok=True)
        with open(self.run_dir / "captures.jsonl", "a") as f:
            f.write(json.dumps({**asdict(rec), "file_url": rec.file_url if ok else ""}) + "\n")
        return rec


SCENE_FILE = "scene.json"  # the vehicle's ground truth, beside its images (evaluation reads it, never the search)


def background_scene_renderer(scene_seed: int, occupied_cells: int, intrinsics: CameraIntrinsics, run_dir: Path,
                              seed: int = 0, spec=None):
    """scene_renderer's (render, close), built in a thread: the scene is generated (or `spec` taken), written
    to run_dir/scene.json, and its world built in the render worker while the vehicle starts up and takes
    off; the first capture waits for it. The images are the same as scene_renderer's."""
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
        return scene_renderer(scene_seed, occupied_cells, intrinsics, seed=seed, spec=spec)

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

    def render(pose: CameraPose) -> np.ndarray:
        return ready()[0](pose)

    def close() -> None:
        if world.exception() is None:
            world.result()[1]()

    return render, close


def scene_renderer(scene_seed: int, occupied_cells: int, intrinsics: CameraIntrinsics, options=None, seed: int = 0,
                   spec=None):
    """The foundation's renderer for a generated scene as (render(pose) -> RGB, close()).

    Sensor randomisation (if the options enable it) draws from a generator seeded by (seed, shot
    number), so the same flight gives the same pixels.
    """
    # lazy: PyBullet and the scene generator cost ~0.4 s, and `uavsearch` (any command) imports this module
    from ..world.render import RenderOptions, SceneRenderer
    from ..world.scene import generate_scene

    if spec is None:  # a saved spec (uavsearch scene save) is rendered as it is
        spec = generate_scene(scene_seed, occupied_cells)
    renderer = SceneRenderer(spec, intrinsics, options if options is not None else RenderOptions())
    shots = [0]

    def render(pose: CameraPose) -> np.ndarray:
        rng = np.random.default_rng([seed, scene_seed, shots[0]])
        shots[0] += 1
        return np.asarray(renderer.render(pose, rng).rgb)

    return render, renderer.close
