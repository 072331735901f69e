"""The project's one geometry module: rigid transforms, UR poses, registration, voxel grid, rays.

Conventions used everywhere in touchshape:
- Units are metres and radians unless a name says otherwise (``_mm``, ``_deg``).
- A 4x4 homogeneous matrix named ``pose_a_b`` (or ``T_a_b``) maps points from frame ``b`` into
  frame ``a``: ``x_a = pose_a_b @ x_b``. So ``pose_world_tcp`` is the TCP's pose in the world.
- The world frame is z-up with its origin at the object point on the table top (table = z=0).
- UR poses are ``[x, y, z, rx, ry, rz]`` with an axis-angle rotation vector, as ur-rtde uses.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

FloatArray = NDArray[np.float64]


# --- rigid transforms --------------------------------------------------------------------------


def make_transform(
    rotation: ArrayLike | None = None, translation: ArrayLike | None = None
) -> FloatArray:
    """4x4 homogeneous transform from a 3x3 rotation and a translation (metres)."""
    transform = np.eye(4)
    if rotation is not None:
        transform[:3, :3] = np.asarray(rotation, dtype=float)
    if translation is not None:
        transform[:3, 3] = np.asarray(translation, dtype=float)
    return transform


def invert_transform(transform: ArrayLike) -> FloatArray:
    """Inverse of a rigid transform, using R^T rather than a general matrix inverse."""
    transform = np.asarray(transform, dtype=float)
    rotation_t = transform[:3, :3].T
    return make_transform(rotation_t, -rotation_t @ transform[:3, 3])


def transform_points(transform: ArrayLike, points: ArrayLike) -> FloatArray:
    """Apply a 4x4 transform to (..., 3) points."""
    transform = np.asarray(transform, dtype=float)
    points = np.asarray(points, dtype=float)
    return points @ transform[:3, :3].T + transform[:3, 3]


def transform_directions(transform: ArrayLike, directions: ArrayLike) -> FloatArray:
    """Rotate (..., 3) direction vectors by a 4x4 transform (no translation)."""
    transform = np.asarray(transform, dtype=float)
    return np.asarray(directions, dtype=float) @ transform[:3, :3].T


def rotation_about_axis(axis: ArrayLike, angle_rad: float) -> FloatArray:
    """3x3 rotation of ``angle_rad`` about a (not necessarily unit) axis."""
    axis = np.asarray(axis, dtype=float)
    return Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle_rad).as_matrix()


def frame_from_z_axis(z_axis: ArrayLike, x_hint: ArrayLike = (1.0, 0.0, 0.0)) -> FloatArray:
    """3x3 right-handed rotation with third column ``z_axis``; x follows ``x_hint`` if possible."""
    z = np.asarray(z_axis, dtype=float)
    z = z / np.linalg.norm(z)
    x = np.asarray(x_hint, dtype=float) - np.dot(x_hint, z) * z
    if np.linalg.norm(x) < 1e-6:  # hint parallel to z: any perpendicular will do
        x = np.cross(z, [0.0, 1.0, 0.0] if abs(z[1]) < 0.9 else [1.0, 0.0, 0.0])
    x = x / np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


# --- UR poses -------------------------------------------------------------------------------------


def ur_pose_to_matrix(pose: ArrayLike) -> FloatArray:
    """``[x, y, z, rx, ry, rz]`` (metres, axis-angle radians) -> 4x4 matrix."""
    pose = np.asarray(pose, dtype=float)
    if pose.shape != (6,):
        raise ValueError(f"a UR pose has 6 values [x, y, z, rx, ry, rz], got shape {pose.shape}")
    return make_transform(Rotation.from_rotvec(pose[3:]).as_matrix(), pose[:3])


def matrix_to_ur_pose(transform: ArrayLike) -> FloatArray:
    """4x4 matrix -> ``[x, y, z, rx, ry, rz]`` with the rotation vector's angle in [0, pi]."""
    transform = np.asarray(transform, dtype=float)
    rotvec = Rotation.from_matrix(transform[:3, :3]).as_rotvec()
    return np.concatenate([transform[:3, 3], rotvec])


def rotation_angle_between(rotation_a: ArrayLike, rotation_b: ArrayLike) -> float:
    """Geodesic angle (radians) between two 3x3 rotations."""
    relative = np.asarray(rotation_a, dtype=float).T @ np.asarray(rotation_b, dtype=float)
    return float(np.arccos(np.clip((np.trace(relative) - 1.0) / 2.0, -1.0, 1.0)))


# --- registration ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Registration:
    """A rigid registration ``x_to = R x_from + t`` and how well the points agreed."""

    transform_to_from: FloatArray
    residuals_m: FloatArray

    @property
    def rms_residual_m(self) -> float:
        return float(np.sqrt(np.mean(self.residuals_m**2)))

    @property
    def max_residual_m(self) -> float:
        return float(np.max(self.residuals_m))

    def report(self) -> str:
        return (
            f"{len(self.residuals_m)} points, rms residual {self.rms_residual_m * 1e3:.2f} mm, "
            f"max {self.max_residual_m * 1e3:.2f} mm"
        )


def register_points(points_from: ArrayLike, points_to: ArrayLike) -> Registration:
    """Least-squares rigid transform mapping ``points_from`` onto ``points_to`` (Kabsch).

    This is the paper's world<-robot registration (``x_r = R_r x_w + T_r``): with exactly three
    calibrated points it reproduces the paper's construction; with more it is the least-squares
    fit and the residuals tell the user how good the registration is.
    """
    source = np.asarray(points_from, dtype=float)
    target = np.asarray(points_to, dtype=float)
    if source.shape != target.shape or source.ndim != 2 or source.shape[1] != 3:
        raise ValueError(
            f"need two (N, 3) point sets of equal shape, got {source.shape}, {target.shape}"
        )
    if source.shape[0] < 3:
        raise ValueError(f"registration needs at least 3 points, got {source.shape[0]}")
    centred_source = source - source.mean(axis=0)
    if np.linalg.matrix_rank(centred_source, tol=1e-6) < 2:
        raise ValueError("registration points are collinear: the rotation is undetermined")
    centred_target = target - target.mean(axis=0)
    u, _, vt = np.linalg.svd(centred_source.T @ centred_target)
    reflection_fix = np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))])
    rotation = vt.T @ reflection_fix @ u.T
    translation = target.mean(axis=0) - rotation @ source.mean(axis=0)
    transform = make_transform(rotation, translation)
    residuals = np.linalg.norm(transform_points(transform, source) - target, axis=1)
    return Registration(transform, residuals)


# --- voxel grid <-> world -------------------------------------------------------------------------


@dataclass(frozen=True)
class VoxelGrid:
    """A cubic voxel grid registered to the world as in the paper.

    ``x_w = R_v (x_v - o_v) + o_w`` with ``R_v = s [a_x a_y a_z]`` (the voxel axes' world
    directions as columns), ``s = extent_m / resolution`` metres per voxel, ``o_v`` the grid's
    bottom centre in voxel coordinates and ``o_w`` the object point on the table. Voxel (i, j, k)
    covers the continuous voxel coordinates [i, i+1) x [j, j+1) x [k, k+1); its centre is at +0.5.
    The paper's axes are a_x = (-1, 0, 0), a_y = (0, 1, 0), a_z = (0, 0, 1) (its camera looks
    along +x); ``axes_facing_camera`` derives them for any camera yaw.
    """

    resolution: int = 64
    extent_m: float = 0.26
    origin_world: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axes_world: tuple[tuple[float, float, float], ...] = field(
        default=((-1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    )

    def __post_init__(self) -> None:
        axes = np.asarray(self.axes_world, dtype=float)
        if axes.shape != (3, 3) or not np.allclose(axes @ axes.T, np.eye(3), atol=1e-6):
            raise ValueError("voxel axes must be three orthonormal world directions")
        if self.resolution < 2 or self.extent_m <= 0:
            raise ValueError("voxel grid needs resolution >= 2 and a positive extent")

    @property
    def voxel_size_m(self) -> float:
        return self.extent_m / self.resolution

    @property
    def origin_voxel(self) -> FloatArray:
        """o_v: the bottom centre of the grid in continuous voxel coordinates."""
        half = self.resolution / 2.0
        return np.array([half, half, 0.0])

    @property
    def rotation_scale(self) -> FloatArray:
        """R_v = s [a_x a_y a_z] (3x3, metres per voxel)."""
        return self.voxel_size_m * np.asarray(self.axes_world, dtype=float).T

    @property
    def matrix_world_voxel(self) -> FloatArray:
        """4x4 affine (with scale) mapping continuous voxel coordinates to world metres."""
        affine = np.eye(4)
        affine[:3, :3] = self.rotation_scale
        affine[:3, 3] = np.asarray(self.origin_world) - self.rotation_scale @ self.origin_voxel
        return affine

    def voxel_to_world(self, voxel_coords: ArrayLike) -> FloatArray:
        """Continuous voxel coordinates (..., 3) -> world points (metres)."""
        return transform_points(self.matrix_world_voxel, voxel_coords)

    def world_to_voxel(self, points_world: ArrayLike) -> FloatArray:
        """World points (metres) -> continuous voxel coordinates (..., 3)."""
        return transform_points(np.linalg.inv(self.matrix_world_voxel), points_world)

    def voxel_index(self, points_world: ArrayLike) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
        """The (i, j, k) voxel holding each world point (M, 3), and whether it lies in the grid
        (indices of points outside are out of range)."""
        points = np.asarray(points_world, dtype=float).reshape(-1, 3)
        ijk = np.floor(self.world_to_voxel(points)).astype(np.int64)
        return ijk, np.all((ijk >= 0) & (ijk < self.resolution), axis=1)

    def voxel_centres_world(self) -> FloatArray:
        """World coordinates of all voxel centres, shape (N, N, N, 3), indexed [i, j, k]."""
        index = np.arange(self.resolution) + 0.5
        grid = np.stack(np.meshgrid(index, index, index, indexing="ij"), axis=-1)
        return self.voxel_to_world(grid)


def occupied_extent_m(probabilities: ArrayLike, grid: VoxelGrid) -> FloatArray | None:
    """Extent (metres) of the voxels with occupancy > 0.5 along the grid's axes (x, y, z), whole
    voxels counted; None when no voxel is occupied."""
    occupied = np.argwhere(np.asarray(probabilities) > 0.5)
    if len(occupied) == 0:
        return None
    return (occupied.max(axis=0) - occupied.min(axis=0) + 1) * grid.voxel_size_m


def extent_along_axes_m(points_world: ArrayLike, axes_world: ArrayLike) -> FloatArray:
    """Extent (metres) of world points along each of ``axes_world``'s rows (unit vectors)."""
    return np.ptp(np.asarray(points_world, dtype=float) @ np.asarray(axes_world).T, axis=0)


def axes_facing_camera(
    camera_position_world: ArrayLike, object_point_world: ArrayLike = (0.0, 0.0, 0.0)
) -> tuple[tuple[float, float, float], ...]:
    """Voxel axes for a camera: a_z up, a_x horizontal pointing from the object to the camera.

    For a camera looking along world +x this gives the paper's a_x = (-1, 0, 0).
    """
    toward_camera = np.asarray(camera_position_world, float) - np.asarray(object_point_world, float)
    toward_camera[2] = 0.0
    if np.linalg.norm(toward_camera) < 1e-9:
        raise ValueError("camera is straight above the object point: its yaw is undefined")
    a_x = toward_camera / np.linalg.norm(toward_camera)
    a_z = np.array([0.0, 0.0, 1.0])
    a_y = np.cross(a_z, a_x)
    return tuple(tuple(float(v) for v in axis) for axis in (a_x, a_y, a_z))


# --- rays and segments ----------------------------------------------------------------------------


def ray_plane_intersection(
    origin: ArrayLike, direction: ArrayLike, plane_point: ArrayLike, plane_normal: ArrayLike
) -> float | None:
    """Ray parameter t >= 0 where ``origin + t * direction`` meets the plane, or None."""
    direction = np.asarray(direction, dtype=float)
    normal = np.asarray(plane_normal, dtype=float)
    denom = float(np.dot(direction, normal))
    if abs(denom) < 1e-12:
        return None
    t = float(np.dot(np.asarray(plane_point, float) - np.asarray(origin, float), normal) / denom)
    return t if t >= 0.0 else None


def segment_box_clip(
    start: ArrayLike, end: ArrayLike, box_min: ArrayLike, box_max: ArrayLike
) -> tuple[float, float] | None:
    """Parameters [t0, t1] within [0, 1] of the part of segment start->end inside an AABB.

    Slab method; None when the segment misses the box.
    """
    start = np.asarray(start, dtype=float)
    delta = np.asarray(end, dtype=float) - start
    t0, t1 = 0.0, 1.0
    for axis in range(3):
        lo, hi = float(box_min[axis]), float(box_max[axis])
        if abs(delta[axis]) < 1e-15:
            if not lo <= start[axis] <= hi:
                return None
            continue
        ta, tb = (lo - start[axis]) / delta[axis], (hi - start[axis]) / delta[axis]
        t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
        if t0 > t1:
            return None
    return t0, t1


def points_along_segment(start: ArrayLike, end: ArrayLike, max_step_m: float) -> FloatArray:
    """Points from start to end inclusive, no two consecutive ones further apart than max_step_m."""
    start = np.asarray(start, dtype=float)
    end = np.asarray(end, dtype=float)
    count = max(1, int(np.ceil(np.linalg.norm(end - start) / max_step_m)))
    fractions = np.linspace(0.0, 1.0, count + 1)[:, None]
    return start + fractions * (end - start)


def point_segment_distance(point: ArrayLike, start: ArrayLike, end: ArrayLike) -> float:
    """Euclidean distance from a point to the segment start->end."""
    point, start, end = (np.asarray(v, dtype=float) for v in (point, start, end))
    delta = end - start
    length_sq = float(np.dot(delta, delta))
    t = 0.0 if length_sq == 0.0 else float(np.clip(np.dot(point - start, delta) / length_sq, 0, 1))
    return float(np.linalg.norm(point - (start + t * delta)))


def radial_angle_about_vertical(
    point_a_world: ArrayLike, point_b_world: ArrayLike, axis_point_world: ArrayLike = (0, 0, 0)
) -> float:
    """Angle (radians, 0..pi) between two points around the vertical axis through axis_point.

    The paper moves directly between touches when this is small and detours above otherwise.
    """
    a = np.asarray(point_a_world, float)[:2] - np.asarray(axis_point_world, float)[:2]
    b = np.asarray(point_b_world, float)[:2] - np.asarray(axis_point_world, float)[:2]
    if np.linalg.norm(a) < 1e-9 or np.linalg.norm(b) < 1e-9:
        return 0.0
    cosine = np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.arccos(np.clip(cosine, -1.0, 1.0)))
