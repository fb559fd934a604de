"""Replay a flight: re-score it, re-fuse it, draw it, make a video of the occupancy map evolving.

Two inputs:

- a run directory written by `uavsearch fly` (logs/flight_log.py): the logged per-view outputs (p(occupied),
  confidence scores, cells in view, cell areas) are re-fused with the logged method or `--fusion METHOD`
  and re-scored against the ground truth; nothing is re-rendered;
- any MAVLink telemetry log (`FILE.tlog`, ours or another autopilot's, e.g. a MAVSDK survey's): the camera
  is re-rendered in the scene `--scene SEED` at the pose of each CAMERA_IMAGE_CAPTURED (or every
  `--every S` seconds of the logged trajectory), and perception + fusion run on those views.

Outputs in --out: trajectory.png (the track over the scene's top view), maps.png (the fused map after
each view beside the ground truth), metrics.png (Aacc and F1 vs. step), replay.gif or .mp4 (one frame per
view: camera image with the grid, fused map, track so far), replay.json (per-step numbers).

A truncated or corrupt log is read up to the damage with a one-line warning (never a traceback).
"""

from __future__ import annotations

import json
import math
import struct
import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import imageio.v2 as imageio
import numpy as np
import torch
from tqdm import tqdm

from ..errors import LogError, UavsearchError
from ..flight.mavlink import wire_units as wire
from ..fly.missions import WIDE_POLICY, load_mission, mission_from_dict
from ..geometry import CameraIntrinsics, GeodeticOrigin, Grid, camera_pose_from_vehicle
from ..flight.camera import SCENE_FILE
from ..logs.flight_log import read_flight_log, read_header
from ..search.agents import FUSIONS, check_names, make_fusion
from ..search.fusion import Fusion, FusionViews, fusion_name
from ..search.metrics import map_accuracy, map_f1, unseen_counts
from ..search.perception import perceive
from ..search.policy import load_search_model
from ..search.views import make_view
from ..viz import OVERLAY_GRID_RGB, OVERLAY_OCCUPIED_RGB, draw_grid_overlay, pyplot, save_figure
from ..world.render import SceneRenderer
from ..world.scene import generate_scene
from ..world.settings import resolve_k
from ..world.topdown import draw_topdown, topdown_keys

# --------------------------------------------------------------------------------------------------
# tlog reading (robust: stops at the first damaged record)


@dataclass
class TlogTrack:
    """What replay needs from a telemetry log."""

    t_s: np.ndarray  # (K,) log timestamps (UNIX s) of GLOBAL_POSITION_INT
    lla: np.ndarray  # (K, 3) lat, lon (deg), alt AMSL (m)
    rpy_at: list  # [(t_s, (roll, pitch, yaw))] from ATTITUDE
    captures: list  # [dict(t_s, lat, lon, alt, q, index, url)] from CAMERA_IMAGE_CAPTURED
    home: tuple | None  # (lat, lon, alt) from HOME_POSITION
    messages: int
    warning: str | None = None
    sys: np.ndarray | None = None  # (K,) system id of each position (a team's log holds every vehicle's track)

    def rpy(self, t_s: float) -> tuple[float, float, float]:
        if not self.rpy_at:
            return (0.0, 0.0, 0.0)
        ts = np.array([t for t, _ in self.rpy_at])
        return self.rpy_at[int(np.clip(np.searchsorted(ts, t_s), 0, len(ts) - 1))][1]


def read_tlog(path) -> TlogTrack:
    """Parse a .tlog record by record; the first truncated or corrupt record ends it with a warning."""
    from pymavlink.dialects.v20 import common as mavlink

    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise LogError(f"cannot read {path}: {e.strerror or e}") from None
    mav = mavlink.MAVLink(None)
    mav.robust_parsing = False
    t_pos, lla, rpy_at, caps, sys = [], [], [], [], []
    home, n, off, warning = None, 0, 0, None
    while off < len(data):
        if off + 9 > len(data):
            warning = f"{path}: truncated at byte {off} of {len(data)}; read {n} messages before it"
            break
        (usec,) = struct.unpack(">Q", data[off:off + 8])
        magic = data[off + 8]
        if magic == 0xFD and off + 8 + 10 <= len(data):
            plen = data[off + 9]
            size = 10 + plen + 2 + (13 if data[off + 10] & 0x01 else 0)
        elif magic == 0xFE and off + 8 + 6 <= len(data):
            size = 6 + data[off + 9] + 2
        else:
            kind = "truncated" if magic in (0xFD, 0xFE) else "corrupt (no MAVLink start byte)"
            warning = f"{path}: {kind} at byte {off}; read {n} messages before it"
            break
        buf = data[off + 8: off + 8 + size]
        if len(buf) < size:
            warning = f"{path}: truncated at byte {off}; read {n} messages before it"
            break
        try:
            m = mav.decode(bytearray(buf))
        except Exception as e:  # noqa: BLE001 - bad CRC, unknown id: the damage starts here
            if "unknown MAVLink message ID" in str(e) or "Unknown MAVLink message" in str(e):
                off += 8 + size  # a dialect we do not know: skip it, it is not damage
                n += 1
                continue
            warning = f"{path}: corrupt record at byte {off} ({str(e).splitlines()[0][:80]}); read {n} messages before it"
            break
        off += 8 + size
        n += 1
        t = usec * 1e-6
        if t < 1e8 or t > 1e10:  # a timestamp outside 1973..2286 is not a tlog timestamp
            warning = f"{path}: corrupt timestamp at byte {off - 8 - size}; read {n - 1} messages before it"
            break
        typ = m.get_type()
        if typ == "GLOBAL_POSITION_INT" and m.get_srcComponent() in (1, 0):
            t_pos.append(t)
            lla.append(wire.lla(m))
            sys.append(m.get_srcSystem())
        elif typ == "ATTITUDE":
            rpy_at.append((t, (float(m.roll), float(m.pitch), float(m.yaw))))
        elif typ == "CAMERA_IMAGE_CAPTURED":
            url = m.file_url if isinstance(m.file_url, str) else bytes(m.file_url).decode(errors="replace")
            lat, lon, alt = wire.lla(m)
            caps.append(dict(t_s=t, lat=lat, lon=lon, alt=alt, q=list(m.q), sysid=m.get_srcSystem(),
                             index=int(m.image_index), url=url.rstrip("\x00"), ok=int(m.capture_result)))
        elif typ == "HOME_POSITION" and home is None:
            home = wire.home_lla(m)
    if n == 0 and warning is None:
        raise LogError(f"{path}: no MAVLink messages (empty, or not a telemetry log)")
    if n == 0:
        raise LogError(warning.replace("; read 0 messages before it", "") + " (nothing readable)")
    # the same capture is broadcast on every link the log may have recorded: keep the first of each (camera, index)
    seen, unique = set(), []
    for c in caps:
        if (c["sysid"], c["index"]) not in seen and c["ok"] == 1:
            seen.add((c["sysid"], c["index"]))
            unique.append(c)
    return TlogTrack(np.array(t_pos), np.array(lla).reshape(-1, 3), rpy_at, unique, home, n, warning,
                     np.array(sys, dtype=int))


# --------------------------------------------------------------------------------------------------
# One replayed episode, from either source


@dataclass
class ReplayData:
    title: str
    grid: Grid
    labels: np.ndarray  # (N,) bool
    fusion: str
    maps: np.ndarray  # (T, N) fused p(occupied) after each view
    p_occ: np.ndarray  # (T, N)
    valid: np.ndarray  # (T, N)
    positions_enu: np.ndarray  # (T, 3) camera positions of the views (reported)
    track_enu: np.ndarray  # (K, 3) the flown track
    images: list = field(default_factory=list)  # per view: RGB array or None
    poses: list = field(default_factory=list)  # per view: CameraPose (for the grid overlay)
    spec: object = None
    true_positions_enu: np.ndarray | None = None
    logged_maps: np.ndarray | None = None  # the maps the flight itself fused (run dirs)
    track_t: np.ndarray | None = None  # (K,) log time of each track point
    view_t: np.ndarray | None = None  # (T,) log time of each view (to cut the track "so far")
    track_sys: np.ndarray | None = None  # (K,) system id of each track point (a team: one track per vehicle)
    view_sys: np.ndarray | None = None  # (T,) system id that took each view (a team's log; None: one vehicle)
    warnings: list = field(default_factory=list)
    intrinsics: CameraIntrinsics | None = None  # the flight's camera (the mission's), for the grid overlay

    @property
    def acc(self) -> np.ndarray:
        return map_accuracy(self.maps, np.broadcast_to(self.labels, self.maps.shape))

    @property
    def f1(self) -> np.ndarray:
        return map_f1(self.maps, np.broadcast_to(self.labels, self.maps.shape))

    @property
    def seen(self) -> np.ndarray:
        """(T, N) cells some view had measured by view t (the others hold the fusion's prior)."""
        return np.logical_or.accumulate(np.asarray(self.valid, dtype=bool), axis=0)


def _fuse_all(method, p, valid, area=None, scores=None, labels=None, viewpoints=None, logged=None,
              features=None) -> np.ndarray:
    """The fused map after each view, with the inputs the log holds (the method takes what it needs); `method`
    is a name, a spec, or a Fusion object (one fitted on training scenes, loaded from a checkpoint).
    `viewpoints` (T,): each view's lattice index (a neighbour fusion reads its altitude layer); `features`
    (T, N, D): each view's cell features where perception ran again (a tlog's replay); else `logged` (T, N): the
    maps the flight fused, what a fusion reading cell features (which no log holds) replays."""
    if isinstance(method, Fusion):
        fusion, method = method, fusion_name(method)
    elif ":" in method:  # a spec with its prior (a wide-area mission's fusion, e.g. bayes:0.5)
        fusion = make_fusion(method)
    else:
        check_names(fusion=method)
        fusion = FUSIONS[method]()
    if "scores" in fusion.needs and scores is None:
        raise LogError(f"{method} fusion needs confidence scores, which this log does not hold "
                       "(it was flown without a learned confidence network)")
    if "cell_features" in fusion.needs and features is None:
        if logged is None:
            raise LogError(f"{fusion_name(fusion)} reads each view's cell features, which a flight log does not "
                           "hold: replay the flight's own maps (without --fusion) or name another fusion")
        return np.asarray(logged, dtype=float)
    if "viewpoints" in fusion.needs and viewpoints is None:
        raise LogError(f"{fusion_name(fusion)} reads each view's viewpoint, which this log does not hold")

    def t(x):  # one episode: a batch of one
        return None if x is None else torch.as_tensor(np.asarray(x))[None]
    views = FusionViews(t(np.asarray(p, float)), t(np.asarray(valid, bool)), t(area), scores=t(scores),
                        labels=t(labels), viewpoints=None if viewpoints is None else t(np.asarray(viewpoints, np.int64)),
                        cell_features=None if features is None else t(np.asarray(features, np.float32)))
    with torch.no_grad():
        return np.asarray(fusion.prefixes(views)[0], dtype=float)


def _checkpoint_fusion(header: dict) -> Fusion | None:
    """The fusion a flight fused with where a checkpoint holds it (fitted on training scenes, so no name
    rebuilds it): a learned wide-area policy's, saved beside it, or a learned aggregation the mission names
    (neighbour:PATH, a team's); None for every other flight."""
    named = str((header.get("mission") or {}).get("fusion") or "")
    if header.get("policy") != WIDE_POLICY and not named.startswith("neighbour:"):
        return None
    try:
        mission = mission_from_dict(header["mission"], header.get("mission_file"))
        if header.get("policy") != WIDE_POLICY:
            return make_fusion(mission.fusion)
        return load_search_model(mission.checkpoint_path).fusion
    except (UavsearchError, KeyError) as e:
        raise LogError(f"the flight fused with its policy's checkpoint, which cannot be loaded: {e} (give "
                       "--fusion to re-fuse with another method)") from None


def _track_from_tlog(path: Path, origin: GeodeticOrigin):
    """(track ENU (K, 3), track times (K,), system ids (K,), {(system id, image index): capture time}) from a
    run directory's tlog."""
    empty = (np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=int), {})
    if not path.is_file():
        return empty
    try:
        tr = read_tlog(path)
    except LogError:
        return empty
    if not len(tr.lla):
        return empty
    return (origin.geodetic_to_enu(tr.lla), tr.t_s, tr.sys,
            {(c["sysid"], c["index"]): c["t_s"] for c in tr.captures})


def replay_run_dir(run_dir, fusion: str | None = None) -> ReplayData:
    """Re-fuse and re-score a `uavsearch fly` run directory."""
    run_dir = Path(run_dir)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        log = read_flight_log(run_dir)
    if not log.steps:
        raise LogError(f"{run_dir}: the flight log has no completed step to replay"
                       + (f" ({log.failure.get('error')})" if log.failure else ""))
    h = log.header
    grid = Grid(int(h["grid"]["n"]), float(h["grid"]["cell_m"]))
    labels = log.labels
    method = fusion or h["fusion"]
    p, valid, area = log.array("p_occ"), log.array("valid") > 0.5, log.array("cell_area_px")
    scores = None if any(s.scores is None for s in log.steps) else log.array("scores")
    idx = None if any(s.lattice_idx is None for s in log.steps) else [s.lattice_idx for s in log.steps]
    own = None if fusion else _checkpoint_fusion(h)
    maps = _fuse_all(fusion or own or method, p, valid, area, scores, labels, idx,
                     log.array("fused") if own is not None else None)
    images, poses = [], []
    for s in log.steps:
        img = cv2.imread(str(run_dir / s.image), cv2.IMREAD_COLOR)
        images.append(None if img is None else img[..., ::-1].copy())
        poses.append(camera_pose_from_vehicle(s.reported_position_enu, *s.reported_rpy_rad))
    spec, intrinsics = None, None
    try:
        mission = mission_from_dict(h["mission"], h.get("mission_file"))
        spec = mission.scene_spec()
        origin = mission.origin()
        intrinsics = mission.search_config().intrinsics
    except UavsearchError:
        origin = GeodeticOrigin()
    true_pos = [s.true_pose.position_enu if s.true_pose else None for s in log.steps]
    track, track_t, track_sys, cap_t = _track_from_tlog(run_dir / "telemetry.tlog", origin)
    team = any(s.vehicle is not None for s in log.steps)
    one = {i: t for (_, i), t in cap_t.items()}  # one camera: by image index
    view_t = [cap_t.get((s.vehicle, s.image_index)) if team else one.get(s.image_index) for s in log.steps]
    data = ReplayData(
        title=f"{run_dir.name}: {h.get('agent', '')}" + (f", re-fused with {method}" if fusion else ""),
        grid=grid, labels=labels, fusion=method, maps=maps, p_occ=p, valid=valid,
        positions_enu=log.array("reported_position_enu"), track_enu=track, track_t=track_t,
        view_t=None if any(t is None for t in view_t) else np.asarray(view_t, float),
        track_sys=track_sys if team else None,
        view_sys=np.asarray([s.vehicle for s in log.steps], dtype=int) if team else None,
        images=images, poses=poses, spec=spec,
        true_positions_enu=None if any(t is None for t in true_pos) else np.asarray(true_pos, float),
        logged_maps=log.array("fused"), intrinsics=intrinsics,
        warnings=[str(w.message) for w in caught] + ([f"flight ended early: {log.failure.get('error')}"]
                                                    if log.failure else []),
    )
    return data


FOREIGN_HOME_M = 100.0  # a log whose HOME_POSITION is this far from the mission's home was flown elsewhere


def _local_file(url: str) -> Path | None:
    """The file a CAMERA_IMAGE_CAPTURED URL names, when it is a file on this machine that exists."""
    if not url or not url.startswith("file://"):
        return None
    import urllib.parse
    import urllib.request

    path = Path(urllib.request.url2pathname(urllib.parse.urlparse(url).path))
    return path if path.is_file() else None


def _read_rgb(path: Path):
    import cv2

    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    return None if bgr is None else np.ascontiguousarray(bgr[..., ::-1])


def replay_tlog(path, spec, mission, fusion: str | None = None, every_s: float | None = None,
                progress: bool = True) -> ReplayData:
    """Re-render the camera along any MAVLink log's trajectory in `spec` and run perception + fusion."""
    path = Path(path)
    tr = read_tlog(path)
    warns = [tr.warning] if tr.warning else []
    config = mission.search_config()
    method = fusion or mission.fusion
    # The scene origin is the mission's home; the vehicle's HOME_POSITION is where it armed (off the origin by
    # its estimate's error at arming), so it only stands in for a log flown somewhere else entirely.
    origin = mission.origin()
    if tr.home and np.hypot(*origin.geodetic_to_enu(np.asarray(tr.home, float))[:2]) > FOREIGN_HOME_M:
        origin = GeodeticOrigin(*tr.home)
    shots = []  # (t, lla, rpy, image file or None), in log time order
    for c in tr.captures:
        shots.append((c["t_s"], (c["lat"], c["lon"], c["alt"]), wire.rpy_rad(c["q"]), _local_file(c["url"])))
    if every_s:
        t_next = -math.inf
        for t, lla in zip(tr.t_s, tr.lla):
            if t >= t_next and lla[2] - origin.alt_m > 5.0:  # in the air
                shots.append((t, tuple(lla), tr.rpy(t), None))
                t_next = t + every_s
        shots.sort(key=lambda s: s[0])
    rerendered = sum(s[3] is None for s in shots)
    if rerendered:
        warns.append(f"{rerendered} of {len(shots)} view(s) re-rendered at the REPORTED pose (the flight's image at "
                     "its true pose is not on this machine): maps can differ from the flight's")
    if not shots:
        raise LogError(f"{path}: no CAMERA_IMAGE_CAPTURED in the log (and no --every S to sample the track)")
    # the agent gives perception (and the confidence net): its fusion is a name, whatever spec fuses below
    plain = method if isinstance(method, str) and method in FUSIONS else "bayes"
    loaded_mission = mission.model_copy(update={"fusion": plain, "policy": "random"})
    loaded = loaded_mission.agent(config)
    renderer = SceneRenderer(spec, config.intrinsics, config.render)
    p_list, valid_list, area_list, score_list, images, poses, positions = [], [], [], [], [], [], []
    # a spec's fusion built once; one that reads cell features (a learned aggregation) gets perception's, which
    # runs again here
    fuser = make_fusion(method) if isinstance(method, str) and ":" in method else method
    feature_list = [] if isinstance(fuser, Fusion) and "cell_features" in fuser.needs else None
    try:
        for _, lla, rpy, image_file in tqdm(shots, desc="views", disable=not progress, file=sys.stderr):
            pos = origin.geodetic_to_enu(np.asarray(lla, float))
            pose = camera_pose_from_vehicle(pos, *rpy, gimbal_stabilised=True)
            img = _read_rgb(image_file) if image_file is not None else None
            if img is None:
                img = np.asarray(renderer.render(pose, None).rgb)
            view = make_view(img, pose, config.grid, config.intrinsics, None, config.min_cell_area_px)
            with torch.no_grad():
                o, valid, _ = perceive(loaded.perception, [view])
                p_list.append(o.log_probs[0, :, 1].exp().cpu().numpy())
                valid_list.append(valid[0].cpu().numpy())
                area_list.append(view.cell_area_px)
                if loaded.scores_net is not None:
                    score_list.append(loaded.scores_net(o.cell_features)[0].reshape(-1).numpy())
                if feature_list is not None:
                    feature_list.append(o.cell_features[0].float().cpu().numpy())
            images.append(img)
            poses.append(pose)
            positions.append(pos)
    finally:
        renderer.close()
    labels = np.asarray(spec.occupancy_array(), dtype=bool)
    scores = np.stack(score_list) if len(score_list) == len(p_list) else None
    p, valid, area = np.stack(p_list), np.stack(valid_list), np.stack(area_list)
    viewpoints = [config.lattice.nearest(x) for x in positions] if feature_list is not None else None
    maps = _fuse_all(fuser, p, valid, area, scores, labels, viewpoints,
                     features=None if feature_list is None else np.stack(feature_list))
    track = origin.geodetic_to_enu(tr.lla) if len(tr.lla) else np.zeros((0, 3))
    return ReplayData(track_t=tr.t_s, view_t=np.array([s[0] for s in shots]), title=f"{path.name} in scene {spec.seed}: {method} fusion over {len(shots)} views",
                      grid=config.grid, labels=labels, fusion=method, maps=maps, p_occ=p, valid=valid,
                      positions_enu=np.asarray(positions), track_enu=track, images=images, poses=poses, spec=spec,
                      warnings=warns, intrinsics=config.intrinsics)


# --------------------------------------------------------------------------------------------------
# Figures and video


def _vehicle_color(sysid: int | None) -> str:
    """One colour per vehicle of a team (system id), the one-vehicle track's blue otherwise."""
    if sysid is None:
        return "tab:blue"
    return ("tab:blue", "tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:pink")[(int(sysid) - 1) % 6]


ALTITUDE_LAYER_TOL_M = 5.0  # views within this of a layer's altitude were taken at it (reported altitudes wander)


def _altitude_layers(alts) -> list[float]:
    """The altitudes the views were taken at, highest first: one per cluster of reported altitudes."""
    layers: list[float] = []
    for a in sorted(np.asarray(alts, float).tolist(), reverse=True):
        if not layers or layers[-1] - a >= ALTITUDE_LAYER_TOL_M:
            layers.append(a)
    return layers


def _draw_track(ax, d: ReplayData, upto: int | None = None) -> list:
    """The track and views over the scene's top view (up to view `upto`); returns the legend handles (its keys)."""
    if d.spec is not None:
        draw_topdown(d.spec, ax=ax)
    else:
        h = d.grid.half_m
        ax.set_xlim(-h - 20, h + 20)
        ax.set_ylim(-h - 20, h + 20)
        ax.set_aspect("equal")
    n = len(d.positions_enu) if upto is None else upto + 1
    team = d.view_sys is not None
    if len(d.track_enu):
        tr, sys = d.track_enu, d.track_sys
        if upto is not None and d.view_t is not None and d.track_t is not None and len(d.track_t) == len(tr):
            keep = d.track_t <= d.view_t[upto]  # the track up to the moment of that view
            tr, sys = tr[keep], None if sys is None else sys[keep]
        for sid in (sorted(set(d.view_sys.tolist())) if team and sys is not None else [None]):
            part = tr if sid is None else tr[sys == sid]
            ax.plot(part[:, 0], part[:, 1], "-", color="white", lw=3.5, alpha=0.9, zorder=3)
            ax.plot(part[:, 0], part[:, 1], "-", color=_vehicle_color(sid), lw=2.0, zorder=4,
                    label="flown track (telemetry)" if sid is None else f"vehicle {sid}: track and views")
    pos = d.positions_enu[:n]
    layers = _altitude_layers(d.positions_enu[:, 2])  # a wide-area search's 70 m and 40 m views differ in marker
    for k, alt in enumerate(layers):
        at = np.abs(pos[:, 2] - alt) < ALTITUDE_LAYER_TOL_M
        marker, ms = ("o", 7) if k == 0 else ("v", 9)
        where = f" at {alt:.0f} m" if len(layers) > 1 else ""
        if team:
            for sid in sorted(set(d.view_sys.tolist())):
                mine = at & (d.view_sys[:n] == sid)
                ax.plot(pos[mine, 0], pos[mine, 1], marker, color=_vehicle_color(sid), ms=ms, mec="white", zorder=5,
                        label=f"views{where}" if where and sid == min(d.view_sys.tolist()) else None)
        else:
            ax.plot(pos[at, 0], pos[at, 1], marker, color="tab:red", ms=ms, mec="white",
                    label=f"views{where} (reported pose)", zorder=5)
    for i, q in enumerate(pos):
        ax.annotate(str(i + 1), (q[0], q[1]), textcoords="offset points", xytext=(5, 5), color="white",
                    fontsize=9, weight="bold", zorder=7)
    if d.true_positions_enu is not None:
        tp = d.true_positions_enu[:n]
        ax.plot(tp[:, 0], tp[:, 1], "x", color="black", ms=7, label="views (true pose)", zorder=6)
    handles, _ = ax.get_legend_handles_labels()
    return handles + (topdown_keys(d.spec) if d.spec is not None else [])


UNSEEN_COLOR = "#b0b0b0"  # cells no view has measured yet: grey, off the magma scale of p(occupied)
TRUTH_COLOR = "cyan"  # outline of the ground truth's occupied cells on a fused map


def _draw_map(ax, d: ReplayData, t: int, title: str | None = None):
    """The fused map after view t (unseen cells grey, occupied cells outlined); returns the image for a colour bar."""
    import matplotlib

    n = d.grid.n
    h = d.grid.half_m
    cmap = matplotlib.colormaps["magma"].with_extremes(bad=UNSEEN_COLOR)
    shown = np.ma.masked_where(~d.seen[t].reshape(n, n), d.maps[t].reshape(n, n))
    im = ax.imshow(shown, cmap=cmap, vmin=0, vmax=1, extent=[-h, h, -h, h])
    y = d.labels.reshape(n, n)
    for r, c in zip(*np.nonzero(y)):
        x0, y0 = -h + c * d.grid.cell_m, h - (r + 1) * d.grid.cell_m
        ax.add_patch(pyplot().Rectangle((x0, y0), d.grid.cell_m, d.grid.cell_m, fill=False, ec=TRUTH_COLOR, lw=1.5))
    by = f" (vehicle {d.view_sys[t]})" if d.view_sys is not None else ""
    ax.set_title(title or f"fused after view {t + 1}{by}\nacc {d.acc[t]:.2f}  F1 {d.f1[t]:.2f}", fontsize=9)
    ax.set_xticks([])
    ax.set_yticks([])
    return im


def _map_keys(d: ReplayData, upto: int | None = None) -> list:
    """Legend handles of what a fused map draws besides p(occupied): the truth's outlines, unseen cells (if any
    map up to view `upto` has some), with what acc and F1 count them as."""
    from matplotlib.patches import Patch

    keys = [Patch(facecolor="none", edgecolor=TRUTH_COLOR, lw=1.5, label="occupied (ground truth)")]
    last = len(d.maps) - 1 if upto is None else upto
    first = next((t for t in range(last + 1) if not d.seen[t].all()), None)
    if first is not None:
        _, prior, counted = unseen_counts(d.maps[first], d.seen[first])
        keys.append(Patch(facecolor=UNSEEN_COLOR, label=f"unseen (prior {prior:.2g}: counts as {counted})"))
    return keys


def trajectory_figure(d: ReplayData):
    fig, ax = pyplot().subplots(figsize=(7, 7), layout="constrained")
    fig.legend(handles=_draw_track(ax, d), loc="outside lower center", ncol=2, fontsize=7, frameon=False)
    ax.set_title(d.title, fontsize=9, wrap=True)
    return fig


MAPS_COLUMNS = 6  # maps.png: panels per row
MAPS_PANELS = 24  # at most this many (views sampled evenly beyond), so the image stays a readable size


def shown_views(T: int, most: int = MAPS_PANELS - 1) -> list[int]:
    """The views maps.png draws: every one up to `most`, else `most` spread evenly, the first and last kept."""
    if T <= most:
        return list(range(T))
    return sorted({int(round(x)) for x in np.linspace(0, T - 1, most)})


def maps_figure(d: ReplayData):
    """The fused map after each view (sampled evenly past MAPS_PANELS) and the ground truth, in rows of at most
    MAPS_COLUMNS; one colour bar and one key for every panel."""
    T = len(d.maps)
    views = shown_views(T)
    cols = min(MAPS_COLUMNS, len(views) + 1)
    rows = math.ceil((len(views) + 1) / cols)
    fig, axes = pyplot().subplots(rows, cols, figsize=(2.5 * cols + 1.2, 2.75 * rows + 0.9), layout="constrained",
                                  squeeze=False)
    axes = axes.ravel()
    for ax, t in zip(axes, views):
        im = _draw_map(ax, d, t)
    n = d.grid.n
    truth = axes[len(views)]
    truth.imshow(d.labels.reshape(n, n), cmap="magma", vmin=0, vmax=1)
    truth.set_title("ground truth\n(1 = occupied)", fontsize=9)
    truth.set_xticks([])
    truth.set_yticks([])
    for ax in axes[len(views) + 1:]:
        ax.axis("off")
    fig.colorbar(im, ax=list(axes), fraction=0.03 if rows > 1 else 0.015, pad=0.01, label="p(occupied)")
    fig.legend(handles=_map_keys(d), loc="outside lower center", ncol=2, fontsize=8, frameon=False)
    which = f" ({len(views)} of {T} views shown, evenly spread)" if len(views) < T else ""
    fig.suptitle(f"{d.fusion} fusion: p(occupied) per cell after each view{which}", fontsize=10)
    return fig


def metrics_figure(d: ReplayData):
    """Aacc and F1 after each view, as the flight's summary scores the map (unseen cells at the prior included),
    with the share of cells seen so far when some were not: that share is what lifts both early on."""
    from matplotlib.ticker import MaxNLocator

    T = len(d.maps)
    fig, ax = pyplot().subplots(figsize=(5.6, 3.8), layout="constrained")
    steps = np.arange(1, T + 1)
    ax.plot(steps, d.acc, "o-", label="accuracy (Eq. 16)")
    ax.plot(steps, d.f1, "s-", label="F1 (Eq. 17)")
    if d.logged_maps is not None and not np.allclose(d.logged_maps, d.maps, atol=1e-5):  # re-fused: show both
        y = np.broadcast_to(d.labels, d.logged_maps.shape)
        ax.plot(steps, map_f1(d.logged_maps, y), "s--", color="grey", alpha=0.6, label="F1 as flown")
        ax.plot(steps, map_accuracy(d.logged_maps, y), "o--", color="silver", alpha=0.6, label="accuracy as flown")
    note = ""
    first = next((t for t in range(T) if not d.seen[t].all()), None)
    if first is not None:
        _, prior, counted = unseen_counts(d.maps[first], d.seen[first])
        ax.plot(steps, d.seen.mean(axis=1), ":", color="black", label="share of cells seen")
        note = f"\nunseen cells hold the prior {prior:.2g} and count as {counted}"
    ax.set_xlabel("view t")
    ax.set_ylim(0, 1.02)
    ax.xaxis.set_major_locator(MaxNLocator(integer=True, nbins=min(T, 12)))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="lower right")
    ax.set_title(f"metrics after each view ({d.fusion} fusion): final Aacc {d.acc[-1]:.3f}, F1 {d.f1[-1]:.3f}{note}",
                 fontsize=9)
    return fig


def write_figures(d: ReplayData, out: Path) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    return [save_figure(trajectory_figure(d), out / "trajectory.png"), save_figure(maps_figure(d), out / "maps.png"),
            save_figure(metrics_figure(d), out / "metrics.png")]


def frame_figure(d: ReplayData, t: int):
    """One video frame: the view with the grid, the fused map so far, the track so far (a fixed canvas, so
    every frame has the same size; the layout keeps every title and label on it)."""
    fig, axes = pyplot().subplots(1, 3, figsize=(13.5, 4.6), layout="constrained")
    img = d.images[t] if t < len(d.images) else None
    if img is not None:
        intr = d.intrinsics if d.intrinsics is not None else _intrinsics_of(img)
        axes[0].imshow(draw_grid_overlay(img, d.poses[t], d.grid, intr, d.labels, scale=2))
    axes[0].set_title(f"view {t + 1} (grid at the reported pose)", fontsize=9)
    axes[0].axis("off")
    axes[0].legend(handles=_overlay_keys(), loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=2, fontsize=7,
                   frameon=False)
    im = _draw_map(axes[1], d, t)
    fig.colorbar(im, ax=axes[1], fraction=0.046, pad=0.03).set_label("p(occupied)", fontsize=8)
    axes[1].legend(handles=_map_keys(d, upto=t), loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=1,
                   fontsize=7, frameon=False)
    fig.legend(handles=_draw_track(axes[2], d, upto=t), loc="outside right center", fontsize=7, frameon=False)
    axes[2].set_title("track so far", fontsize=9)
    fig.suptitle(d.title, fontsize=9)
    return fig


def _overlay_keys() -> list:
    """Legend handles of draw_grid_overlay's outlines."""
    from matplotlib.lines import Line2D

    return [Line2D([], [], color=np.divide(OVERLAY_GRID_RGB, 255), lw=1, label="grid cell"),
            Line2D([], [], color=np.divide(OVERLAY_OCCUPIED_RGB, 255), lw=2, label="occupied (ground truth)")]


def _frame(d: ReplayData, t: int) -> np.ndarray:
    fig = frame_figure(d, t)
    fig.canvas.draw()
    buf = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    pyplot().close(fig)
    return buf


def _intrinsics_of(img):
    c = CameraIntrinsics()
    return c if (c.height_px, c.width_px) == img.shape[:2] else CameraIntrinsics(img.shape[1], img.shape[0], c.hfov_deg)


def write_video(d: ReplayData, out: Path, fmt: str = "gif", seconds_per_view: float = 1.0) -> Path:
    frames = [_frame(d, t) for t in range(len(d.maps))]
    path = out / f"replay.{fmt}"
    if fmt == "gif":
        imageio.mimsave(path, frames, duration=seconds_per_view * 1000, loop=0)
    else:  # MP4 through OpenCV's bundled FFmpeg (no extra imageio plugin needed)
        h, w = frames[0].shape[:2]
        fps = 10
        vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w - w % 2, h - h % 2))
        if not vw.isOpened():
            raise UavsearchError(f"cannot write {path}: OpenCV has no MP4 encoder here (try --video gif)")
        for f in frames:
            bgr = np.ascontiguousarray(f[: h - h % 2, : w - w % 2, ::-1])
            for _ in range(max(1, int(round(seconds_per_view * fps)))):
                vw.write(bgr)
        vw.release()
    for t, f in enumerate(frames):
        imageio.imwrite(out / f"frame_{t + 1:02d}.png", f)
    return path


def write_replay(d: ReplayData, out, video: str = "gif") -> dict:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    figs = write_figures(d, out)
    vid = write_video(d, out, video)
    res = {"title": d.title, "fusion": d.fusion, "views": len(d.maps),
           "acc": [float(a) for a in d.acc], "f1": [float(f) for f in d.f1],
           "positions_enu": np.round(d.positions_enu, 3).tolist(), "final_map": np.round(d.maps[-1], 4).tolist(),
           "labels": d.labels.astype(int).tolist(), "warnings": d.warnings,
           "files": [p.name for p in figs] + [vid.name]}
    (out / "replay.json").write_text(json.dumps(res, indent=2) + "\n")
    return res


# --------------------------------------------------------------------------------------------------
# What a run folder recorded: replay takes it from there, and a flag may only agree with it


@dataclass
class FlightRecord:
    """What a flight recorded about itself: the mission as flown, its scene, fusion and vehicles."""

    run_dir: Path
    header: dict
    mission: object  # Mission, as flown (mission.json; the header's copy when that is missing)
    seed: int
    setting: int | str | None  # the scene family or paper setting (None: a K given as a number)
    occupied_cells: int
    fusion: str
    vehicles: int

    def scene_text(self) -> str:
        fam = f" of the {self.setting} family" if isinstance(self.setting, str) else \
            f" of setting {self.setting}" if self.setting is not None else ""
        return f"scene {self.seed}{fam} ({self.occupied_cells} occupied cells)"

    def scene_spec(self):
        """The scene the vehicles flew over: the vehicle's own scene.json, else the flown mission's."""
        path = self.run_dir / SCENE_FILE
        if path.is_file():
            from ..world.scene import load_scene

            return load_scene(path)
        return self.mission.scene_spec()


def run_dir_of(src: Path) -> Path | None:
    """The run folder a replay source belongs to: the folder itself, or the one a .tlog lies in (its search.jsonl
    beside it); None for a telemetry log flown elsewhere."""
    if src.is_dir():
        return src
    return src.parent if src.is_file() and (src.parent / "search.jsonl").is_file() else None


def flight_record(run_dir) -> FlightRecord:
    """Read what the run folder recorded (search.jsonl's header, mission.json, scene.json, summary.json); files
    that disagree on the scene are one line (a folder mixing two flights), never a silently wrong score."""
    run_dir = Path(run_dir)
    h = read_header(run_dir)
    data = h.get("mission")
    mfile = run_dir / "mission.json"
    try:
        if mfile.is_file():
            data = json.loads(mfile.read_text())
        mission = mission_from_dict(data, h.get("mission_file"), check_registry=False)
    except (ValueError, OSError, UavsearchError) as e:
        raise LogError(f"{run_dir}: the flown mission cannot be read back: {str(e).splitlines()[0]}") from None
    scene = h.get("scene") or {}
    seed = scene.get("seed", mission.scene.seed)
    seen = {"search.jsonl's header": seed}
    for name, key in ((SCENE_FILE, "seed"), ("summary.json", "scene_seed")):
        try:
            value = json.loads((run_dir / name).read_text()).get(key) if (run_dir / name).is_file() else None
        except (ValueError, OSError, AttributeError):
            value = None  # damaged: the header speaks (read_flight_log warns about a damaged summary)
        if value is not None:
            seen[name] = value
    if len(set(seen.values())) > 1:
        raise LogError(f"{run_dir}: the run folder mixes flights: scene "
                       + ", ".join(f"{v} in {k}" for k, v in seen.items()))
    setting = scene.get("setting", mission.scene.setting if mission.scene.occupied_cells is None else None)
    team = h.get("team") or {}
    return FlightRecord(run_dir, h, mission, int(seed), setting,
                        int(scene.get("occupied_cells", sum(h.get("labels") or []))),
                        str(h.get("fusion", mission.fusion)), int(team.get("vehicles", mission.vehicles)))


def _as_setting(v):
    return int(v) if isinstance(v, str) and v.isdigit() else v


def check_flags(rec: FlightRecord, scene=None, setting=None, occupied_cells=None, mission=None,
                fusion=None) -> None:
    """A flag that contradicts what the flight recorded is a one-line error (--fusion re-fuses on purpose)."""
    said = []
    if scene is not None and int(scene) != rec.seed:
        said.append(f"--scene {scene}")
    if setting is not None:
        s = _as_setting(setting)
        if (rec.setting is not None and _as_setting(rec.setting) != s) or \
                (rec.setting is None and resolve_k(s) != rec.occupied_cells):
            said.append(f"--setting {setting}")
    if occupied_cells is not None and int(occupied_cells) != rec.occupied_cells:
        said.append(f"--occupied-cells {occupied_cells}")
    if mission is not None:
        m = load_mission(mission)
        theirs = []
        if scene is None and int(m.scene.seed) != rec.seed:
            theirs.append(f"scene {m.scene.seed}")
        if (m.scene.setting, m.scene.occupied_cells) != (rec.mission.scene.setting, rec.mission.scene.occupied_cells):
            theirs.append(f"scene setting {m.scene.setting}" if m.scene.occupied_cells is None
                          else f"{m.scene.occupied_cells} occupied cells")
        if fusion is None and m.fusion != rec.fusion:
            theirs.append(f"fusion {m.fusion}")
        if m.vehicles != rec.vehicles:
            theirs.append(f"{m.vehicles} vehicle(s)")
        if theirs:
            said.append(f"--mission {mission} ({', '.join(theirs)})")
    if said:
        raise UavsearchError(f"replay: {' and '.join(said)} contradicts the flight log {rec.run_dir}: it was flown "
                             f"in {rec.scene_text()} with {rec.fusion} fusion and {rec.vehicles} vehicle(s); "
                             "drop the flag to replay what was flown")


# --------------------------------------------------------------------------------------------------
# CLI


def recorded_flight(args) -> FlightRecord | None:
    """What the replayed run folder recorded, after checking the command's flags against it; None for a telemetry
    log flown elsewhere."""
    run = run_dir_of(Path(args.log))
    if run is None:
        return None
    rec = flight_record(run)
    check_flags(rec, args.scene, args.setting, args.occupied_cells, args.mission, args.fusion)
    return rec


def replay_command(args) -> int:
    src = Path(args.log)
    rec = recorded_flight(args)  # what the flight recorded decides the scene, the mission and the fusion
    run = None if rec is None else rec.run_dir
    if src.is_dir():
        d = replay_run_dir(src, args.fusion)
    elif run is not None:  # the run's own tlog: re-rendered in the flown scene with the flown mission
        d = replay_tlog(src, rec.scene_spec(), rec.mission, args.fusion, args.every)
    elif src.is_file():
        if args.scene is None:
            raise UavsearchError("replaying a .tlog needs --scene SEED (the scene to re-render the camera in)")
        mission = load_mission(args.mission)
        if args.occupied_cells is None and args.setting is None and mission.family is not None:
            spec = mission.with_overrides(**{"scene.seed": int(args.scene)}).scene_spec()  # the family's scene
        else:
            k = resolve_k(args.occupied_cells, is_setting=False) if args.occupied_cells is not None \
                else resolve_k(_as_setting(args.setting) if args.setting is not None else 2)
            spec = generate_scene(args.scene, k)
        d = replay_tlog(src, spec, mission, args.fusion, args.every)
    else:
        raise LogError(f"{src}: no such run directory or telemetry log")
    for w in d.warnings:
        print(f"uavsearch: warning: {w}", file=sys.stderr)
    print(f"writing the figures and a {args.video} of {len(d.maps)} view(s) to {args.out} ...", flush=True)
    res = write_replay(d, args.out, args.video)
    print(f"{'view':>4} {'east':>7} {'north':>7} {'up':>6} {'acc':>6} {'F1':>6}")
    for t, (pos, a, f) in enumerate(zip(d.positions_enu, res["acc"], res["f1"])):
        print(f"{t + 1:>4} {pos[0]:7.1f} {pos[1]:7.1f} {pos[2]:6.1f} {a:6.3f} {f:6.3f}")
    print(f"{d.fusion} fusion over {len(d.maps)} view(s): final Aacc {res['acc'][-1]:.3f}  F1 {res['f1'][-1]:.3f}")
    print(f"wrote {', '.join(res['files'])}, frame_*.png, replay.json to {args.out}")
    return 0


__all__ = ["FlightRecord", "ReplayData", "TlogTrack", "check_flags", "flight_record", "read_tlog", "recorded_flight", "run_dir_of", "replay_command", "replay_run_dir", "replay_tlog", "write_replay"]
