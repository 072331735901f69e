"""The simulated bench's physical world and shared state.

One ``SimWorld`` holds the table, the fixed object, the arm's joint state and the finger opening;
the simulated camera, GelSight, arm and gripper all read and change this one state, so a touch
seen by the GelSight is exactly where the arm and gripper put the pad.

Threads: the state (joints, flange pose, finger opening, clock) changes on the event loop only.
The devices' heavy work (collision checks, finger planning, gel forces and images, depth noise)
runs in worker threads on poses and openings read before the hop and on the fixed geometry
(meshes, tool, their lazy caches built here), and its result is committed on the loop after the
await: a call cancelled meanwhile commits nothing. The session awaits one device call at a time,
so each computation starts from the state the previous one left.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
import trimesh
from numpy.typing import NDArray

from drivers.config import ArmConfig, GripperConfig, SensorConfig, SimConfig
from drivers.tool import ToolBox, ToolModel
from models.geometry import (
    invert_transform,
    make_transform,
    rotation_about_axis,
    transform_points,
    ur_pose_to_matrix,
)
from models.procedural import object_mesh
from models.render import Scene, SceneObject, make_table
from models.shapes import check_explorable

log = logging.getLogger(__name__)

_T = TypeVar("_T")

COLLISION_LINE_SPACING_M = 0.004
"""Spacing of the probe lines on each tool box face: thinner object slivers could slip through."""
CONTACT_POINT_SPACING_M = 0.002
"""Spacing of the points on a tool box's faces whose depth in the object gives a contact's."""


def min_object_extent_m(sensor: SensorConfig) -> float:
    """The smallest object the bench explores: its largest side must be at least the gel
    pad's (19 mm by default). Anything smaller fits inside one contact, so a touch cannot
    tell one part of it from another and further touches add nothing; it would also be under
    five voxels of the default 4 mm grid, below what the vision estimate resolves."""
    return max(sensor.pad_width_mm, sensor.pad_height_mm) / 1e3


class SimClock:
    """Simulated time. ``real_time_factor`` 0 runs motions instantly (still yielding to the
    event loop at every step), 1 runs them in real time."""

    def __init__(self, real_time_factor: float = 0.0) -> None:
        self.real_time_factor = real_time_factor
        self.now_s = 0.0

    async def advance(self, dt_s: float) -> None:
        self.now_s += dt_s
        await asyncio.sleep(dt_s * self.real_time_factor)


@dataclass(frozen=True)
class Collision:
    """Which rigid tool part touches what; for a contact (``SimWorld.tool_contact``) also how
    deep it presses in and the force that pushes the tool back."""

    part: str
    obstacle: str  # "object" or "table"
    depth_m: float = 0.0
    force_world_n: tuple[float, float, float] = (0.0, 0.0, 0.0)


class SimWorld:
    """Table (top at world z=0) + one fixed object + the robot's state.

    ``scene`` is what the camera renders; ``scene_mesh_world`` (object + table) is what the gel
    pad can press against.
    """

    def __init__(
        self,
        object_mesh_world: trimesh.Trimesh,
        *,
        sim: SimConfig,
        arm: ArmConfig,
        gripper: GripperConfig,
        sensor: SensorConfig,
    ) -> None:
        self.sim_config = sim
        self.arm_config = arm
        self.gripper_config = gripper
        self.sensor_config = sensor
        self.object_mesh_world = object_mesh_world
        self.scene = Scene(
            objects=[SceneObject(object_mesh_world, albedo_rgb=sim.object_albedo_rgb)],
            table=make_table(sim.table_size_m),
        )
        self.table_mesh_world = self.scene.table.mesh
        self.scene_mesh_world = trimesh.util.concatenate(
            [self.object_mesh_world, self.table_mesh_world]
        )
        self._compute_lock = threading.Lock()
        # Background scores may query these meshes from other threads: build trimesh's lazy
        # caches now, so those threads only read them.
        for mesh in (self.object_mesh_world, self.scene_mesh_world):
            mesh.ray.intersects_any([[0.0, 0.0, 10.0]], [[0.0, 0.0, -1.0]])
            _ = mesh.face_normals, mesh.area_faces
        self.tool = ToolModel(gripper, sensor)
        self.clock = SimClock(sim.real_time_factor)
        self.pose_world_base = ur_pose_to_matrix(arm.pose_world_base)
        self.joints_rad = np.asarray(arm.home_joints_rad, dtype=float)
        self.pose_base_flange = np.eye(4)  # set by the arm from forward kinematics on connect
        self.gripper_width_m = gripper.stroke_m / 2

    async def compute(self, function: Callable[..., _T], *args: Any, **kwargs: Any) -> _T:
        """Run a device simulation's computation in a worker thread, one at a time: trimesh's
        lazily built structures and Embree's scenes are not documented as safe to enter from
        two threads at once, and one at a time keeps the simulation's results independent of
        thread timing."""

        def locked() -> _T:
            with self._compute_lock:
                return function(*args, **kwargs)

        return await asyncio.to_thread(locked)

    @classmethod
    def from_config(
        cls,
        sim: SimConfig,
        arm: ArmConfig,
        gripper: GripperConfig,
        sensor: SensorConfig,
        *,
        max_object_extent_m: float | None = None,
    ) -> SimWorld:
        """Build the object from the shape library (or a mesh file) at the world origin.

        ShapeError (one line naming the file) when the bench cannot explore it: larger than
        ``max_object_extent_m`` on a side (the controller passes its voxel grid's extent: the
        shape is perceived in that cube; None = no upper limit), smaller than the gel pad
        (``min_object_extent_m``), or not a closed solid."""
        rng = np.random.default_rng(sim.seed)
        mesh = object_mesh(sim.object, rng, up_axis=sim.object_up_axis, scale=sim.object_scale)
        check_explorable(
            mesh,
            sim.object,
            min_extent_m=min_object_extent_m(sensor),
            max_extent_m=max_object_extent_m,
        )
        mesh.apply_transform(
            make_transform(rotation_about_axis((0, 0, 1), np.radians(sim.object_yaw_deg)))
        )
        return cls(mesh, sim=sim, arm=arm, gripper=gripper, sensor=sensor)

    # --- poses ----------------------------------------------------------------------------------

    def pose_world_tcp(self) -> NDArray[np.float64]:
        return self.pose_world_base @ self.pose_base_flange

    def pose_world_pad(self) -> NDArray[np.float64]:
        return self.pose_world_tcp() @ self.tool.pose_tcp_pad(self.gripper_width_m)

    def surface_point_toward(
        self, direction_world: NDArray[np.float64], height_m: float
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Object surface point (and outward face normal) seen from far out along a horizontal
        direction at a height above the table."""
        direction = np.asarray(direction_world, dtype=float) * [1.0, 1.0, 0.0]
        direction /= np.linalg.norm(direction)
        origin = direction * 1.0 + [0.0, 0.0, height_m]
        locations, _, triangles = self.object_mesh_world.ray.intersects_location(
            [origin], [-direction], multiple_hits=False
        )
        if len(locations) == 0:
            raise ValueError(f"no object surface along {direction} at height {height_m} m")
        return locations[0], self.object_mesh_world.face_normals[triangles[0]]

    # --- collision ------------------------------------------------------------------------------

    def tool_collision(
        self, pose_world_tcp: NDArray[np.float64], width_m: float
    ) -> Collision | None:
        """First rigid tool part that penetrates the object or the table, or None."""
        for box, _, obstacle in self._touching_parts(pose_world_tcp, width_m):
            return Collision(box.name, obstacle)
        return None

    def tool_contact(self, pose_world_tcp: NDArray[np.float64], width_m: float) -> Collision | None:
        """The deepest contact of a rigid tool part with the object or the table, with the
        force it makes, or None when nothing touches. The force is elastic: the sim config's
        ``contact_stiffness_n_per_m`` times the depth of the deepest point, pushing the tool out
        along the way that point leaves the obstacle (the compliance of the object, the table
        and the arm's joints, lumped)."""
        deepest: tuple[float, NDArray[np.float64], str, str] | None = None
        for box, pose_world_box, obstacle in self._touching_parts(pose_world_tcp, width_m):
            penetration = (
                self._table_penetration if obstacle == "table" else self._object_penetration
            )
            depth_m, push_world = penetration(pose_world_box, box.half_extents_m)
            if deepest is None or depth_m > deepest[0]:
                deepest = (depth_m, push_world, box.name, obstacle)
        if deepest is None:
            return None
        depth_m, push_world, part, obstacle = deepest
        force = self.sim_config.contact_stiffness_n_per_m * depth_m * push_world
        return Collision(
            part, obstacle, depth_m, (float(force[0]), float(force[1]), float(force[2]))
        )

    def _touching_parts(
        self, pose_world_tcp: NDArray[np.float64], width_m: float
    ) -> Iterator[tuple[ToolBox, NDArray[np.float64], str]]:
        """Every rigid tool part in contact, with its world pose and what it meets ("table",
        then "object"), part by part: lazily, so the first one costs only its own tests."""
        for box in self.tool.rigid_boxes(width_m):
            pose_world_box = pose_world_tcp @ box.pose_tcp_box
            if self._box_below_table(pose_world_box, box.half_extents_m):
                yield box, pose_world_box, "table"
            if self._box_hits_object(pose_world_box, box):
                yield box, pose_world_box, "object"

    def _table_penetration(
        self, pose_world_box: NDArray[np.float64], half: NDArray
    ) -> tuple[float, NDArray[np.float64]]:
        corners = transform_points(pose_world_box, _BOX_CORNER_SIGNS * half)
        return float(max(0.0, -corners[:, 2].min())), np.array([0.0, 0.0, 1.0])

    def _object_penetration(
        self, pose_world_box: NDArray[np.float64], half: NDArray
    ) -> tuple[float, NDArray[np.float64]]:
        """How deep a box presses into the object, and the way out (world, unit). Two cases,
        the deeper counts: object vertices inside the box (an edge or a corner poking in: the
        depth is the vertex's distance from the nearest box face, pushed back through it) and
        points of the box's faces inside the object (a face pressed onto a surface: the depth
        is the shortest way out along the box's axes, pushed that way)."""
        world_box = invert_transform(pose_world_box)
        mesh = self.object_mesh_world
        best_depth, best_push = 0.0, np.array([0.0, 0.0, 1.0])
        local = transform_points(world_box, mesh.vertices)
        inside = np.all(np.abs(local) < half, axis=1)
        if np.any(inside):
            gaps = half - np.abs(local[inside])  # to each pair of faces
            axis = np.argmin(gaps, axis=1)
            depths = gaps[np.arange(len(axis)), axis]
            k = int(np.argmax(depths))
            push_box = np.zeros(3)
            push_box[axis[k]] = -np.sign(local[inside][k, axis[k]]) or 1.0
            best_depth, best_push = float(depths[k]), pose_world_box[:3, :3] @ push_box
        face_points = transform_points(pose_world_box, _box_face_points(half))
        in_object = mesh.contains(face_points)
        if np.any(in_object):
            points = face_points[in_object]
            axes = np.concatenate([pose_world_box[:3, :3].T, -pose_world_box[:3, :3].T])
            origins = np.repeat(points, len(axes), axis=0)
            directions = np.tile(axes, (len(points), 1))
            _, rays, hits = mesh.ray.intersects_id(
                origins, directions, multiple_hits=False, return_locations=True
            )
            out_m = np.full(len(origins), np.inf)
            out_m[rays] = np.linalg.norm(hits - origins[rays], axis=1)
            out_m = out_m.reshape(len(points), len(axes))
            way = np.argmin(out_m, axis=1)
            depths = out_m[np.arange(len(points)), way]
            k = int(np.argmax(np.where(np.isfinite(depths), depths, -1.0)))
            if np.isfinite(depths[k]) and depths[k] > best_depth:
                best_depth, best_push = float(depths[k]), axes[way[k]]
        return best_depth, best_push

    def _box_below_table(self, pose_world_box: NDArray[np.float64], half: NDArray) -> bool:
        corners = transform_points(pose_world_box, _BOX_CORNER_SIGNS * half)
        table_x, table_y = self.sim_config.table_size_m
        on_table = (np.abs(corners[:, 0]) <= table_x / 2) & (np.abs(corners[:, 1]) <= table_y / 2)
        return bool(np.any(on_table & (corners[:, 2] < 0.0)))

    def _box_hits_object(self, pose_world_box: NDArray[np.float64], box: ToolBox) -> bool:
        half = box.half_extents_m
        # Object vertices inside the box catch parts poking in; probe lines on the box faces
        # catch surfaces crossing a face between vertices.
        vertices_box = transform_points(
            invert_transform(pose_world_box), self.object_mesh_world.vertices
        )
        if np.any(np.all(np.abs(vertices_box) < half, axis=1)):
            return True
        origins_box, directions_box, lengths = _face_probe_lines(half)
        origins = transform_points(pose_world_box, origins_box)
        directions = directions_box @ pose_world_box[:3, :3].T
        _, ray_ids, locations = self.object_mesh_world.ray.intersects_id(
            origins, directions, multiple_hits=False, return_locations=True
        )
        if len(ray_ids) == 0:
            return False
        distances = np.linalg.norm(locations - origins[ray_ids], axis=1)
        return bool(np.any(distances <= lengths[ray_ids]))


_BOX_CORNER_SIGNS = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T


def _box_face_points(half: NDArray) -> NDArray[np.float64]:
    """Points on a box's six faces, CONTACT_POINT_SPACING_M apart (box frame)."""
    points = []
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        grid_u = np.linspace(
            -half[u], half[u], max(2, int(np.ceil(2 * half[u] / CONTACT_POINT_SPACING_M)) + 1)
        )
        grid_v = np.linspace(
            -half[v], half[v], max(2, int(np.ceil(2 * half[v] / CONTACT_POINT_SPACING_M)) + 1)
        )
        gu, gv = np.meshgrid(grid_u, grid_v, indexing="ij")
        for side in (-half[axis], half[axis]):
            face = np.zeros((gu.size, 3))
            face[:, axis], face[:, u], face[:, v] = side, gu.ravel(), gv.ravel()
            points.append(face)
    return np.concatenate(points)


def _face_probe_lines(half: NDArray) -> tuple[NDArray, NDArray, NDArray]:
    """Segments covering a box's faces: for each axis, lines parallel to it on the four faces
    that contain that direction, spaced COLLISION_LINE_SPACING_M apart (box frame)."""
    origins, directions, lengths = [], [], []
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        count_u = max(2, int(np.ceil(2 * half[u] / COLLISION_LINE_SPACING_M)) + 1)
        count_v = max(2, int(np.ceil(2 * half[v] / COLLISION_LINE_SPACING_M)) + 1)
        grid_u = np.linspace(-half[u], half[u], count_u)
        grid_v = np.linspace(-half[v], half[v], count_v)
        # Lines on the two faces at u = +-half[u] and the two at v = +-half[v].
        for fixed, sweep, grid in ((u, v, grid_v), (v, u, grid_u)):
            for side in (-half[fixed], half[fixed]):
                start = np.zeros((len(grid), 3))
                start[:, axis] = -half[axis]
                start[:, fixed] = side
                start[:, sweep] = grid
                origins.append(start)
                direction = np.zeros((len(grid), 3))
                direction[:, axis] = 1.0
                directions.append(direction)
                lengths.append(np.full(len(grid), 2 * half[axis]))
    return np.concatenate(origins), np.concatenate(directions), np.concatenate(lengths)
