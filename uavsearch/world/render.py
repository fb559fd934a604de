"""PyBullet camera for a scene spec: RGB, person segmentation, supersampling, optional sensor randomisation.

How the world is built (fast: a scene takes well under a second):
- the ground is painted into ONE texture: roads, markings, sidewalks, grass and plazas
  (topdown.paint_ground). By default (RenderOptions.ground = "composite") TinyRenderer never draws it:
  the texture, shaded once exactly as TinyRenderer shades it, is warped to the camera with the ground
  homography and laid under the bodies where no body is nearer (GroundCompositor), which halves the
  per-pixel work; ground = "mesh" draws it as a textured quad, the reference;
- every other static object is merged into a few large meshes textured with a colour palette
  (one texel per colour, uvs at texel centres), so thousands of objects are a handful of bodies; with
  the composite ground they are grouped in square tiles, and each view hides the tiles it cannot see;
- every person is its own small body, so the segmentation mask gives exact person pixels and ids.
The camera matches uavsearch.geometry exactly: the view and projection matrices are built from
CameraPose and CameraIntrinsics (pinhole, principal point at the centre, OpenCV axes), not from
PyBullet's look-at/FOV helpers; tests/test_render.py checks markers land on project_points' pixels.

Supersampling renders at s times the resolution and averages s x s blocks (area downsampling), so a
person smaller than a pixel stays a faint blob instead of appearing or vanishing with aliasing.
person_fraction is the share of a pixel's subpixels showing a person; person_mask is
person_fraction > 0 (any subpixel), i.e. every pixel whose colour a person contributed to.
"""

from __future__ import annotations

import atexit
import ctypes
import math
import os
import pickle
import subprocess
import sys
import tempfile
import weakref
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..geometry import CameraIntrinsics, CameraPose
from .scene import SceneObject, SceneSpec, scene_from_json, scene_to_json
from .topdown import ground_raster, paint_ground


def _import_pybullet():
    """Import pybullet without its 'pybullet build time' banner on stdout (printed from C at import)."""
    sys.stdout.flush()
    saved, devnull = os.dup(1), os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    try:
        import pybullet

        ctypes.CDLL(None).fflush(None)
    finally:
        os.dup2(saved, 1)
        os.close(saved)
        os.close(devnull)
    return pybullet


class _LazyPybullet:
    """pybullet, imported on first use: a parent process whose worlds live in workers never loads it."""

    _mod = None

    def __getattr__(self, name):
        if _LazyPybullet._mod is None:
            _LazyPybullet._mod = _import_pybullet()
        return getattr(_LazyPybullet._mod, name)


pb = _LazyPybullet()

NEAR_M = 1.0
FAR_M = 1000.0
PALETTE_SIDE = 64  # texels per side of a palette texture, at least: 4096 colours; it doubles when more are needed
MAX_VERTICES = 90_000  # PyBullet refuses meshes of about 131k vertices and more
GROUND_MODES = ("composite", "mesh")
CULL_TILE_M = 20.0  # side of the square tiles the static objects are grouped into (composite ground)
CULL_MARGIN_PX = 2.0  # a body counts as in view this far (supersampled pixels) outside the image


@dataclass(frozen=True)
class RenderOptions:
    """How images are made. Randomisation is OFF by default (all zeros): the paper's AirSim frames are
    clean renders, the difficulty comes from size, occlusion and confusers, and the teleport env caches
    renders; turn it on (e.g. RenderOptions.randomised()) for training-time augmentation.
    It is applied only when render() gets an rng."""

    supersample: int = 2
    noise_std: float = 0.0  # max Gaussian sensor noise, in 0-255 grey levels (the std is drawn in [0, max])
    blur_sigma_px: float = 0.0  # max Gaussian blur sigma in output pixels (drawn in [0, max])
    exposure_jitter: float = 0.0  # gain drawn in [1 - j, 1 + j]
    ambient: float = 0.62
    diffuse: float = 0.42
    isolate: bool = True  # build the PyBullet world in a recycled worker process (PyBullet leaks memory)
    # "composite": TinyRenderer draws the bodies, the ground is the shaded texture warped to the camera (a
    # homography) under them: the same pixels (tools/compare_render.py: 96 of 100 views identical, the
    # rest >= 58 dB PSNR, person masks identical) in about half the time. "mesh": the ground is a textured
    # quad drawn by TinyRenderer, the reference. Left out of repr, so view sets, caches and the world tag
    # made with either stay valid for the other.
    ground: str = field(default="composite", repr=False)

    @staticmethod
    def randomised(supersample: int = 2, isolate: bool = True) -> "RenderOptions":
        return RenderOptions(supersample=supersample, noise_std=4.0, blur_sigma_px=0.7, exposure_jitter=0.15,
                             isolate=isolate)  # fmt: skip


@dataclass(frozen=True)
class Render:
    rgb: np.ndarray  # (H, W, 3) uint8
    person_mask: np.ndarray  # (H, W) bool: at least one subpixel shows a person
    person_fraction: np.ndarray  # (H, W) float32: share of subpixels showing a person
    person_index: np.ndarray  # (H, W) int16: index into spec.people of the person covering most subpixels, -1 none


# --------------------------------------------------------------------------------------------------
# Camera matrices (OpenGL, column-major), built from the geometry module's camera model


def view_matrix(pose: CameraPose) -> list[float]:
    """World -> OpenGL eye coordinates (x right, y up, looking down -z) for an OpenCV-axes camera pose."""
    r_cv_from_world = pose.R_enu_from_cam.T
    r = np.diag([1.0, -1.0, -1.0]) @ r_cv_from_world
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = -r @ np.asarray(pose.position_enu, dtype=float)
    return m.T.ravel().tolist()


# TinyRenderer rasterises at pixel corners, not centres: without a correction its image sits half a pixel
# right of and above the pinhole model (measured: +0.5 px in u, -0.5 px in v, at every resolution).
TINY_RENDERER_SHIFT_PX = (0.5, -0.5)


def projection_matrix(
    intr: CameraIntrinsics, near_m: float = NEAR_M, far_m: float = FAR_M, shift_px=TINY_RENDERER_SHIFT_PX
) -> list[float]:
    """The pinhole K as an OpenGL projection: pixel (u, v) with v down <-> NDC (x, y) with y up.

    `shift_px` is the renderer's own offset, cancelled so that rendered pixels agree with project_points.
    """
    w, h = intr.width_px, intr.height_px
    m = np.zeros((4, 4))
    m[0, 0] = 2.0 * intr.fx / w
    m[1, 1] = 2.0 * intr.fy / h
    m[0, 2] = 1.0 - 2.0 * intr.cx / w + 2.0 * shift_px[0] / w
    m[1, 2] = 2.0 * intr.cy / h - 1.0 - 2.0 * shift_px[1] / h
    m[2, 2] = -(far_m + near_m) / (far_m - near_m)
    m[2, 3] = -2.0 * far_m * near_m / (far_m - near_m)
    m[3, 2] = -1.0
    return m.T.ravel().tolist()


# --------------------------------------------------------------------------------------------------
# Meshes


def _unit_box() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangles (T, 3, 3), normals (T, 3, 3) and face group (T,) of a unit cube [-.5,.5]^2 x [0, 1];
    groups: 0 = sides, 1 = top (no bottom face: nobody looks at it)."""
    tris, norms, groups = [], [], []
    faces = [((1, 0, 0), (0, 1, 0), (0, 0, 1), 0), ((-1, 0, 0), (0, -1, 0), (0, 0, 1), 0),
             ((0, 1, 0), (-1, 0, 0), (0, 0, 1), 0), ((0, -1, 0), (1, 0, 0), (0, 0, 1), 0),
             ((0, 0, 1), (1, 0, 0), (0, 1, 0), 1)]  # fmt: skip
    for n, u, v, g in faces:
        n, u, v = (np.array(a, float) for a in (n, u, v))
        q = [(n + a * u + b * v) * 0.5 for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
        q = [c + np.array([0, 0, 0.5]) for c in q]
        for tri in ((q[0], q[1], q[2]), (q[0], q[2], q[3])):
            tris.append(tri)
            norms.append((n, n, n))
            groups.append(g)
    return np.array(tris), np.array(norms), np.array(groups)


def _unit_prism(n: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit-diameter n-gon prism from z=0 to 1 (groups: 0 sides, 1 top), smooth side normals."""
    a = np.arange(n + 1) * 2 * np.pi / n
    ring = np.stack([0.5 * np.cos(a), 0.5 * np.sin(a)], -1)
    nrm = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], -1)
    tris, norms, groups = [], [], []
    for i in range(n):
        p0, p1 = ring[i], ring[i + 1]
        b0, b1, t0, t1 = [*p0, 0], [*p1, 0], [*p0, 1], [*p1, 1]
        tris += [(b0, b1, t1), (b0, t1, t0)]
        norms += [(nrm[i], nrm[i + 1], nrm[i + 1]), (nrm[i], nrm[i + 1], nrm[i])]
        groups += [0, 0]
        tris.append(([0, 0, 1], t0, t1))
        norms.append(([0, 0, 1],) * 3)
        groups.append(1)
    return np.array(tris, float), np.array(norms, float), np.array(groups)


def _unit_sphere(n_lon: int = 7, n_lat: int = 4) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit-diameter low-poly sphere centred at z=0.5, smooth normals; group = face index mod 3 (shades)."""
    lat = np.linspace(-np.pi / 2, np.pi / 2, n_lat + 1)
    lon = np.linspace(0, 2 * np.pi, n_lon + 1)

    def pt(i, j):
        return np.array([math.cos(lat[i]) * math.cos(lon[j]), math.cos(lat[i]) * math.sin(lon[j]), math.sin(lat[i])])

    tris, norms = [], []
    for i in range(n_lat):
        for j in range(n_lon):
            a, b, c, d = pt(i, j), pt(i, j + 1), pt(i + 1, j + 1), pt(i + 1, j)
            for tri in ((a, b, c), (a, c, d)):
                if np.linalg.norm(np.cross(tri[1] - tri[0], tri[2] - tri[0])) < 1e-9:
                    continue  # degenerate at the poles
                tris.append(tri)
                norms.append(tri)
    tris = np.array(tris) * 0.5 + np.array([0, 0, 0.5])
    return tris, np.array(norms), np.arange(len(tris)) % 3


BOX, PRISM, SPHERE = _unit_box(), _unit_prism(8), _unit_sphere()


def _rot(yaw: float, pitch: float = 0.0) -> np.ndarray:
    """Rotation about z by yaw after a tilt about the local y axis by pitch."""
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    return rz @ ry


class Palette:
    """Distinct colours -> texels of one palette texture (one texel per colour). Its side is the smallest
    power of two from PALETTE_SIDE that holds them all, so a palette never overflows; the world keeps one
    for the static objects and one for the people, so many people never crowd the city's colours."""

    def __init__(self):
        self.index: dict[tuple[int, int, int], int] = {}

    def colour_index(self, rgb) -> int:
        return self.index.setdefault(tuple(int(c) for c in rgb), len(self.index))

    @property
    def side(self) -> int:
        side = PALETTE_SIDE
        while side * side < len(self.index):
            side *= 2
        return side

    def image(self) -> np.ndarray:
        """(side, side, 3) uint8: colour i at row i // side, column i % side."""
        img = np.zeros((self.side, self.side, 3), np.uint8)
        for rgb, i in self.index.items():
            img[i // self.side, i % self.side] = rgb
        return img


class MeshBuilder:
    """Accumulates coloured primitives into triangle soup with palette uvs."""

    def __init__(self, palette: Palette):
        self.palette = palette
        self.pos: list[np.ndarray] = []
        self.nrm: list[np.ndarray] = []
        self.col: list[np.ndarray] = []

    def add(self, unit, centre, scale, rot: np.ndarray, colours) -> None:
        """Place a unit primitive: scale (3,), rotation, base centre (3,); colours per face group."""
        tris, norms, groups = unit
        scale = np.asarray(scale, float)
        p = (tris * scale) @ rot.T + np.asarray(centre, float)
        n = (norms / np.where(scale == 0, 1, scale)) @ rot.T
        n /= np.linalg.norm(n, axis=-1, keepdims=True) + 1e-12
        idx = np.array([self.palette.colour_index(colours[min(g, len(colours) - 1)]) for g in range(3)])
        self.pos.append(p.reshape(-1, 3))
        self.nrm.append(n.reshape(-1, 3))
        self.col.append(np.repeat(idx[groups], 3))

    def add_object(self, o: SceneObject) -> None:
        add_object_parts(self, o)

    def arrays(self):
        """Vertices, normals and uvs at texel centres (call once the palette holds every colour)."""
        if not self.pos:
            return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 2))
        pos, nrm, col = np.concatenate(self.pos), np.concatenate(self.nrm), np.concatenate(self.col)
        side = self.palette.side
        uv = np.stack([(col % side + 0.5) / side, 1.0 - (col // side + 0.5) / side], -1)
        return pos, nrm, uv


def _shade(rgb, f: float):
    return tuple(int(np.clip(c * f, 0, 255)) for c in rgb)


def add_object_parts(mb: MeshBuilder, o: SceneObject) -> None:
    """The 3-D shape of each kind of object, from its footprint, height and colours."""
    x, y, z, yaw = o.x_m, o.y_m, o.z_m, o.yaw_rad
    r = _rot(yaw)

    def at(dx, dy, dz=0.0):
        return np.array([x, y, z]) + r @ np.array([dx, dy, dz])

    if o.kind == "building":
        mb.add(BOX, (x, y, z), (o.sx_m, o.sy_m, o.sz_m), r, [o.color, o.color2 or o.color])
        # a parapet rim makes roofs read as roofs from above
        t = 0.35
        rim = _shade(o.color2 or o.color, 0.8)
        for dx, dy, sx, sy in ((0, o.sy_m / 2 - t / 2, o.sx_m, t), (0, -o.sy_m / 2 + t / 2, o.sx_m, t),
                               (o.sx_m / 2 - t / 2, 0, t, o.sy_m), (-o.sx_m / 2 + t / 2, 0, t, o.sy_m)):  # fmt: skip
            mb.add(BOX, at(dx, dy, o.sz_m), (sx, sy, 0.5), r, [o.color, rim])
    elif o.kind == "roof_unit":
        mb.add(BOX, (x, y, z), (o.sx_m, o.sy_m, o.sz_m), r, [_shade(o.color, 0.85), o.color])
    elif o.kind == "tree":
        trunk_h = o.sz_m - o.sx_m * 0.9
        mb.add(PRISM, (x, y, 0), (0.3, 0.3, max(trunk_h + 0.5, 0.5)), r, [o.color2, o.color2])
        c1, c2, c3 = o.color, _shade(o.color, 0.85), _shade(o.color, 1.12)
        canopy_h = o.sz_m - trunk_h
        mb.add(SPHERE, (x, y, trunk_h), (o.sx_m, o.sy_m, canopy_h), r, [c1, c2, c3])
    elif o.kind == "car":
        h = o.sz_m
        body_h = h * (0.85 if o.variant == "van" else 0.55)
        mb.add(BOX, at(0, 0, 0.15), (o.sx_m, o.sy_m, body_h), r, [o.color, o.color])
        if o.variant == "van":
            mb.add(BOX, at(o.sx_m * 0.36, 0, 0.15 + body_h * 0.45), (o.sx_m * 0.2, o.sy_m * 0.92, body_h * 0.5), r,
                   [o.color2, o.color])  # fmt: skip
        else:
            mb.add(BOX, at(-o.sx_m * 0.05, 0, 0.15 + body_h), (o.sx_m * 0.5, o.sy_m * 0.86, h - body_h - 0.15), r,
                   [o.color2, o.color])  # fmt: skip
    elif o.kind == "clutter":
        v = o.variant
        if v in ("bin", "bollard", "cone"):
            top = _shade(o.color, 0.7) if v == "bin" else o.color
            scale = (o.sx_m, o.sy_m, o.sz_m) if v != "cone" else (o.sx_m, o.sy_m, o.sz_m * 0.15)
            mb.add(PRISM, (x, y, 0), scale, r, [o.color, top])
            if v == "cone":
                mb.add(PRISM, (x, y, 0), (o.sx_m * 0.55, o.sy_m * 0.55, o.sz_m), r, [o.color, (240, 240, 236)])
        elif v == "bench":
            mb.add(BOX, at(0, 0, 0.4), (o.sx_m, o.sy_m * 0.8, 0.08), r, [o.color, o.color])
            mb.add(BOX, at(0, -o.sy_m * 0.45, 0.4), (o.sx_m, 0.08, 0.45), r, [o.color, o.color])
            for dx in (-o.sx_m * 0.4, o.sx_m * 0.4):
                mb.add(BOX, at(dx, 0, 0), (0.08, o.sy_m * 0.7, 0.4), r, [(50, 50, 54), (50, 50, 54)])
        elif v == "planter":
            mb.add(BOX, (x, y, 0), (o.sx_m, o.sy_m, o.sz_m), r, [o.color, o.color2 or o.color])
        elif v == "lamp":
            mb.add(PRISM, (x, y, 0), (o.sx_m, o.sy_m, o.sz_m), r, [o.color, o.color])
            mb.add(BOX, (x, y, o.sz_m - 0.15), (0.7, 0.35, 0.15), r, [o.color, (230, 230, 200)])
        elif v == "parasol":
            mb.add(PRISM, (x, y, 0), (0.08, 0.08, o.sz_m), r, [(200, 200, 200), (200, 200, 200)])
            mb.add(PRISM, (x, y, o.sz_m - 0.3), (o.sx_m, o.sy_m, 0.3), r, [_shade(o.color, 0.8), o.color])
        elif v == "fountain":
            mb.add(PRISM, (x, y, 0), (o.sx_m, o.sy_m, o.sz_m), r, [o.color, o.color2 or o.color])
        elif v == "kiosk":
            mb.add(BOX, (x, y, 0), (o.sx_m, o.sy_m, o.sz_m), r, [o.color, o.color2 or o.color])
        else:
            mb.add(BOX, (x, y, 0), (o.sx_m, o.sy_m, o.sz_m), r, [o.color, o.color])
    elif o.kind == "person":
        add_person_parts(mb, o)


def add_person_parts(mb: MeshBuilder, o: SceneObject) -> None:
    """A blocky pedestrian: legs, torso, arms, head with hair on top; walking swings limbs, crouching folds."""
    s = o.sz_m / (1.75 * (0.65 if o.variant == "crouching" else 1.0))  # the person's scale
    r = _rot(o.yaw_rad)
    base = np.array([o.x_m, o.y_m, o.z_m])
    shirt, trousers, skin, hair = o.color, o.color2 or o.color, o.color3 or o.color, o.color4 or o.color

    def at(dx, dy, dz):
        return base + r @ (np.array([dx, dy, dz]) * s)

    swing = 0.35 if o.variant == "walking" else 0.0
    crouch = o.variant == "crouching"
    leg_h = 0.5 if crouch else 0.86
    for side, sgn in ((-1, 1), (1, -1)):
        pitch = sgn * swing
        mb.add(BOX, at(0, side * 0.1, 0) + _rot(o.yaw_rad, pitch) @ np.array([0, 0, 0]), (0.15 * s, 0.15 * s, leg_h * s),
               _rot(o.yaw_rad, pitch), [trousers, trousers])  # fmt: skip
    torso_z = leg_h
    torso_pitch = 0.5 if crouch else 0.0
    rt = _rot(o.yaw_rad, torso_pitch)
    mb.add(BOX, at(0, 0, torso_z), (0.26 * s, 0.44 * s, 0.6 * s), rt, [shirt, shirt])
    shoulder = at(0, 0, torso_z) + rt @ np.array([0, 0, 0.6 * s])
    for side, sgn in ((-1, -1), (1, 1)):
        ra = _rot(o.yaw_rad, math.pi + sgn * swing + (0.6 if crouch else 0.0))
        mb.add(BOX, shoulder + r @ np.array([0, side * 0.28 * s, 0]), (0.11 * s, 0.11 * s, 0.6 * s), ra,
               [shirt, skin])  # fmt: skip
    neck = shoulder
    mb.add(BOX, neck, (0.2 * s, 0.19 * s, 0.22 * s), rt, [skin, hair])


# --------------------------------------------------------------------------------------------------
# The renderer


def _write_texture(img_rgb: np.ndarray, client: int) -> int:
    """PyBullet loads textures from files only: write a BMP (no compression: fast), load, delete."""
    fd, path = tempfile.mkstemp(suffix=".bmp", prefix="uavsearch_tex_")
    os.close(fd)
    try:
        cv2.imwrite(path, np.ascontiguousarray(img_rgb[:, :, ::-1]))
        tex = pb.loadTexture(path, physicsClientId=client)
    finally:
        os.unlink(path)
    if tex < 0:
        raise RuntimeError("PyBullet could not load a texture")
    return tex


def ground_shading(options: RenderOptions, light_dir) -> np.ndarray:
    """TinyRenderer's shading of a texel on the level ground as a 256-entry table: colour * (ambient +
    diffuse * max(0, n . light)) in float32, truncated to an integer (specular is off). Measured: it
    reproduces every ground pixel of the textured quad bit for bit."""
    k = np.float32(options.ambient) + np.float32(options.diffuse) * np.float32(max(0.0, float(light_dir[2])))
    return np.minimum((np.arange(256, dtype=np.float32) * k).astype(np.int32), 255).astype(np.uint8)


def ground_homography(intr: CameraIntrinsics, pose: CameraPose) -> np.ndarray:
    """Ground plane z = 0, (x, y, 1) in ENU metres -> homogeneous pixel coordinates (centres at +0.5)."""
    r_cam_from_enu = pose.R_enu_from_cam.T
    t = -r_cam_from_enu @ np.asarray(pose.position_enu, float)
    return intr.K @ np.column_stack([r_cam_from_enu[:, 0], r_cam_from_enu[:, 1], t])


class GroundCompositor:
    """The ground without TinyRenderer: the painted texture, shaded once, warped to the camera by the
    ground homography (nearest texel, as TinyRenderer samples it) and laid under the bodies wherever
    no body is nearer than the ground (depth test against the ground plane's depth, so parts of a body
    below z = 0 stay hidden as the ground quad hid them). Beyond the texture the ground is the base
    colour out to the base's edge; beyond that, and above the horizon, the background stays."""

    def __init__(self, texture: np.ndarray, tex_half_m: float, base_half_m: float, base_colour, shading: np.ndarray):
        n = texture.shape[0]
        self.texture = np.dstack([shading[texture], np.full(texture.shape[:2], 255, np.uint8)])  # RGBA, as pybullet's
        self.border = (*(int(v) for v in shading[np.asarray(base_colour, int)]), 255)
        # ENU (x, y) -> texel (col, row) of the north-up texture, minus half a texel: warpPerspective's
        # nearest neighbour rounds, TinyRenderer's texture lookup truncates
        self.texel_from_enu = np.array([[n / (2 * tex_half_m), 0.0, n / 2 - 0.5],
                                        [0.0, -n / (2 * tex_half_m), n / 2 - 0.5], [0.0, 0.0, 1.0]])  # fmt: skip
        self.base_half_m = base_half_m

    def composite(self, rgba: np.ndarray, depth: np.ndarray, pidx: np.ndarray, pose: CameraPose,
                  intr: CameraIntrinsics) -> None:  # fmt: skip
        """Lay the ground under the bodies of a TinyRenderer frame, in place: rgba (h, w, 4) uint8, its
        window depth (h, w) float32, person index (h, w) (cleared where the ground wins)."""
        h, w = depth.shape
        if float(pose.position_enu[2]) <= 0.0:
            return  # at or below the ground: the quad's back face, which TinyRenderer culls
        pixel_from_index = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
        # ENU z of the camera ray through index (x, y) scaled to z_cam = 1, as a row over (x, y, 1)
        ray_z = pose.R_enu_from_cam[2] @ np.linalg.inv(intr.K) @ pixel_from_index
        inv_depth = ray_z / -float(pose.position_enu[2])  # 1 / eye depth of the ground, affine in (x, y)
        # OpenGL window depth of the ground, 0.5 * (c1 - c2 / d) + 0.5, in float32 as TinyRenderer's buffer
        c1, c2 = (FAR_M + NEAR_M) / (FAR_M - NEAR_M), 2.0 * FAR_M * NEAR_M / (FAR_M - NEAR_M)
        xs = (-0.5 * c2 * (inv_depth[0] * np.arange(w) + inv_depth[2]) + 0.5 * c1 + 0.5).astype(np.float32)
        ys = (-0.5 * c2 * inv_depth[1] * np.arange(h)).astype(np.float32)[:, None]
        ground = depth >= xs + ys  # ties go to the ground, as when the quad was drawn last
        enu_from_index = np.linalg.inv(ground_homography(intr, pose)) @ pixel_from_index
        if not self._all_inside(enu_from_index, inv_depth, w, h):
            xf, yf = np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64)[:, None]
            ground &= self._inside(enu_from_index, inv_depth[0] * xf + inv_depth[1] * yf + inv_depth[2], w, h)
        img = cv2.warpPerspective(self.texture, self.texel_from_enu @ enu_from_index, (w, h),
                                  flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT,
                                  borderValue=self.border)  # fmt: skip
        mask = ground.view(np.uint8)
        cv2.copyTo(img, mask, rgba)
        pidx[ground] = -1

    def _all_inside(self, enu_from_index: np.ndarray, inv_depth: np.ndarray, w: int, h: int) -> bool:
        """Whether every pixel sees the base in front of the far plane (true unless near the horizon or
        the base's edge): the view's ground footprint is the quad of its corner pixels, the base is convex."""
        corners = np.array([[0.0, 0.0, 1.0], [w - 1.0, 0.0, 1.0], [w - 1.0, h - 1.0, 1.0], [0.0, h - 1.0, 1.0]])
        if (corners @ inv_depth <= 1.0 / FAR_M).any():
            return False
        q = corners @ enu_from_index.T
        return bool((np.abs(q[:, :2] / q[:, 2:]) < self.base_half_m).all())

    def _inside(self, enu_from_index: np.ndarray, inv_d: np.ndarray, w: int, h: int) -> np.ndarray:
        """Per pixel: the ground point is in front of the far plane and on the base."""
        xs, ys = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        q = np.stack([xs, ys, np.ones_like(xs)], -1) @ enu_from_index.T
        with np.errstate(divide="ignore", invalid="ignore"):
            x, y = q[..., 0] / q[..., 2], q[..., 1] / q[..., 2]
        return (inv_d > 1.0 / FAR_M) & (np.abs(x) < self.base_half_m) & (np.abs(y) < self.base_half_m)


class _World:
    """The PyBullet world of one scene in THIS process: one DIRECT client, built once, rendered often."""

    def __init__(self, spec: SceneSpec, intrinsics: CameraIntrinsics, options: RenderOptions):
        self.spec = spec
        self.intrinsics = intrinsics
        self.options = options
        self._client = pb.connect(pb.DIRECT)
        if self._client < 0:
            raise RuntimeError("cannot start a PyBullet DIRECT client")
        try:
            self._build()
        except Exception:
            self.close()
            raise

    def _mesh_body(self, mb: MeshBuilder, tex: int) -> list[int]:
        pos, nrm, uv = mb.arrays()
        bodies = []
        step = MAX_VERTICES - MAX_VERTICES % 3
        for start in range(0, len(pos), step):
            sl = slice(start, start + step)
            n = len(pos[sl])
            vs = pb.createVisualShape(pb.GEOM_MESH, vertices=pos[sl].tolist(), indices=list(range(n)),
                                      normals=nrm[sl].tolist(), uvs=uv[sl].tolist(), physicsClientId=self._client)  # fmt: skip
            body = pb.createMultiBody(0, -1, vs, physicsClientId=self._client)
            pb.changeVisualShape(body, -1, textureUniqueId=tex, rgbaColor=[1, 1, 1, 1], physicsClientId=self._client)
            bodies.append(body)
            self._bounds.append((pos[sl].min(0), pos[sl].max(0)))
        return bodies

    def _build(self) -> None:
        spec, c = self.spec, self._client
        if len(spec.people) > np.iinfo(np.int16).max:
            raise ValueError(f"{len(spec.people)} people: person indices are int16, at most 32767")
        palette, person_palette = Palette(), Palette()
        person_meshes = []
        for o in spec.people:
            mb = MeshBuilder(person_palette)
            add_person_parts(mb, o)
            person_meshes.append(mb)
        composite = self.options.ground == "composite"
        # Composite: static objects go into square tiles, each its own bodies, so that a view hides the
        # tiles it cannot see (TinyRenderer skips a body whose alpha is 0; it has no culling of its own).
        tiles: dict[tuple[int, int], MeshBuilder] = {}
        for o in spec.objects:  # drawn before the ground: the z-test then skips ground under roofs
            if o.kind in ("building", "roof_unit", "tree", "car", "clutter"):
                key = (math.floor(o.x_m / CULL_TILE_M), math.floor(o.y_m / CULL_TILE_M)) if composite else (0, 0)
                tiles.setdefault(key, MeshBuilder(palette)).add_object(o)
        static = tiles.setdefault((0, 0), MeshBuilder(palette))
        gr = ground_raster(spec)
        base = next(o for o in spec.objects if o.kind == "base")
        g, t = base.sx_m / 2, gr.half_m
        if not composite:  # plain ground beyond the painted texture: four quads around it (no overdraw)
            for x0, y0, x1, y1 in ((-g, t, g, g), (-g, -g, g, -t), (-g, -t, -t, t), (t, -t, g, t)):
                static.add(BOX, ((x0 + x1) / 2, (y0 + y1) / 2, -0.02), (x1 - x0, y1 - y0, 0.02), np.eye(3),
                           [base.color, base.color])  # fmt: skip
        pal_tex = _write_texture(palette.image(), c)
        self._bounds: list[tuple[np.ndarray, np.ndarray]] = []
        person_bodies, static_bodies, person_of_body = [], [], []
        person_tex = _write_texture(person_palette.image(), c) if person_meshes else -1
        for i, mb in enumerate(person_meshes):  # one body per person: its segmentation id names it
            bodies = self._mesh_body(mb, person_tex)
            person_bodies += bodies
            person_of_body += [i] * len(bodies)
        for mb in tiles.values():
            static_bodies += self._mesh_body(mb, pal_tex)
        self._bodies = np.array([*person_bodies, *static_bodies], np.int64)
        lo, hi = (np.array([b[k] for b in self._bounds]).reshape(-1, 3) for k in (0, 1))
        self._box_corners = np.stack([np.where(np.array(m, bool), hi, lo) for m in np.ndindex(2, 2, 2)], 1)
        self._shown = np.ones(len(self._bodies), bool)
        az, el = math.radians(spec.sun_azimuth_deg), math.radians(spec.sun_elevation_deg)
        self._light = [math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)]
        if composite:
            self._ground = GroundCompositor(paint_ground(spec, gr), t, g, base.color,
                                            ground_shading(self.options, self._light))  # fmt: skip
            ground = -1
        else:
            self._ground = None
            ground_tex = _write_texture(paint_ground(spec, gr), c)
            vs = pb.createVisualShape(pb.GEOM_MESH, vertices=[[-t, -t, 0], [t, -t, 0], [t, t, 0], [-t, t, 0]],
                                      indices=[0, 1, 2, 0, 2, 3], normals=[[0, 0, 1]] * 4,
                                      uvs=[[0, 0], [1, 0], [1, 1], [0, 1]], physicsClientId=c)  # fmt: skip
            ground = pb.createMultiBody(0, -1, vs, physicsClientId=c)
            pb.changeVisualShape(ground, -1, textureUniqueId=ground_tex, rgbaColor=[1, 1, 1, 1], physicsClientId=c)
        # segmentation id (a body's unique id) -> person index (-1 for everything else, including
        # the background, -1 = the last entry)
        ids = np.array(person_bodies, dtype=np.int64)
        self._seg_lut = np.full(int(max([ground, *static_bodies, *person_bodies]) + 2), -1, np.int16)
        self._seg_lut[ids] = np.array(person_of_body, dtype=np.int16)
        self._proj = projection_matrix(self.intrinsics.scaled(int(self.options.supersample)))

    def capture(self, pose: CameraPose) -> tuple[np.ndarray, np.ndarray]:
        """The supersampled frame: RGB (sH, sW, 3) uint8 and person index (sH, sW) int16."""
        s = int(self.options.supersample)
        w, h = self.intrinsics.width_px * s, self.intrinsics.height_px * s
        if self._ground is not None:
            self._cull(pose, self.intrinsics.scaled(s))
        _, _, rgba, depth, seg = pb.getCameraImage(
            w, h, view_matrix(pose), self._proj, renderer=pb.ER_TINY_RENDERER, shadow=0,
            lightDirection=self._light, lightAmbientCoeff=self.options.ambient,
            lightDiffuseCoeff=self.options.diffuse, lightSpecularCoeff=0.0, physicsClientId=self._client,
        )  # fmt: skip
        rgba = np.ascontiguousarray(rgba, dtype=np.uint8).reshape(h, w, 4)
        seg = np.asarray(seg, dtype=np.int64).reshape(h, w)
        pidx = self._seg_lut[np.clip(seg, -1, len(self._seg_lut) - 2)]
        if self._ground is not None:
            self._ground.composite(rgba, np.asarray(depth, np.float32).reshape(h, w), pidx, pose,
                                   self.intrinsics.scaled(s))  # fmt: skip
        return rgba[:, :, :3], pidx

    def _cull(self, pose: CameraPose, intr: CameraIntrinsics) -> None:
        """Hide the bodies whose bounding box lies wholly outside the view frustum (beyond one side plane,
        with a margin of CULL_MARGIN_PX, or before the near plane) and show the others: the image is the
        same, TinyRenderer just skips their vertices and triangles."""
        pc = pose.world_to_camera(self._box_corners)  # (B, 8, 3)
        x, y, z = pc[..., 0], pc[..., 1], pc[..., 2]
        m = CULL_MARGIN_PX
        out = ((x < -(intr.cx + m) / intr.fx * z).all(1) | (x > (intr.width_px - intr.cx + m) / intr.fx * z).all(1)
               | (y < -(intr.cy + m) / intr.fy * z).all(1) | (y > (intr.height_px - intr.cy + m) / intr.fy * z).all(1)
               | (z < NEAR_M).all(1))  # fmt: skip
        show = ~out
        for i in np.flatnonzero(show != self._shown):
            pb.changeVisualShape(int(self._bodies[i]), -1, rgbaColor=[1, 1, 1, float(show[i])],
                                 physicsClientId=self._client)  # fmt: skip
        self._shown = show

    def render(self, position_enu, r_enu_from_cam) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Clean float image (H, W, 3), person fraction (H, W) and person index (H, W)."""
        pose = CameraPose(np.asarray(position_enu, float), np.asarray(r_enu_from_cam, float))
        s = int(self.options.supersample)
        intr = self.intrinsics
        rgb, pidx = self.capture(pose)
        H, W = intr.height_px, intr.width_px
        if s > 1:
            frac = _block_share(pidx >= 0, s)
            return area_downsample(rgb, s), frac, _majority(pidx, s, frac > 0)
        return rgb.astype(np.float32), (pidx >= 0).astype(np.float32), pidx.astype(np.int16)

    def close(self) -> None:
        if getattr(self, "_client", -1) >= 0:
            try:
                pb.disconnect(physicsClientId=self._client)
            except Exception:  # pybullet.error: already disconnected
                pass
            self._client = -1


# --------------------------------------------------------------------------------------------------
# Worker processes: PyBullet never gives back a client's meshes and textures, not even on disconnect
# (measured: about 30 MB per 90k-vertex mesh, 30 MB per 2048^2 texture, 35 MB per client). A world
# is therefore built in a worker process that is recycled after RECYCLE_AFTER_SCENES scenes, which
# bounds the leak; idle workers are kept (up to MAX_IDLE_WORKERS) so the start-up cost is paid rarely.

RECYCLE_AFTER_SCENES = 8
MAX_IDLE_WORKERS = 2
BACKGROUND_NICE = 10  # a background worker's priority offset, where SCHED_IDLE is not at hand
_BACKGROUND: "weakref.WeakSet[_Worker]" = weakref.WeakSet()
_IDLE: list["_Worker"] = []


class _Worker:
    def __init__(self, background: bool = False):
        pkg_parent = str(Path(__file__).resolve().parents[2])
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (pkg_parent, os.environ.get("PYTHONPATH")) if p))
        lower = ""
        if background:  # SCHED_IDLE keeps its nice value, so foreground() may undo it without privileges
            lower = ("os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0)); " if hasattr(os, "SCHED_IDLE")
                     else f"os.nice({BACKGROUND_NICE}); ")
        code = (f"import os; {lower}fd = os.dup(1); os.dup2(2, 1); "
                "from uavsearch.world.render import _worker_main; _worker_main(fd)")
        self.proc = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.DEVNULL, env=env)  # fmt: skip
        self.scenes = 0
        self.owner_pid = os.getpid()
        if background:
            _BACKGROUND.add(self)

    def foreground(self) -> None:
        """Back to the normal scheduling class (Linux; a nice value once raised stays)."""
        if hasattr(os, "SCHED_OTHER") and self.proc.poll() is None:
            try:
                os.sched_setscheduler(self.proc.pid, os.SCHED_OTHER, os.sched_param(0))
            except OSError:  # gone meanwhile, or a platform without it: it keeps its class
                pass

    def call(self, *msg):
        try:
            pickle.dump(msg, self.proc.stdin, protocol=pickle.HIGHEST_PROTOCOL)
            self.proc.stdin.flush()
            status, value = pickle.load(self.proc.stdout)
        except (EOFError, BrokenPipeError, OSError, pickle.UnpicklingError):
            self.kill()
            raise RuntimeError("the render worker process died") from None
        if status == "error":
            raise RuntimeError(f"render worker: {value}")
        return value

    def kill(self) -> None:
        if self.proc.poll() is None:
            try:
                self.proc.stdin.close()
                self.proc.wait(timeout=5)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()
                self.proc.wait()


def _worker_main(out_fd: int) -> None:
    """Serve ('load', spec_json, intrinsics, options) / ('render', position, R) / ('unload',) until EOF."""
    out = os.fdopen(out_fd, "wb")
    inp = sys.stdin.buffer
    world = None
    while True:
        try:
            msg = pickle.load(inp)
        except EOFError:
            break
        try:
            if msg[0] == "load":
                if world is not None:
                    world.close()
                world = _World(scene_from_json(msg[1]), msg[2], msg[3])
                reply = ("ok", None)
            elif msg[0] == "generate":  # ('generate', seed, occupied_cells): see generate_in_worker
                from .scene import generate_scene

                reply = ("ok", scene_to_json(generate_scene(msg[1], msg[2])))
            elif msg[0] == "render":
                reply = ("ok", world.render(msg[1], msg[2]))
            elif msg[0] == "unload":
                if world is not None:
                    world.close()
                world = None
                reply = ("ok", None)
            else:
                reply = ("error", f"unknown request {msg[0]!r}")
        except Exception as e:  # reported to the parent, which raises it
            reply = ("error", f"{type(e).__name__}: {e}")
        pickle.dump(reply, out, protocol=pickle.HIGHEST_PROTOCOL)
        out.flush()


@atexit.register
def _stop_idle_workers() -> None:
    while _IDLE:
        w = _IDLE.pop()
        if w.owner_pid == os.getpid():
            w.kill()


def start_idle_worker(background: bool = False) -> None:
    """An idle worker started now (unless one is idle), which the next isolated SceneRenderer takes: its
    interpreter and PyBullet start (0.3-0.5 s) run beside the caller's own work instead of in the renderer's.
    `background` runs it on CPU time that nothing else wants (Linux's SCHED_IDLE; elsewhere nice
    BACKGROUND_NICE): work beside a flight, which must not slow it, until foreground_workers()."""
    if not _IDLE:
        _IDLE.append(_Worker(background))


def foreground_workers() -> None:
    """Every background worker back to normal scheduling: once the work it ran beside is over, a busy machine
    must not starve it."""
    for worker in list(_BACKGROUND):
        worker.foreground()


def generate_in_worker(seed: int, occupied_cells: int) -> SceneSpec:
    """generate_scene(seed, occupied_cells), run in an idle worker (started if none), which the next
    isolated SceneRenderer then takes: the generator's 0.5-1 s of Python run beside the caller's own work
    (a flight's vehicle: importing and building its physics) instead of holding its GIL."""
    start_idle_worker()
    worker = _IDLE[-1]
    try:
        return scene_from_json(worker.call("generate", int(seed), int(occupied_cells)))
    except Exception:
        _IDLE.remove(worker)
        worker.kill()
        raise


# A forked child must not talk to its parent's workers over the inherited pipes.
os.register_at_fork(after_in_child=_IDLE.clear)


class SceneRenderer:
    """The camera of one scene: render(pose) -> Render. One PyBullet DIRECT client per renderer, in a
    worker process by default (options.isolate), so renderers never share state and memory is bounded."""

    def __init__(self, spec: SceneSpec, intrinsics: CameraIntrinsics, options: RenderOptions = RenderOptions()):
        if int(options.supersample) < 1:
            raise ValueError("supersample must be >= 1")
        if options.ground not in GROUND_MODES:
            raise ValueError(f"ground must be one of {', '.join(GROUND_MODES)}, not {options.ground!r}")
        self.spec = spec
        self.intrinsics = intrinsics
        self.options = options
        self._world: _World | None = None
        self._worker: _Worker | None = None
        if options.isolate:
            worker = _IDLE.pop() if _IDLE else _Worker()
            try:
                worker.call("load", scene_to_json(spec), intrinsics, options)
            except Exception:
                worker.kill()
                raise
            worker.scenes += 1
            self._worker = worker
        else:
            self._world = _World(spec, intrinsics, options)

    def render(self, pose: CameraPose, rng: np.random.Generator | None = None) -> Render:
        """The view from `pose`; `rng` draws the sensor randomisation (none when rng is None)."""
        if self._world is not None:
            img, frac, person_index = self._world.render(pose.position_enu, pose.R_enu_from_cam)
        elif self._worker is not None:
            img, frac, person_index = self._worker.call("render", np.asarray(pose.position_enu, float),
                                                        np.asarray(pose.R_enu_from_cam, float))  # fmt: skip
        else:
            raise RuntimeError("render() on a closed SceneRenderer")
        if rng is not None:
            img = self._randomise(img, rng)
        out = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        return Render(rgb=out, person_mask=frac > 0, person_fraction=frac, person_index=person_index)

    def _randomise(self, img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        o = self.options
        if o.exposure_jitter > 0:
            img = img * rng.uniform(1 - o.exposure_jitter, 1 + o.exposure_jitter)
        if o.blur_sigma_px > 0:
            sigma = rng.uniform(0, o.blur_sigma_px)
            if sigma > 0.05:
                img = cv2.GaussianBlur(img, (0, 0), sigma)
        if o.noise_std > 0:
            img = img + rng.normal(0, rng.uniform(0, o.noise_std), img.shape).astype(np.float32)
        return img

    def close(self) -> None:
        if self._world is not None:
            self._world.close()
            self._world = None
        worker, self._worker = self._worker, None
        if worker is not None and worker.owner_pid == os.getpid():  # never a worker inherited through fork
            try:
                worker.call("unload")
            except RuntimeError:
                return
            if worker.scenes >= RECYCLE_AFTER_SCENES or len(_IDLE) >= MAX_IDLE_WORKERS:
                worker.kill()
            else:
                _IDLE.append(worker)

    def __enter__(self) -> "SceneRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass


def area_downsample(img: np.ndarray, s: int) -> np.ndarray:
    """Mean of each s x s block of a uint8 (h, w, c) image as float32: integer sums of s*s strided views,
    one division. Bit-identical to img.reshape(H, s, W, s, c).astype(float32).mean((1, 3)), about 8x
    faster (no float copy of the big image, no pairwise float reduction)."""
    acc = np.zeros((img.shape[0] // s, img.shape[1] // s) + img.shape[2:], np.uint16 if s <= 16 else np.uint32)
    for a in range(s):
        for b in range(s):
            acc += img[a::s, b::s]
    out = acc.astype(np.float32)
    out /= s * s
    return out


def _block_share(flags: np.ndarray, s: int) -> np.ndarray:
    """Share of True in each s x s block of a bool (h, w) array, float32 (as bool mean: float64 then cast)."""
    n = np.zeros((flags.shape[0] // s, flags.shape[1] // s), np.uint16)
    for a in range(s):
        for b in range(s):
            n += flags[a::s, b::s]
    return (n / (s * s)).astype(np.float32)


def _majority(pidx: np.ndarray, s: int, has: np.ndarray) -> np.ndarray:
    """Per output pixel, the person index covering most of its s x s subpixels (ties: lowest index);
    -1 where none (`has`: the pixels with any person subpixel, the only ones looked at)."""
    out = np.full(has.shape, -1, np.int16)
    rows, cols = np.nonzero(has)
    if not len(rows):
        return out
    sub = np.stack([pidx[rows * s + a, cols * s + b] for a in range(s) for b in range(s)], -1)
    best = np.full(len(sub), -1, np.int16)
    best_n = np.zeros(len(sub), np.int32)
    for v in np.unique(sub[sub >= 0]):
        n = (sub == v).sum(-1)
        better = n > best_n
        best[better], best_n[better] = v, n[better]
    out[rows, cols] = best
    return out


__all__ = ["RenderOptions", "Render", "SceneRenderer", "GroundCompositor", "Palette", "GROUND_MODES", "area_downsample",
           "ground_homography", "ground_shading", "view_matrix", "projection_matrix"]
