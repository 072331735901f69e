"""`touchshape sim snapshot`: look at the bench - camera views and one real touch."""

from __future__ import annotations

import dataclasses
import logging
from functools import partial
from pathlib import Path

import numpy as np
from matplotlib import colormaps
from PIL import Image

from controller.config import Config
from controller.motion.planner import MotionPlanner
from controller.motion.safety import Obstacles
from drivers.factory import make_devices
from models.files import write_folder_atomically
from models.geometry import invert_transform, matrix_to_ur_pose

log = logging.getLogger(__name__)


async def capture_snapshot(
    config: Config,
    *,
    object_spec: str | None = None,
    up_axis: str | None = None,
    seed: int | None = None,
) -> dict[str, np.ndarray]:
    """Render the Kinect views and touch the object once on its robot-facing side.

    Returns RGB images by name: kinect_colour, kinect_depth (colourised), tactile and
    tactile_reference (the raw GelSight frames, converted from BGR), and their difference.
    """
    sim = config.sim
    sim = dataclasses.replace(
        sim,
        object=object_spec or sim.object,
        object_up_axis=up_axis or sim.object_up_axis,
        seed=sim.seed if seed is None else seed,
    )
    devices = make_devices(
        arm=config.robot.arm,
        gripper=config.gripper,
        sensor=config.sensor,
        camera=config.cameras.rgbd,
        sim=sim,
        rng=np.random.default_rng(sim.seed),
        max_object_extent_m=config.voxel_grid.extent_m,
    )
    await devices.connect()
    try:
        frame = await devices.camera.read()
        images = {
            "kinect_colour": frame.colour_rgb,
            "kinect_depth": _colourise_depth(frame.depth_m),
        }
        assert devices.world is not None
        await devices.gripper.home()
        world = devices.world
        toward_robot = world.pose_world_base[:3, 3] * [1.0, 1.0, 0.0]
        # High on the side facing the robot: the gripper body above the pad stays clear.
        touch_height_m = max(0.008, float(world.object_mesh_world.bounds[1, 2]) - 0.02)
        point, normal = world.surface_point_toward(toward_robot, touch_height_m)
        await devices.gripper.move(
            config.motion.touch_width_m,
            speed_m_s=0.05,
            force_limit_n=config.limits.max_force_n,
            timeout_s=10,
        )
        # The controller's checked motions, clear of the true object (the sim knows it).
        planner = MotionPlanner(
            tool=world.tool,
            limits=config.limits,
            motion=config.motion,
            pose_world_base=world.pose_world_base,
            stroke_m=config.gripper.stroke_m,
        )
        obstacles = Obstacles(world.object_mesh_world.voxelized(0.004).fill().points)
        touch_geometry = planner.touch_geometry(point, -np.asarray(normal))
        arm = await devices.arm.state()
        waypoints = planner.plan_transit(
            world.pose_world_tcp(), arm.joints_rad, touch_geometry, obstacles
        )
        joints = waypoints[-1].joints_rad if waypoints else arm.joints_rad
        waypoints.append(planner.plan_approach(touch_geometry, joints, obstacles))
        pose_base_world = invert_transform(world.pose_world_base)
        for waypoint in waypoints:
            await devices.arm.move_linear(
                matrix_to_ur_pose(pose_base_world @ waypoint.pose_world_tcp),
                speed_m_s=waypoint.speed_m_s,
                acceleration_m_s2=config.limits.max_tcp_acceleration_m_s2,
                timeout_s=60.0,
            )
        reference = await devices.tactile.reference()
        touch = await devices.gripper.move(
            config.gripper.stroke_m,
            speed_m_s=0.005,
            force_limit_n=config.limits.contact_force_n,
            timeout_s=30.0,
        )
        log.info(
            "touch at %s: %s, force %.2f N",
            np.round(point, 4),
            "contact" if touch.blocked else "miss",
            touch.force_n,
        )
        tactile = await devices.tactile.read()
        images["tactile"] = tactile.image_bgr[..., ::-1]
        images["tactile_reference"] = reference.image_bgr[..., ::-1]
        # The raw change is a few grey levels on gently curved surfaces: amplify it to look at.
        change = tactile.image_bgr.astype(np.int16) - reference.image_bgr.astype(np.int16)
        images["tactile_difference_x3"] = np.clip(128 + 3 * change[..., ::-1], 0, 255).astype(
            np.uint8
        )
    finally:
        await devices.close()
    return images


def _colourise_depth(depth_m: np.ndarray) -> np.ndarray:
    """Depth as a turbo-coloured image; no return (0) is black."""
    valid = depth_m > 0
    if not valid.any():
        return np.zeros((*depth_m.shape, 3), dtype=np.uint8)
    near, far = np.percentile(depth_m[valid], [1, 99])
    scaled = np.clip((depth_m - near) / max(far - near, 1e-6), 0, 1)
    rgb = (colormaps["turbo"](scaled)[..., :3] * 255).astype(np.uint8)
    rgb[~valid] = 0
    return rgb


def save_images(images: dict[str, np.ndarray], out_dir: Path) -> list[Path]:
    """Write RGB images as ``<name>.png`` into ``out_dir``, all of them or none."""
    writers = {f"{name}.png": partial(_save_png, image_rgb) for name, image_rgb in images.items()}
    return write_folder_atomically(out_dir, writers)


def _save_png(image_rgb: np.ndarray, path: Path) -> None:
    Image.fromarray(np.ascontiguousarray(image_rgb)).save(path)
