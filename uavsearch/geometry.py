"""Frames, the camera model and the search grid: the one module that converts between them.

Conventions (DESIGN.md):
- Scene frame: ENU metres, origin on the ground at the centre of the search area, z up.
- MAVLink local frame: NED with the same origin (home). Global: WGS84, home at the scene origin.
- Vehicle attitude: roll, pitch, yaw (rad) of the FRD body in NED, yaw clockwise from north.
- Camera frame: OpenCV (x right, y down, z along the optical axis). Pixel coordinates are continuous:
  pixel (row i, col j) covers u in [j, j+1), v in [i, i+1); its centre is (j + 0.5, i + 0.5).
- Grid: N x N cells of `cell_m` metres centred on the origin; cell index i = row * N + col, row 0 the
  northernmost, col 0 the westernmost, so a map array reads like a north-up image.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np

# --------------------------------------------------------------------------------------------------
# Frames

R_ENU_FROM_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # its own inverse

WGS84_A_M = 6378137.0
WGS84_E2 = 6.69437999014e-3


def enu_to_ned(p_enu) -> np.ndarray:
    """ENU -> NED for points or arrays of points (..., 3). The matrix is symmetric and its own inverse."""
    return np.asarray(p_enu, dtype=float) @ R_ENU_FROM_NED.T


ned_to_enu = enu_to_ned


@dataclass(frozen=True)
class GeodeticOrigin:
    """WGS84 position of the scene origin (home): local tangent-plane conversion with WGS84 radii.

    Exact round trips; under 1 mm of error against a full ellipsoidal conversion over the scene's extent
    (a few hundred metres), which is far below GPS noise.
    """

    lat_deg: float = 47.397742  # PX4 SITL's default home (Zurich)
    lon_deg: float = 8.545594
    alt_m: float = 488.0  # AMSL of the ground at the origin

    @functools.cached_property
    def _radii(self) -> tuple[float, float]:
        s = math.sin(math.radians(self.lat_deg))
        d = 1.0 - WGS84_E2 * s * s
        r_north = WGS84_A_M * (1.0 - WGS84_E2) / d**1.5  # meridian radius of curvature
        r_east = WGS84_A_M / math.sqrt(d) * math.cos(math.radians(self.lat_deg))
        return r_north, r_east

    def enu_to_geodetic(self, p_enu) -> np.ndarray:
        """(..., 3) ENU metres -> (..., 3) [lat_deg, lon_deg, alt_m AMSL]."""
        p = np.asarray(p_enu, dtype=float)
        r_n, r_e = self._radii
        lat = self.lat_deg + np.degrees(p[..., 1] / r_n)
        lon = self.lon_deg + np.degrees(p[..., 0] / r_e)
        return np.stack([lat, lon, self.alt_m + p[..., 2]], axis=-1)

    def geodetic_to_enu(self, lla) -> np.ndarray:
        """(..., 3) [lat_deg, lon_deg, alt_m AMSL] -> (..., 3) ENU metres."""
        q = np.asarray(lla, dtype=float)
        r_n, r_e = self._radii
        north = np.radians(q[..., 0] - self.lat_deg) * r_n
        east = np.radians(q[..., 1] - self.lon_deg) * r_e
        return np.stack([east, north, q[..., 2] - self.alt_m], axis=-1)


# Attitude conversions, written out: scipy's Rotation gives the same bits (tests/test_geometry.py compares them
# over random attitudes) but importing scipy.spatial costs every process 0.3-0.6 s of CPU (shared 2-core machine),
# which a flight's controller paid during its take-off. The operations and their order are scipy's own
# (intrinsic ZYX = quaternion products z * y * x; its quaternion -> matrix terms; its quaternion -> Euler angles,
# with the C library's hypot as scipy calls it).


def _quat_xyzw_from_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> tuple[float, float, float, float]:
    """[x, y, z, w] of the intrinsic ZYX rotation (yaw, then pitch, then roll)."""

    def axis(i: int, a: float) -> list[float]:
        q = [0.0, 0.0, 0.0, math.cos(a / 2.0)]
        q[i] = math.sin(a / 2.0)
        return q

    def compose(p: list[float], q: list[float]) -> list[float]:
        c0, c1, c2 = p[1] * q[2] - p[2] * q[1], p[2] * q[0] - p[0] * q[2], p[0] * q[1] - p[1] * q[0]
        return [p[3] * q[0] + q[3] * p[0] + c0, p[3] * q[1] + q[3] * p[1] + c1, p[3] * q[2] + q[3] * p[2] + c2,
                p[3] * q[3] - p[0] * q[0] - p[1] * q[1] - p[2] * q[2]]

    x, y, z, w = compose(compose(axis(2, float(yaw_rad)), axis(1, float(pitch_rad))), axis(0, float(roll_rad)))
    return x, y, z, w


def rotation_ned_from_body(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """Body FRD -> NED rotation matrix (aerospace ZYX Euler angles)."""
    if roll_rad == 0.0 and pitch_rad == 0.0 and yaw_rad == 0.0:  # the lattice's poses: the exact identity
        return np.eye(3)
    x, y, z, w = _quat_xyzw_from_euler(roll_rad, pitch_rad, yaw_rad)
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    return np.array([[x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw)],
                     [2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw)],
                     [2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2]])


def quaternion_from_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> np.ndarray:
    """[w, x, y, z] of the body FRD -> NED rotation, as MAVLink's attitude quaternions."""
    x, y, z, w = _quat_xyzw_from_euler(roll_rad, pitch_rad, yaw_rad)
    return np.array([w, x, y, z])


def euler_from_quaternion(q_wxyz) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in rad from a MAVLink [w, x, y, z] quaternion; yaw in (-pi, pi]."""
    w, x, y, z = (float(v) for v in q_wxyz)
    norm = math.sqrt(x * x + y * y + z * z + w * w)
    if not norm > 0.0:
        raise ValueError("Found zero norm quaternions in `quat`.")
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    a, b, c, d = w - y, x + z, y + w, z - x  # the intrinsic ZYX sequence as scipy permutes it
    hypot = np.hypot  # the C library's (math.hypot rounds differently)
    mid = 2 * math.atan2(float(hypot(c, d)), float(hypot(a, b)))
    half_sum, half_diff = math.atan2(b, a), math.atan2(d, c)
    if abs(mid) <= 1e-7:  # gimbal lock (pitch +-90 deg): roll set to zero, as scipy does
        roll, yaw = 0.0, 2 * half_sum
    elif abs(mid - math.pi) <= 1e-7:
        roll, yaw = 0.0, 2 * half_diff
    else:
        roll, yaw = half_sum - half_diff, half_sum + half_diff
    angles = [roll, mid - math.pi / 2, yaw]
    for i, v in enumerate(angles):
        angles[i] = v + 2 * math.pi if v < -math.pi else v - 2 * math.pi if v > math.pi else v
    return angles[0], angles[1], angles[2]


def wrap_pi(angle_rad):
    """Wrap to [-pi, pi)."""
    return (np.asarray(angle_rad) + np.pi) % (2.0 * np.pi) - np.pi


# --------------------------------------------------------------------------------------------------
# Camera


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole camera with square pixels and the principal point at the image centre."""

    width_px: int = 224
    height_px: int = 224
    hfov_deg: float = 60.0

    @property
    def fx(self) -> float:
        return (self.width_px / 2.0) / math.tan(math.radians(self.hfov_deg) / 2.0)

    @property
    def fy(self) -> float:
        return self.fx

    @property
    def cx(self) -> float:
        return self.width_px / 2.0

    @property
    def cy(self) -> float:
        return self.height_px / 2.0

    @property
    def vfov_deg(self) -> float:
        return math.degrees(2.0 * math.atan((self.height_px / 2.0) / self.fy))

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, factor: int) -> "CameraIntrinsics":
        """The same camera at `factor` times the resolution (for supersampling)."""
        return CameraIntrinsics(self.width_px * factor, self.height_px * factor, self.hfov_deg)


# Body FRD -> camera (x right, y down, z forward) for a camera looking straight down with image up
# pointing to the vehicle's nose: columns are the camera axes expressed in the body frame.
R_BODY_FROM_NADIR_CAM = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class CameraPose:
    """Camera centre in scene ENU metres and the camera -> ENU rotation."""

    position_enu: np.ndarray
    R_enu_from_cam: np.ndarray = field(repr=False)

    @property
    def forward_enu(self) -> np.ndarray:
        return self.R_enu_from_cam[:, 2]

    @property
    def up_enu(self) -> np.ndarray:
        """Image-up direction (minus the camera's y axis)."""
        return -self.R_enu_from_cam[:, 1]

    def world_to_camera(self, points_enu) -> np.ndarray:
        p = np.asarray(points_enu, dtype=float) - self.position_enu
        return p @ self.R_enu_from_cam  # == (R^T p^T)^T


def camera_pose_from_vehicle(
    position_enu,
    roll_rad: float = 0.0,
    pitch_rad: float = 0.0,
    yaw_rad: float = 0.0,
    gimbal_stabilised: bool = True,
) -> CameraPose:
    """Compose the vehicle pose with the nadir gimbal.

    A stabilised gimbal cancels roll and pitch and keeps the vehicle's yaw (as a 2-axis gimbal does);
    a hard-mounted camera follows the full attitude.
    """
    if gimbal_stabilised:
        r_ned_body = rotation_ned_from_body(0.0, 0.0, yaw_rad)
    else:
        r_ned_body = rotation_ned_from_body(roll_rad, pitch_rad, yaw_rad)
    r = R_ENU_FROM_NED @ r_ned_body @ R_BODY_FROM_NADIR_CAM
    return CameraPose(np.asarray(position_enu, dtype=float).copy(), r)


def nadir_camera_pose(position_enu, yaw_rad: float = 0.0) -> CameraPose:
    """A perfectly level nadir camera with image-up along heading `yaw_rad` (0 = north)."""
    return camera_pose_from_vehicle(position_enu, 0.0, 0.0, yaw_rad, gimbal_stabilised=True)


def project_points(points_enu, intr: CameraIntrinsics, pose: CameraPose) -> tuple[np.ndarray, np.ndarray]:
    """Eq. (1): world points -> pixel coordinates (..., 2) and depth along the optical axis (...).

    Points behind the camera (depth <= 0) get NaN pixel coordinates.
    """
    pc = pose.world_to_camera(points_enu)
    z = pc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = intr.fx * pc[..., 0] / z + intr.cx
        v = intr.fy * pc[..., 1] / z + intr.cy
    uv = np.stack([u, v], axis=-1)
    uv[z <= 0] = np.nan
    return uv, z


@functools.lru_cache(maxsize=16)
def _pixel_rays_cam(intr: CameraIntrinsics) -> np.ndarray:
    """Unnormalised camera-frame rays through every pixel centre, (H, W, 3)."""
    u = (np.arange(intr.width_px) + 0.5 - intr.cx) / intr.fx
    v = (np.arange(intr.height_px) + 0.5 - intr.cy) / intr.fy
    uu, vv = np.meshgrid(u, v)
    rays = np.stack([uu, vv, np.ones_like(uu)], axis=-1)
    rays.setflags(write=False)
    return rays


def ground_points_of_pixels(intr: CameraIntrinsics, pose: CameraPose, ground_z_m: float = 0.0) -> np.ndarray:
    """Where each pixel centre's ray meets the ground plane, (H, W, 2) ENU x/y; NaN where it never does."""
    d = _pixel_rays_cam(intr) @ pose.R_enu_from_cam.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (ground_z_m - pose.position_enu[2]) / d[..., 2]
    t = np.where(t > 0, t, np.nan)
    return pose.position_enu[:2] + t[..., None] * d[..., :2]


# --------------------------------------------------------------------------------------------------
# Grid


@dataclass(frozen=True)
class Grid:
    """The N x N occupancy grid over the search area, centred on the scene origin."""

    n: int = 10
    cell_m: float = 5.0

    @property
    def size_m(self) -> float:
        return self.n * self.cell_m

    @property
    def half_m(self) -> float:
        return self.size_m / 2.0

    @property
    def num_cells(self) -> int:
        return self.n * self.n

    def row_col(self, index) -> tuple:
        return np.divmod(index, self.n)

    def cell_corners_enu(self, index: int) -> np.ndarray:
        """The four ground corners of a cell (NW, NE, SE, SW), (4, 3) ENU metres, z = 0.

        The one function that maps a cell to the ground; everything else calls it.
        """
        if not 0 <= index < self.num_cells:
            raise IndexError(f"cell {index} outside a {self.n}x{self.n} grid")
        r, c = divmod(int(index), self.n)
        x0 = -self.half_m + c * self.cell_m
        y0 = self.half_m - r * self.cell_m
        x1, y1 = x0 + self.cell_m, y0 - self.cell_m
        return np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])

    @functools.cached_property
    def all_corners_enu(self) -> np.ndarray:
        """(num_cells, 4, 3)."""
        return np.stack([self.cell_corners_enu(i) for i in range(self.num_cells)])

    @functools.cached_property
    def centers_enu(self) -> np.ndarray:
        """(num_cells, 3) cell centres on the ground."""
        return self.all_corners_enu.mean(axis=1)

    def cell_of_points(self, x_m, y_m) -> np.ndarray:
        """Cell index of ground points (ENU x, y); -1 outside the grid or for NaN."""
        x = np.asarray(x_m, dtype=float)
        y = np.asarray(y_m, dtype=float)
        with np.errstate(invalid="ignore"):
            col = np.floor((x + self.half_m) / self.cell_m)
            row = np.floor((self.half_m - y) / self.cell_m)
            ok = (col >= 0) & (col < self.n) & (row >= 0) & (row < self.n)
        idx = np.where(ok, np.nan_to_num(row) * self.n + np.nan_to_num(col), -1)
        return idx.astype(np.int64)


def _clip_polygon(poly: list, axis: int, bound: float, keep_greater: bool) -> list:
    """Sutherland-Hodgman: keep the part of a convex polygon (a list of coordinate tuples of floats) on one side
    of coordinate axis = bound. Plain floats, not a numpy array per vertex: the same IEEE operations, and a wide
    lattice clips about 2,500 cells the image border crosses."""
    out = []
    n = len(poly)
    for k in range(n):
        a, b = poly[k], poly[(k + 1) % n]
        ina = a[axis] >= bound if keep_greater else a[axis] <= bound
        inb = b[axis] >= bound if keep_greater else b[axis] <= bound
        if ina:
            out.append(a)
        if ina != inb:
            t = (bound - a[axis]) / (b[axis] - a[axis])
            out.append(tuple(ai + t * (bi - ai) for ai, bi in zip(a, b)))
    return out


def polygon_area(poly: np.ndarray) -> float:
    """Shoelace area of a 2D polygon."""
    if len(poly) < 3:
        return 0.0
    x, y = poly[:, 0], poly[:, 1]
    xn, yn = np.concatenate((x[1:], x[:1])), np.concatenate((y[1:], y[:1]))  # np.roll(., -1), without its overhead
    return 0.5 * abs(float(np.dot(x, yn) - np.dot(y, xn)))


NEAR_PLANE_M = 0.05


def _clip_to_view(pc: np.ndarray, intr: CameraIntrinsics) -> np.ndarray:
    """A camera-frame polygon clipped to the near plane, projected and clipped to the image."""
    inside = pc
    if not np.all(pc[:, 2] > NEAR_PLANE_M):
        kept = _clip_polygon([tuple(map(float, p)) for p in pc], 2, NEAR_PLANE_M, keep_greater=True)
        inside = np.array(kept) if kept else np.zeros((0, 3))
    if len(inside) < 3:
        return np.zeros((0, 2))
    uv = np.stack(
        [intr.fx * inside[:, 0] / inside[:, 2] + intr.cx, intr.fy * inside[:, 1] / inside[:, 2] + intr.cy], axis=-1
    )
    poly = [(float(u), float(v)) for u, v in uv]
    for axis, bound, keep_greater in ((0, 0.0, True), (0, float(intr.width_px), False), (1, 0.0, True),
                                      (1, float(intr.height_px), False)):
        poly = _clip_polygon(poly, axis, bound, keep_greater)
    return np.array(poly) if len(poly) >= 3 else np.zeros((0, 2))


def _project_cells(grid: Grid, intr: CameraIntrinsics, pose: CameraPose):
    """Every cell's corners in the camera frame (cells, 4, 3) and in pixels (cells, 4, 2), and which cells lie
    wholly in front of the camera and inside the image, and which wholly beyond one image edge."""
    pc = pose.world_to_camera(grid.all_corners_enu)  # (cells, 4, 3)
    z = pc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([intr.fx * pc[..., 0] / z + intr.cx, intr.fy * pc[..., 1] / z + intr.cy], axis=-1)
    front = np.all(z > NEAR_PLANE_M, axis=1)
    u, v = uv[..., 0], uv[..., 1]
    whole = front & np.all((u >= 0) & (u <= intr.width_px), axis=1) & np.all((v >= 0) & (v <= intr.height_px), axis=1)
    beyond = front & (np.all(u < 0, axis=1) | np.all(u > intr.width_px, axis=1)
                      | np.all(v < 0, axis=1) | np.all(v > intr.height_px, axis=1))
    return pc, uv, whole, beyond


def cell_image_polygons(grid: Grid, intr: CameraIntrinsics, pose: CameraPose) -> list[np.ndarray]:
    """Each cell's image polygon, clipped to the camera's near plane and the image (never wrapped).

    Returns one (k, 2) array of pixel coordinates per cell (k = 0 when the cell is out of view).
    Cells wholly in front of the camera and inside the image skip the clipping, and so do those wholly
    beyond one image edge (empty: what the clipping would return). On a wide grid most cells are one or
    the other, so only the cells the image border crosses are clipped one by one.
    """
    pc, uv, whole, beyond = _project_cells(grid, intr, pose)
    empty = np.zeros((0, 2))
    return [uv[i] if whole[i] else empty if beyond[i] else _clip_to_view(pc[i], intr) for i in range(grid.num_cells)]


def quad_areas(quads: np.ndarray) -> np.ndarray:
    """Shoelace areas of (n, 4, 2) quadrilaterals at once: polygon_area of each, to the last bit on this
    machine (the products are summed in pairs, in the order np.dot sums four)."""
    x, y = quads[..., 0], quads[..., 1]
    xn, yn = np.roll(x, -1, axis=1), np.roll(y, -1, axis=1)
    a = (x[:, 0] * yn[:, 0] + x[:, 2] * yn[:, 2]) + (x[:, 1] * yn[:, 1] + x[:, 3] * yn[:, 3])
    b = (y[:, 0] * xn[:, 0] + y[:, 2] * xn[:, 2]) + (y[:, 1] * xn[:, 1] + y[:, 3] * xn[:, 3])
    return 0.5 * np.abs(a - b)


def cell_pixel_areas(grid: Grid, intr: CameraIntrinsics, pose: CameraPose) -> np.ndarray:
    """F_size of every cell: the area in pixels of its clipped image polygon, (num_cells,).

    The cells wholly in the image at once (quad_areas); only those the image border crosses are clipped one
    by one (a wide lattice, 73 viewpoints over 900 cells, takes about half the time it took cell by cell)."""
    pc, uv, whole, beyond = _project_cells(grid, intr, pose)
    areas = np.zeros(grid.num_cells)
    areas[whole] = quad_areas(uv[whole])
    for i in np.flatnonzero(~whole & ~beyond):
        areas[i] = polygon_area(_clip_to_view(pc[i], intr))
    return areas


def cell_label_image(grid: Grid, intr: CameraIntrinsics, pose: CameraPose) -> np.ndarray:
    """Which cell each pixel sees on the ground plane, (H, W) int16; -1 off the grid.

    The mask m_i of Eq. (2) is `label == i`: exact per pixel centre, for any attitude.
    """
    g = ground_points_of_pixels(intr, pose)
    return grid.cell_of_points(g[..., 0], g[..., 1]).astype(np.int16)


def cell_masks(grid: Grid, intr: CameraIntrinsics, pose: CameraPose) -> np.ndarray:
    """(num_cells, H, W) bool masks m_i^t."""
    label = cell_label_image(grid, intr, pose)
    return label[None, :, :] == np.arange(grid.num_cells, dtype=np.int16)[:, None, None]


def cells_in_view(grid: Grid, intr: CameraIntrinsics, pose: CameraPose, min_area_px: float = 1.0) -> np.ndarray:
    """c^t: which cells cover at least `min_area_px` pixels of the image, (num_cells,) bool."""
    return cell_pixel_areas(grid, intr, pose) >= min_area_px
