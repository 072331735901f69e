"""SimUR5: kinematics, trapezoidal timing, straight lines, collisions, stop and cancel."""

from __future__ import annotations

import asyncio
import math
from collections.abc import AsyncIterator

import numpy as np
import pytest
import trimesh

from drivers.base import (
    ArmState,
    DeviceNotConnectedError,
    DeviceTimeoutError,
    MotionRejectedError,
    ProtectiveStopError,
)
from drivers.config import ArmConfig, GripperConfig, SensorConfig, SimConfig
from drivers.sim.arm import PROTECTIVE_STOP_HOLD_S, SimUR5
from drivers.sim.world import SimWorld
from drivers.ur5.kinematics import forward_kinematics, inverse_kinematics
from models.geometry import (
    invert_transform,
    make_transform,
    matrix_to_ur_pose,
    point_segment_distance,
    rotation_about_axis,
    rotation_angle_between,
    ur_pose_to_matrix,
)

TOOL_DOWN = rotation_about_axis((0.0, 1.0, 0.0), np.pi)
"""Tool z along world -z (the base frame is not rotated in the world)."""
FACING_OBJECT_JOINTS = np.array([-1.5708, -1.5708, 1.5708, -1.5708, -1.5708, 0.0])
"""Home with the shoulder turned to face the object (world origin, base +y)."""
START_WORLD = (0.25, 0.0, 0.3)
"""Flange start, 0.2 m to the +x side of the 10 cm box, fingertips 12.8 cm above the table."""
PERIOD_S = 1.0 / ArmConfig().control_frequency_hz


@pytest.fixture
def world() -> SimWorld:
    box = trimesh.creation.box(
        (0.1, 0.1, 0.1), transform=trimesh.transformations.translation_matrix((0, 0, 0.05))
    )
    return SimWorld(
        box, sim=SimConfig(), arm=ArmConfig(), gripper=GripperConfig(), sensor=SensorConfig()
    )


@pytest.fixture
async def arm(world: SimWorld) -> AsyncIterator[SimUR5]:
    """Connected arm with the flange at START_WORLD, tool pointing down."""
    joints = inverse_kinematics(base_pose(world, START_WORLD), FACING_OBJECT_JOINTS)
    assert joints is not None
    world.joints_rad = joints
    arm = SimUR5(world, ArmConfig())
    await arm.connect()
    yield arm
    await arm.close()


def base_pose(world: SimWorld, position_world: tuple[float, float, float]) -> np.ndarray:
    """4x4 tool-down pose in the base frame at a world position."""
    return invert_transform(world.pose_world_base) @ make_transform(TOOL_DOWN, position_world)


def ur_target(world: SimWorld, position_world: tuple[float, float, float]) -> np.ndarray:
    return matrix_to_ur_pose(base_pose(world, position_world))


async def move_l(arm: SimUR5, target: np.ndarray, speed: float = 0.25, acc: float = 1.0) -> None:
    await arm.move_linear(target, speed_m_s=speed, acceleration_m_s2=acc, timeout_s=30.0)


async def record_while(task: asyncio.Task, arm: SimUR5) -> list[ArmState]:
    """Every state the arm passes through until ``task`` is done. Polled every millisecond, not
    at every yield: each control step computes in a worker thread, which a loop spinning on
    ``sleep(0)`` would starve of the GIL."""
    states: list[ArmState] = []
    while not task.done():
        state = await arm.state()
        if not states or not np.array_equal(state.joints_rad, states[-1].joints_rad):
            states.append(state)
        await asyncio.sleep(0.001)
    return states


async def sim_time_passes(world: SimWorld, duration_s: float) -> None:
    """Wait until ``duration_s`` of simulated time has passed. The wait sleeps (as an event
    loop with nothing to do does) rather than spinning on ``sleep(0)``: a spinning loop keeps
    the GIL from the worker thread that computes each control step, and the move crawls. The
    60 s bound only stops a hung move from hanging the test run."""
    end_s = world.clock.now_s + duration_s
    async with asyncio.timeout(60.0):
        while world.clock.now_s < end_s:
            await asyncio.sleep(0.0005)


def pose_error(pose_a: np.ndarray, pose_b: np.ndarray) -> tuple[float, float]:
    a, b = ur_pose_to_matrix(pose_a), ur_pose_to_matrix(pose_b)
    return float(np.linalg.norm(a[:3, 3] - b[:3, 3])), rotation_angle_between(a[:3, :3], b[:3, :3])


def trapezoid_time(distance: float, speed: float, acc: float) -> float:
    if distance * acc >= speed**2:
        return distance / speed + speed / acc
    return 2.0 * math.sqrt(distance / acc)


def test_fk_ik_round_trip(rng: np.random.Generator) -> None:
    for _ in range(50):
        joints = FACING_OBJECT_JOINTS + rng.uniform(-0.5, 0.5, 6)
        pose = forward_kinematics(joints)
        solution = inverse_kinematics(pose, joints + rng.uniform(-0.02, 0.02, 6))
        assert solution is not None
        np.testing.assert_allclose(solution, joints, atol=1e-6)
        np.testing.assert_allclose(forward_kinematics(solution), pose, atol=1e-9)
    assert inverse_kinematics(make_transform(None, (2.0, 0.0, 0.3)), joints) is None


async def test_connect_sets_flange_from_fk(arm: SimUR5, world: SimWorld) -> None:
    np.testing.assert_allclose(
        world.pose_world_tcp(), make_transform(TOOL_DOWN, START_WORLD), atol=1e-9
    )
    state = await arm.state()
    assert not state.is_moving and not state.protective_stopped
    assert state.timestamp_s == world.clock.now_s


async def test_move_linear_reaches_target_on_a_straight_line(arm: SimUR5, world: SimWorld) -> None:
    start = (await arm.state()).pose_base_tcp
    target_matrix = base_pose(world, (0.15, 0.1, 0.25)) @ make_transform(
        rotation_about_axis((1.0, 0.0, 0.0), 0.3)
    )
    target = matrix_to_ur_pose(target_matrix)
    task = asyncio.create_task(move_l(arm, target))
    states = await record_while(task, arm)
    await task

    position_error, angle_error = pose_error((await arm.state()).pose_base_tcp, target)
    assert position_error < 1e-6 and angle_error < 1e-6
    assert len(states) > 50 and any(s.is_moving for s in states)
    for state in states:
        assert point_segment_distance(state.pose_base_tcp[:3], start[:3], target[:3]) < 1e-9
    # Orientation progresses with position (both follow one path parameter).
    total_m = np.linalg.norm(target[:3] - start[:3])
    total_rad = pose_error(start, target)[1]
    for state in states[::10]:
        fraction = np.linalg.norm(state.pose_base_tcp[:3] - start[:3]) / total_m
        assert pose_error(start, state.pose_base_tcp)[1] == pytest.approx(
            fraction * total_rad, abs=1e-6
        )
    assert not (await arm.state()).is_moving


async def test_move_linear_moves_the_tcp_not_the_flange(world: SimWorld) -> None:
    tcp_offset = (0.0, 0.02, 0.15, 0.0, 0.0, 0.4)
    joints = inverse_kinematics(base_pose(world, START_WORLD), FACING_OBJECT_JOINTS)
    world.joints_rad = joints
    arm = SimUR5(world, ArmConfig(tcp_offset=tcp_offset))
    await arm.connect()
    start = (await arm.state()).pose_base_tcp
    np.testing.assert_allclose(
        ur_pose_to_matrix(start),
        world.pose_base_flange @ ur_pose_to_matrix(tcp_offset),
        atol=1e-12,
    )
    target = matrix_to_ur_pose(
        ur_pose_to_matrix(start)
        @ make_transform(rotation_about_axis((0, 1, 0), 0.5), (0.05, 0.0, 0.0))
    )
    task = asyncio.create_task(move_l(arm, target))
    states = await record_while(task, arm)
    await task
    position_error, angle_error = pose_error((await arm.state()).pose_base_tcp, target)
    assert position_error < 1e-6 and angle_error < 1e-6
    for state in states:
        assert point_segment_distance(state.pose_base_tcp[:3], start[:3], target[:3]) < 1e-9
    await arm.close()


@pytest.mark.parametrize("distance_m", [0.2, 0.01])  # trapezoid, triangle
async def test_move_linear_takes_the_trapezoid_time(
    arm: SimUR5, world: SimWorld, distance_m: float
) -> None:
    x, y, z = START_WORLD
    start_s = world.clock.now_s
    await move_l(arm, ur_target(world, (x, y - distance_m, z)), speed=0.25, acc=1.0)
    elapsed_s = world.clock.now_s - start_s
    expected_s = trapezoid_time(distance_m, 0.25, 1.0)
    assert expected_s - 1e-9 <= elapsed_s <= expected_s + PERIOD_S


async def test_pure_rotation_takes_time(arm: SimUR5, world: SimWorld) -> None:
    target = matrix_to_ur_pose(
        base_pose(world, START_WORLD) @ make_transform(rotation_about_axis((0, 0, 1), 1.0))
    )
    start_s = world.clock.now_s
    await move_l(arm, target)
    assert world.clock.now_s - start_s >= 1.0  # rotation capped at 1 rad/s
    assert pose_error((await arm.state()).pose_base_tcp, target)[1] < 1e-6


async def test_unreachable_target_is_rejected_without_motion(arm: SimUR5, world: SimWorld) -> None:
    joints, now_s = world.joints_rad.copy(), world.clock.now_s
    with pytest.raises(MotionRejectedError, match="unreachable"):
        await move_l(arm, ur_target(world, (1.5, 0.0, 0.3)))
    np.testing.assert_array_equal(world.joints_rad, joints)
    assert world.clock.now_s == now_s


@pytest.mark.parametrize(
    ("target", "kwargs"),
    [
        ((0.1, 0.4, 0.3, 0.0, np.pi, np.nan), {}),
        ((0.1, 0.4, 0.3), {}),
        ((0.1, 0.4, 0.3, 0.0, np.pi, 0.0), {"speed_m_s": 1.5}),
        ((0.1, 0.4, 0.3, 0.0, np.pi, 0.0), {"speed_m_s": 0.0}),
        ((0.1, 0.4, 0.3, 0.0, np.pi, 0.0), {"acceleration_m_s2": 6.0}),
        ((0.1, 0.4, 0.3, 0.0, np.pi, 0.0), {"timeout_s": 0.0}),
    ],
)
async def test_bad_move_linear_arguments_are_rejected(
    arm: SimUR5, target: tuple, kwargs: dict
) -> None:
    arguments = {"speed_m_s": 0.1, "acceleration_m_s2": 1.0, "timeout_s": 10.0} | kwargs
    with pytest.raises(MotionRejectedError):
        await arm.move_linear(np.array(target), **arguments)
    assert not (await arm.state()).is_moving


async def test_rotation_past_the_joint_limit_stops_at_the_limit(
    arm: SimUR5, world: SimWorld
) -> None:
    world.joints_rad = world.joints_rad + np.array([0, 0, 0, 0, 0, 6.0 - world.joints_rad[5]])
    await arm.connect()
    pose = (await arm.state()).pose_base_tcp
    target = matrix_to_ur_pose(
        ur_pose_to_matrix(pose) @ make_transform(rotation_about_axis((0, 0, 1), 0.5))
    )
    with pytest.raises(MotionRejectedError, match="limit"):
        await move_l(arm, target)
    # Stopped within one step (1 rad/s rotation cap) before wrist 3 passes 2 pi.
    assert 2 * np.pi - PERIOD_S <= world.joints_rad[5] <= 2 * np.pi
    assert not (await arm.state()).is_moving


async def test_line_through_the_base_axis_is_rejected_midway(arm: SimUR5, world: SimWorld) -> None:
    start = (await arm.state()).pose_base_tcp
    target = start.copy()
    target[:2] = -start[:2]  # the line passes over the base
    with pytest.raises(MotionRejectedError, match="singular"):
        await move_l(arm, target)
    reached = (await arm.state()).pose_base_tcp
    assert point_segment_distance(reached[:3], start[:3], target[:3]) < 1e-9
    assert 0.05 < np.linalg.norm(reached[:3] - start[:3]) < np.linalg.norm(target[:3] - start[:3])
    assert not (await arm.state()).is_moving


async def test_move_into_table_protective_stops_and_recovers(arm: SimUR5, world: SimWorld) -> None:
    x, y, _ = START_WORLD
    with pytest.raises(ProtectiveStopError, match="table"):
        await move_l(arm, ur_target(world, (x, y, 0.1)), speed=0.1)
    stopped_at_s = world.clock.now_s
    # The fingertips press into the table until the force passes the protective-stop limit:
    # the arm holds the last pose under it, within a step of the depth that makes it.
    fingertip_z = world.pose_world_tcp()[2, 3] - world.tool.finger_tip_z_m
    stop_depth_m = (
        world.sim_config.protective_stop_force_n / world.sim_config.contact_stiffness_n_per_m
    )
    assert stop_depth_m - 0.1 * PERIOD_S - 1e-9 < -fingertip_z <= stop_depth_m + 1e-9
    state = await arm.state()
    assert state.protective_stopped and not state.is_moving
    limit_n = world.sim_config.protective_stop_force_n
    step_n = world.sim_config.contact_stiffness_n_per_m * 0.1 * PERIOD_S  # a step's press
    assert limit_n - step_n - 1e-6 < state.tcp_wrench_base[2] <= limit_n  # pushed up
    assert arm.protective_stops[-1].obstacle == "table"

    with pytest.raises(ProtectiveStopError):
        await move_l(arm, ur_target(world, START_WORLD))
    with pytest.raises(ProtectiveStopError):
        await arm.move_joints(
            FACING_OBJECT_JOINTS, speed_rad_s=1.0, acceleration_rad_s2=1.0, timeout_s=10.0
        )
    with pytest.raises(DeviceTimeoutError):
        await arm.recover_protective_stop(timeout_s=1.0)
    assert (await arm.state()).protective_stopped

    await arm.recover_protective_stop()
    assert world.clock.now_s - stopped_at_s >= PROTECTIVE_STOP_HOLD_S
    assert not (await arm.state()).protective_stopped
    await move_l(arm, ur_target(world, START_WORLD))
    np.testing.assert_allclose(world.pose_world_tcp()[:3, 3], START_WORLD, atol=1e-6)


async def test_sideways_into_the_object_protective_stops(arm: SimUR5, world: SimWorld) -> None:
    x, y, _ = START_WORLD
    await move_l(arm, ur_target(world, (x, y, 0.2)))  # fingertips 2.8 cm above the table
    with pytest.raises(ProtectiveStopError, match="object"):
        await move_l(arm, ur_target(world, (0.0, y, 0.2)), speed=0.1)
    state = await arm.state()
    assert state.protective_stopped
    # The sensor side (tool +x = world -x) leads: it presses into the box face until the force
    # passes the limit, and is pushed back along +x.
    leading_x = world.pose_world_tcp()[0, 3] - max(
        box.pose_tcp_box[0, 3] + box.half_extents_m[0]
        for box in world.tool.rigid_boxes(world.gripper_width_m)
        if box.name != "gripper_body"  # passes above the box
    )
    stop_depth_m = (
        world.sim_config.protective_stop_force_n / world.sim_config.contact_stiffness_n_per_m
    )
    assert stop_depth_m - 0.1 * PERIOD_S - 1e-9 < 0.05 - leading_x <= stop_depth_m + 1e-9
    step_n = world.sim_config.contact_stiffness_n_per_m * 0.1 * PERIOD_S
    assert state.tcp_wrench_base[0] > world.sim_config.protective_stop_force_n - step_n - 1e-6


async def test_a_light_press_is_felt_as_tcp_force_and_released(
    arm: SimUR5, world: SimWorld
) -> None:
    """A rigid part pressed 2 mm into the object, slowly: the arm reports the elastic force
    (stiffness x depth, pushing the tool out) and no protective stop; backing out releases it."""
    x, y, _ = START_WORLD
    await move_l(arm, ur_target(world, (x, y, 0.2)))
    assert not np.any((await arm.state()).tcp_wrench_base)
    leading_x = x - max(
        box.pose_tcp_box[0, 3] + box.half_extents_m[0]
        for box in world.tool.rigid_boxes(world.gripper_width_m)
        if box.name != "gripper_body"
    )
    press_m = 0.002
    await move_l(arm, ur_target(world, (x - (leading_x - 0.05) - press_m, y, 0.2)), speed=0.02)
    state = await arm.state()
    assert not state.protective_stopped
    stiffness = world.sim_config.contact_stiffness_n_per_m
    np.testing.assert_allclose(state.tcp_wrench_base[:3], [stiffness * press_m, 0, 0], atol=0.5)
    assert arm.rigid_contacts and arm.rigid_contacts[-1].obstacle == "object"
    await move_l(arm, ur_target(world, (x, y, 0.2)), speed=0.02)
    assert not np.any((await arm.state()).tcp_wrench_base)


async def test_cancelling_the_move_stops_the_arm(arm: SimUR5, world: SimWorld) -> None:
    start = (await arm.state()).pose_base_tcp
    target = ur_target(world, (0.25, 0.0, 0.18))
    task = asyncio.create_task(move_l(arm, target))
    await sim_time_passes(world, 0.3)
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    state = await arm.state()
    assert not state.is_moving
    assert point_segment_distance(state.pose_base_tcp[:3], start[:3], target[:3]) < 1e-9
    assert 0.01 < np.linalg.norm(state.pose_base_tcp[:3] - start[:3]) < 0.11
    for _ in range(5):  # nothing moves on after the cancel
        await asyncio.sleep(0)
    np.testing.assert_array_equal((await arm.state()).pose_base_tcp, state.pose_base_tcp)


async def test_stop_from_another_task_ends_the_move_early(arm: SimUR5, world: SimWorld) -> None:
    target = ur_target(world, (0.25, 0.0, 0.18))
    task = asyncio.create_task(move_l(arm, target))
    start_s = world.clock.now_s
    await sim_time_passes(world, 0.3)
    stop_s = world.clock.now_s
    await arm.stop()
    await task  # returns normally
    state = await arm.state()
    assert not state.is_moving
    assert pose_error(state.pose_base_tcp, target)[0] > 0.01
    assert world.clock.now_s - start_s >= 0.3
    assert world.clock.now_s - stop_s <= PERIOD_S + 1e-9  # the step under way, no more
    await move_l(arm, target)  # a later move is not affected by the old stop
    assert pose_error((await arm.state()).pose_base_tcp, target)[0] < 1e-6


async def test_move_joints_synchronised(arm: SimUR5, world: SimWorld) -> None:
    start = world.joints_rad.copy()
    target = start + np.array([0.3, -0.2, 0.25, 0.1, -0.4, 0.8])
    task = asyncio.create_task(
        arm.move_joints(target, speed_rad_s=1.0, acceleration_rad_s2=2.0, timeout_s=10.0)
    )
    start_s = world.clock.now_s
    states = await record_while(task, arm)
    await task
    np.testing.assert_allclose(world.joints_rad, target, atol=1e-12)
    # Every joint covers the same fraction of its way at every instant: they finish together.
    fractions = (np.array([s.joints_rad for s in states]) - start) / (target - start)
    np.testing.assert_allclose(fractions, fractions[:, :1].repeat(6, axis=1), atol=1e-9)
    # The largest joint (0.8 rad) sets the time.
    expected_s = trapezoid_time(0.8, 1.0, 2.0)
    assert expected_s - 1e-9 <= world.clock.now_s - start_s <= expected_s + PERIOD_S
    np.testing.assert_allclose(world.pose_base_flange, forward_kinematics(target), atol=1e-12)


async def test_move_joints_rejects_bad_targets(arm: SimUR5) -> None:
    for target, speed in [(np.full(6, 7.0), 1.0), (np.zeros(5), 1.0), (np.zeros(6), 4.0)]:
        with pytest.raises(MotionRejectedError):
            await arm.move_joints(target, speed_rad_s=speed, acceleration_rad_s2=1.0, timeout_s=9)


async def test_timeout_stops_the_arm(arm: SimUR5, world: SimWorld) -> None:
    start_s = world.clock.now_s
    with pytest.raises(DeviceTimeoutError):
        await arm.move_linear(
            ur_target(world, (0.25, 0.0, 0.18)), speed_m_s=0.1, acceleration_m_s2=1.0, timeout_s=0.5
        )
    assert world.clock.now_s - start_s <= 0.5
    state = await arm.state()
    assert (
        not state.is_moving
        and pose_error(state.pose_base_tcp, ur_target(world, START_WORLD))[0] > 0.01
    )


async def test_second_move_while_moving_is_busy(arm: SimUR5, world: SimWorld) -> None:
    target = ur_target(world, (0.25, 0.0, 0.2))
    task = asyncio.create_task(move_l(arm, target))
    await asyncio.sleep(0)
    assert (await arm.state()).is_moving
    with pytest.raises(MotionRejectedError, match="busy"):
        await move_l(arm, ur_target(world, START_WORLD))
    with pytest.raises(MotionRejectedError, match="busy"):
        await arm.move_joints(
            FACING_OBJECT_JOINTS, speed_rad_s=1.0, acceleration_rad_s2=1.0, timeout_s=10.0
        )
    await task
    assert pose_error((await arm.state()).pose_base_tcp, target)[0] < 1e-6


async def test_not_connected_and_close(world: SimWorld) -> None:
    arm = SimUR5(world, ArmConfig())
    assert not arm.is_connected
    target = np.array([0.1, 0.4, 0.3, 0.0, np.pi, 0.0])
    calls = [
        arm.state(),
        arm.move_linear(target, speed_m_s=0.1, acceleration_m_s2=1.0, timeout_s=5.0),
        arm.move_joints(np.zeros(6), speed_rad_s=1.0, acceleration_rad_s2=1.0, timeout_s=5.0),
        arm.recover_protective_stop(),
    ]
    for call in calls:
        with pytest.raises(DeviceNotConnectedError):
            await call
    await arm.stop()  # always allowed
    await arm.close()
    await arm.connect()
    assert arm.is_connected
    await arm.close()
    await arm.close()
    with pytest.raises(DeviceNotConnectedError):
        await arm.state()


async def test_close_during_a_move(arm: SimUR5, world: SimWorld) -> None:
    task = asyncio.create_task(move_l(arm, ur_target(world, (0.25, 0.0, 0.18))))
    await asyncio.sleep(0)
    await arm.close()
    with pytest.raises(DeviceNotConnectedError):
        await task
