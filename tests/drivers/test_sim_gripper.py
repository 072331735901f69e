"""Simulated WSG 50: the gel force rises on contact, motion blocks, rigid parts stall it."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
import trimesh

from controller.motion.poses import pad_pose_facing, tcp_pose_for_pad
from drivers.base import DeviceNotConnectedError, MotionRejectedError
from drivers.config import ArmConfig, GripperConfig, SensorConfig, SimConfig
from drivers.sim.gelsight import gel_pad_spec
from drivers.sim.gripper import SimWSG50
from drivers.sim.world import SimWorld
from models.geometry import invert_transform, make_transform
from models.tactile.sim import GelSightSimulator

BOX_FACE_Y_M = -0.05  # the box's robot-facing face
TOUCH_WIDTH_M = 0.08


@pytest.fixture(scope="module")
def gel() -> GelSightSimulator:
    return GelSightSimulator(gel_pad_spec(SensorConfig()))


@pytest.fixture
def world() -> SimWorld:
    box = trimesh.creation.box((0.1, 0.1, 0.1), transform=make_transform(None, (0, 0, 0.05)))
    return SimWorld(
        box, sim=SimConfig(), arm=ArmConfig(), gripper=GripperConfig(), sensor=SensorConfig()
    )


def place_tool(world: SimWorld, pose_world_tcp: np.ndarray, width_m: float) -> None:
    world.pose_base_flange = invert_transform(world.pose_world_base) @ pose_world_tcp
    world.gripper_width_m = width_m


async def homed_gripper(world: SimWorld, gel: GelSightSimulator) -> SimWSG50:
    gripper = SimWSG50(world, GripperConfig(), gel)
    await gripper.connect()
    place_tool(world, make_transform(None, (0.0, -0.3, 0.4)), 0.05)  # in free air
    await gripper.home()
    return gripper


def facing_box_face(world: SimWorld, standoff_m: float, width_m: float = TOUCH_WIDTH_M) -> None:
    pose_world_pad = pad_pose_facing((0.0, BOX_FACE_Y_M, 0.06), (0.0, -1.0, 0.0), standoff_m)
    place_tool(world, tcp_pose_for_pad(pose_world_pad, world.tool, width_m), width_m)


async def test_opening_toward_a_surface_blocks_at_the_force_limit(world, gel) -> None:
    gripper = await homed_gripper(world, gel)
    facing_box_face(world, standoff_m=0.005)
    assert world.tool_collision(world.pose_world_tcp(), TOUCH_WIDTH_M) is None
    state = await gripper.move(0.11, speed_m_s=0.005, force_limit_n=5.0, timeout_s=30)
    assert state.blocked and not state.is_moving
    assert state.force_n == pytest.approx(5.0, rel=0.05)
    # The pad travelled the 5 mm gap plus a fraction of a millimetre of gel indentation.
    pad_travel_m = (state.width_m - TOUCH_WIDTH_M) / 2
    assert 0.005 < pad_travel_m < 0.005 + 1.5e-3
    # The GelSight sees the flat face pressed uniformly across the pad.
    indentation = gel.indentation_mm(world.scene_mesh_world, world.pose_world_pad())
    assert np.mean(indentation > 0) > 0.9
    assert np.median(indentation[indentation > 0]) == pytest.approx(
        (pad_travel_m - 0.005) * 1e3, abs=0.02
    )


async def test_force_rises_monotonically_with_indentation(world, gel) -> None:
    gripper = await homed_gripper(world, gel)
    facing_box_face(world, standoff_m=0.0)
    forces = []
    for extra_mm in (0.0, 0.2, 0.4, 0.6, 0.8):
        state = await gripper.move(
            TOUCH_WIDTH_M + 2 * extra_mm * 1e-3, speed_m_s=0.01, force_limit_n=80.0, timeout_s=5
        )
        assert not state.blocked
        forces.append(state.force_n)
    assert forces[0] == pytest.approx(0.0, abs=0.05)
    assert np.all(np.diff(forces) > 1.0)  # a flat 19x14 mm face: several newtons per 0.2 mm


async def test_no_contact_is_a_miss_over_the_full_stroke(world, gel) -> None:
    gripper = await homed_gripper(world, gel)
    facing_box_face(world, standoff_m=0.06, width_m=0.0)  # the pad travels half the stroke
    state = await gripper.move(0.11, speed_m_s=0.05, force_limit_n=5.0, timeout_s=10)
    assert not state.blocked
    assert state.width_m == pytest.approx(0.11)
    assert state.force_n == 0.0


async def test_contact_by_another_part_stalls_at_the_force_limit(world, gel) -> None:
    gripper = await homed_gripper(world, gel)
    # Turn the tool around: the plain finger (-x side) now faces the box 3 mm away.
    pose_world_pad = pad_pose_facing((0.0, BOX_FACE_Y_M, 0.06), (0.0, -1.0, 0.0), 0.0)
    pose_world_tcp = tcp_pose_for_pad(pose_world_pad, world.tool, 0.02)
    flip = make_transform(np.diag([-1.0, -1.0, 1.0]))  # 180 degrees about the finger axis
    pose_world_tcp = pose_world_tcp @ flip
    finger_face_y = (pose_world_tcp @ [-0.01 - 0.008, 0, 0, 1])[1]  # outer face of that finger
    pose_world_tcp[1, 3] += BOX_FACE_Y_M - 0.003 - finger_face_y
    place_tool(world, pose_world_tcp, 0.02)
    assert world.tool_collision(pose_world_tcp, 0.02) is None
    state = await gripper.move(0.11, speed_m_s=0.01, force_limit_n=20.0, timeout_s=10)
    assert state.blocked
    assert state.force_n == 20.0
    assert (state.width_m - 0.02) / 2 == pytest.approx(0.003, abs=2e-4)


async def test_stop_ends_a_move_early(world, gel) -> None:
    gripper = await homed_gripper(world, gel)
    await gripper.move(0.0, speed_m_s=0.1, force_limit_n=80.0, timeout_s=5)
    move = asyncio.create_task(gripper.move(0.1, speed_m_s=0.01, force_limit_n=80, timeout_s=20))
    # Planned in a worker thread, then moving. The wait sleeps rather than spinning on
    # sleep(0): a spinning loop keeps the GIL from that worker thread and the move crawls.
    async with asyncio.timeout(30):
        while world.gripper_width_m == 0.0:
            await asyncio.sleep(0.0005)
    await gripper.stop()
    state = await move
    assert 0.0 < state.width_m < 0.1 and not state.is_moving


async def test_stop_while_the_move_is_planned_keeps_the_fingers_still(world, gel) -> None:
    gripper = await homed_gripper(world, gel)
    await gripper.move(0.0, speed_m_s=0.1, force_limit_n=80.0, timeout_s=5)
    move = asyncio.create_task(gripper.move(0.1, speed_m_s=0.01, force_limit_n=80, timeout_s=20))
    await asyncio.sleep(0)  # the move is planning in its worker thread: busy already
    with pytest.raises(MotionRejectedError, match="busy"):
        await gripper.move(0.05, speed_m_s=0.01, force_limit_n=80, timeout_s=20)
    await gripper.stop()
    state = await move
    assert state.width_m == 0.0 and not state.is_moving and not state.blocked


async def test_bad_commands_are_rejected(world, gel) -> None:
    gripper = SimWSG50(world, GripperConfig(), gel)
    with pytest.raises(DeviceNotConnectedError):
        await gripper.state()
    await gripper.connect()
    with pytest.raises(MotionRejectedError, match="home"):
        await gripper.move(0.05, speed_m_s=0.01, force_limit_n=5, timeout_s=1)
    gripper = await homed_gripper(world, gel)
    for width, speed, force in (
        (0.2, 0.01, 5.0),
        (-0.01, 0.01, 5.0),
        (0.05, 0.0, 5.0),
        (0.05, 1.0, 5.0),
        (0.05, 0.01, 500.0),
    ):
        with pytest.raises(MotionRejectedError):
            await gripper.move(width, speed_m_s=speed, force_limit_n=force, timeout_s=5)
    await gripper.close()
    await gripper.close()
    assert not gripper.is_connected
