"""The simulated devices compute in worker threads and change the shared world on the event
loop only: a sequence of device calls gives the same result every time, also with another task
reading the devices' states all along, and a reader never sees a half-committed arm step."""

from __future__ import annotations

import asyncio
from dataclasses import dataclass

import numpy as np
import pytest

from controller.config import Config
from controller.motion.poses import pad_pose_facing, tcp_pose_for_pad
from drivers.factory import Devices, make_devices
from drivers.ur5.kinematics import forward_kinematics
from models.geometry import invert_transform, matrix_to_ur_pose, ur_pose_to_matrix


@dataclass
class Outcome:
    depth_m: np.ndarray
    reference_bgr: np.ndarray
    joints_rad: np.ndarray
    width_m: float
    force_n: float
    blocked: bool
    tactile_bgr: np.ndarray


def sim_devices(config: Config) -> Devices:
    return make_devices(
        arm=config.robot.arm,
        gripper=config.gripper,
        sensor=config.sensor,
        camera=config.cameras.rgbd,
        sim=config.sim,
        rng=np.random.default_rng(7),
    )


async def touch_sequence(devices: Devices, config: Config) -> Outcome:
    """Camera frame, GelSight reference, an arm move, then a finger sweep into the object from
    a pose facing its side and a GelSight frame of the contact."""
    world = devices.world
    assert world is not None
    await devices.connect()
    await devices.gripper.home()
    frame = await devices.camera.read()
    reference = await devices.tactile.reference()
    pose = ur_pose_to_matrix((await devices.arm.state()).pose_base_tcp)
    pose[2, 3] -= 0.05
    await devices.arm.move_linear(
        matrix_to_ur_pose(pose), speed_m_s=0.1, acceleration_m_s2=0.5, timeout_s=10.0
    )
    joints = (await devices.arm.state()).joints_rad
    # Face the object's side: the tool placed directly, as the touch benchmark does.
    point, normal = world.surface_point_toward(np.array([0.0, -1.0, 0.0]), 0.05)
    width = config.motion.touch_width_m
    pose_world_pad = pad_pose_facing(point, -normal, 0.01)
    pose_world_tcp = tcp_pose_for_pad(pose_world_pad, world.tool, width)
    world.pose_base_flange = invert_transform(world.pose_world_base) @ pose_world_tcp
    state = await devices.gripper.move(
        config.gripper.stroke_m,
        speed_m_s=config.motion.finger_speed_m_s,
        force_limit_n=config.limits.contact_force_n,
        timeout_s=10.0,
    )
    tactile = await devices.tactile.read()
    await devices.close()
    return Outcome(
        frame.depth_m,
        reference.image_bgr,
        joints,
        state.width_m,
        state.force_n,
        state.blocked,
        tactile.image_bgr,
    )


async def read_states_until(devices: Devices, done: asyncio.Event) -> int:
    """Query the arm and gripper states as fast as the loop allows; while the arm moves, the
    world's flange pose must be that of its joints (never a step half-applied). Returns how
    many reads were made during arm moves."""
    world = devices.world
    assert world is not None
    reads_while_moving = 0
    while not done.is_set():
        if devices.arm.is_connected and devices.gripper.is_connected:
            arm = await devices.arm.state()
            if arm.is_moving:
                expected = forward_kinematics(world.joints_rad)
                assert np.allclose(world.pose_base_flange, expected)
                reads_while_moving += 1
            await devices.gripper.state()
        await asyncio.sleep(0)
    return reads_while_moving


@pytest.fixture(scope="module")
def config() -> Config:
    return Config()


async def test_device_calls_are_deterministic_with_readers_alongside(config: Config) -> None:
    alone = await touch_sequence(sim_devices(config), config)
    devices = sim_devices(config)
    done = asyncio.Event()
    reader = asyncio.create_task(read_states_until(devices, done))
    try:
        watched = await touch_sequence(devices, config)
    finally:
        done.set()
    assert await reader > 20
    assert alone.blocked and alone.force_n > 0.0  # a real contact, with noise drawn throughout
    for field in Outcome.__dataclass_fields__:
        first, second = getattr(alone, field), getattr(watched, field)
        assert np.array_equal(first, second), field
