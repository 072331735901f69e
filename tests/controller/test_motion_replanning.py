"""Singularities are planned around, not faulted on: a touch rolls the tool about its approach
line, and a transit or retract line refused only for its joint rates becomes a checked joint
move (moveJ) that the simulated arm runs."""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np
import pytest
import trimesh

from controller.config import Config, LimitsConfig
from controller.motion.executor import MotionExecutor
from controller.motion.lines import (
    TOOL_REACH_M,
    SingularityViolation,
    duration_s,
    tool_reach_along,
)
from controller.motion.planner import APPROACH_EXEMPT_PARTS, APPROACH_NEAR_PARTS, MotionPlanner
from controller.motion.poses import TOUCH_ROLLS_RAD, at_pose, home_pose_world_tcp
from controller.motion.safety import (
    Obstacles,
    SafetyViolation,
    check_clearance,
    check_reachable,
    check_workspace,
)
from controller.session_times import SessionTimes
from drivers.config import ArmConfig, GripperConfig, SensorConfig, SimConfig
from drivers.factory import Devices
from drivers.sim.arm import SimUR5
from drivers.sim.world import SimWorld
from drivers.tool import ToolModel
from drivers.ur5.kinematics import forward_kinematics
from models.geometry import (
    frame_from_z_axis,
    make_transform,
    rotation_angle_between,
    ur_pose_to_matrix,
)

CONFIG = Config()
LIMITS = CONFIG.limits
TOOL = ToolModel(GripperConfig(), SensorConfig())
POSE_WORLD_BASE = ur_pose_to_matrix(ArmConfig().pose_world_base)
HOME = np.asarray(ArmConfig().home_joints_rad)
WIDTH = CONFIG.motion.touch_width_m
DOWN = make_transform(np.diag([1.0, -1.0, -1.0]))  # tool z pointing down
# The sim arm refuses any control step faster than the controller's joint speed limit.
STRICT_ARM = ArmConfig(max_joint_speed_rad_s=LIMITS.max_joint_speed_rad_s)


def planner(limits: LimitsConfig = LIMITS) -> MotionPlanner:
    return MotionPlanner(
        tool=TOOL,
        limits=limits,
        motion=CONFIG.motion,
        pose_world_base=POSE_WORLD_BASE,
        stroke_m=GripperConfig().stroke_m,
    )


def tool_down_at(x: float, y: float, z: float) -> np.ndarray:
    pose = DOWN.copy()
    pose[:3, 3] = (x, y, z)
    return pose


def flange(joints: np.ndarray) -> np.ndarray:
    return POSE_WORLD_BASE @ forward_kinematics(joints)


def joint_path(start: np.ndarray, end: np.ndarray, steps: int = 400) -> list[np.ndarray]:
    """Flange poses along a joint move, as moveJ moves (linear in the joints)."""
    return [flange(start + f * (end - start)) for f in np.linspace(0.0, 1.0, steps + 1)]


async def sim_arm_at(
    joints: np.ndarray, mesh: trimesh.Trimesh, arm_config: ArmConfig = STRICT_ARM
) -> tuple[SimWorld, SimUR5]:
    """A connected sim arm at these joints, the fingers open to the touch width."""
    world = SimWorld(
        mesh, sim=SimConfig(), arm=arm_config, gripper=GripperConfig(), sensor=SensorConfig()
    )
    world.joints_rad = np.asarray(joints, dtype=float)
    world.gripper_width_m = WIDTH
    arm = SimUR5(world, arm_config)
    await arm.connect()
    return world, arm


class MotionLog:
    """The recorder's motions.jsonl, in memory."""

    def __init__(self) -> None:
        self.motions: list[dict[str, Any]] = []

    def log_motion(self, record: dict[str, Any]) -> None:
        self.motions.append(record)


def executor_for(
    arm: SimUR5, world: SimWorld, plan: MotionPlanner, log: MotionLog
) -> MotionExecutor:
    """The session's executor on the sim arm alone (the moves use no other device)."""
    devices: Any = Devices(camera=None, tactile=None, arm=arm, gripper=None, world=world)
    recorder: Any = log
    return MotionExecutor(
        devices=devices, config=CONFIG, planner=plan, times=SessionTimes(), recorder=recorder
    )


async def test_a_retract_refused_near_a_singularity_is_a_joint_move_the_arm_runs() -> None:
    """The arm at the stand-off of a touch on the far side, in the configuration (the joints
    nearest home) from which the approach start is out of reach without turning the wrist
    over: the elbow would have to stretch past straight on the way, so the straight retract
    passes a singularity. The retract is re-planned as a joint move whose every pose is within
    the limits, never nearer the touched surface, and which the arm runs back to the approach
    start without touching the object."""
    plan = planner()
    target, direction = np.array([-0.12, 0.11, 0.06]), np.array([-0.6, -0.7, -0.4])
    touch = plan.touch_geometry(target, direction, np.radians(60.0))
    standoff = touch.pose_world_tcp_standoff
    joints = check_reachable(standoff, POSE_WORLD_BASE, HOME)
    with pytest.raises(SingularityViolation):
        plan.line(
            standoff,
            touch.pose_world_tcp_start,
            joints,
            Obstacles.none(),
            speed_m_s=LIMITS.max_tcp_speed_m_s,
            label="retract",
            exempt_parts=APPROACH_EXEMPT_PARTS,
            near_parts=APPROACH_NEAR_PARTS,
        )

    retract = plan.plan_retract(touch, standoff, joints)

    assert retract.kind == "joints"
    assert 0.0 < retract.speed_m_s <= LIMITS.max_joint_speed_rad_s  # rad/s for a joint move
    np.testing.assert_allclose(flange(retract.joints_rad), touch.pose_world_tcp_start, atol=1e-9)
    front = tool_reach_along(standoff, WIDTH, TOOL, touch.direction_world)
    for pose in joint_path(joints, retract.joints_rad):
        check_workspace(pose, LIMITS)
        check_clearance(pose, WIDTH, TOOL, Obstacles.none(), LIMITS)
        assert tool_reach_along(pose, WIDTH, TOOL, touch.direction_world) <= front + 1e-9
    # The object: a block whose face is the touched surface, the pad 5 mm from it.
    block = trimesh.creation.box((0.2, 0.2, 0.2))
    normal = -touch.direction_world
    block.apply_transform(make_transform(frame_from_z_axis(normal), target - 0.1 * normal))
    world, arm = await sim_arm_at(joints, block)
    log = MotionLog()
    await executor_for(arm, world, plan, log).move(retract)
    assert not (await arm.state()).protective_stopped
    assert at_pose(world.pose_world_tcp(), touch.pose_world_tcp_start)
    (record,) = log.motions
    assert record["label"] == "retract" and record["kind"] == "joints"
    assert record["speed_rad_s"] == retract.speed_m_s
    np.testing.assert_allclose(record["end_joints_rad"], retract.joints_rad, atol=1e-6)


def test_a_touch_rolls_the_tool_when_the_unrolled_approach_passes_a_singularity() -> None:
    """A touch on the far side near the arm's reach: unrolled, the approach stretches the
    elbow straight (a singularity); rolled 30 degrees about the approach line, the flange is
    nearer the base and the touch is planned, the pad still facing along the approach."""
    plan = planner()
    home = home_pose_world_tcp(ArmConfig())
    target, direction = (-0.15, 0.2, 0.1), (0.0, 1.0, -2.0)
    with pytest.raises(SingularityViolation, match=r"approach.*singularity"):
        plan.plan_touch(home, HOME, target, direction, Obstacles.none(), rolls_rad=(0.0,))

    touch_plan = plan.plan_touch(home, HOME, target, direction, Obstacles.none())

    assert touch_plan.roll_rad == pytest.approx(np.radians(30.0))
    assert touch_plan.touch.roll_rad == touch_plan.roll_rad
    approach_direction = np.asarray(direction) / np.linalg.norm(direction)
    touch = touch_plan.touch
    for pose in (touch.pose_world_tcp_start, touch.pose_world_tcp_standoff):
        pad = pose @ TOOL.pose_tcp_pad(WIDTH)
        np.testing.assert_allclose(pad[:3, 2], approach_direction, atol=1e-12)
    unrolled = plan.touch_geometry(target, direction)
    np.testing.assert_allclose(touch.pad_start_world, unrolled.pad_start_world, atol=1e-12)
    assert rotation_angle_between(
        touch.pose_world_tcp_start[:3, :3], unrolled.pose_world_tcp_start[:3, :3]
    ) == pytest.approx(np.radians(30.0))
    np.testing.assert_allclose(
        touch_plan.transit[-1].pose_world_tcp, touch.pose_world_tcp_start, atol=1e-12
    )
    np.testing.assert_allclose(
        touch_plan.approach.pose_world_tcp, touch.pose_world_tcp_standoff, atol=1e-12
    )
    # The select step's cheap check agrees.
    assert plan.check_touch(target, direction, HOME, Obstacles.none()) == touch_plan.roll_rad
    # Refused at every roll: the preferred (unrolled) refusal is given.
    blocked = Obstacles(np.array([touch.target_world - 0.02 * approach_direction]))
    with pytest.raises(SafetyViolation, match=r"^approach: .*refused too\)$"):
        plan.check_touch(target, direction, HOME, blocked)
    assert all(abs(roll) < np.radians(90.0) for roll in TOUCH_ROLLS_RAD)


def test_a_joint_move_is_refused_when_a_pose_between_its_ends_collides() -> None:
    """Both ends clear; between them the wrist swings the fingers down through the table, or
    through where the object may be."""
    plan = planner()
    swing = np.array([0.0, 0.0, 0.0, 0.0, 1.0, 0.0])  # wrist 2: the tool points down halfway

    low = check_reachable(tool_down_at(0.0, -0.1, 0.17), POSE_WORLD_BASE, HOME)
    for end in (low - swing, low + swing):
        check_clearance(flange(end), WIDTH, TOOL, Obstacles.none(), LIMITS)
    with pytest.raises(SafetyViolation, match=r"joint move.*above the table"):
        plan.joint_move(low - swing, low + swing, Obstacles.none(), "test")

    high = check_reachable(tool_down_at(0.0, -0.1, 0.35), POSE_WORLD_BASE, HOME)
    below_fingertips = flange(high) @ np.array([0.0, 0.0, TOOL.finger_tip_z_m + 0.005, 1.0])
    obstacle = Obstacles(below_fingertips[None, :3])
    for end in (high - swing, high + swing):
        check_clearance(flange(end), WIDTH, TOOL, obstacle, LIMITS)
    plan.joint_move(high - swing, high + swing, Obstacles.none(), "test")
    with pytest.raises(SafetyViolation, match=r"joint move.*where the object may be"):
        plan.joint_move(high - swing, high + swing, obstacle, "test")


def test_a_joint_move_that_does_not_turn_keeps_a_speed_the_arm_accepts() -> None:
    """A joint move back to where the arm already is (a retreat from a joint move interrupted
    at its start): forward kinematics' rounding makes the tool seem to move while no joint
    turns; the speed must stay positive (the arm refuses 0 rad/s: a fault on mug_p2_7cm)."""
    plan = planner()
    joints = check_reachable(tool_down_at(0.0, -0.1, 0.3), POSE_WORLD_BASE, HOME)
    move = plan.joint_move(joints, joints.copy(), Obstacles.none(), "test")
    assert move.speed_m_s == LIMITS.max_joint_speed_rad_s


@pytest.mark.parametrize("joint_limit_rad_s", [LIMITS.max_joint_speed_rad_s, 0.4])
async def test_joint_move_speeds_keep_the_joint_and_tool_speed_limits(
    joint_limit_rad_s: float,
) -> None:
    """The speed of a joint move (its fastest joint's, rad/s) is within
    ``max_joint_speed_rad_s``, and slow enough that the tool moves within
    ``max_tcp_speed_m_s``; the sim arm, refusing any faster step, runs them."""
    limits = LimitsConfig(max_joint_speed_rad_s=joint_limit_rad_s)
    plan = planner(limits)
    start = check_reachable(tool_down_at(0.0, -0.1, 0.3), POSE_WORLD_BASE, HOME)
    moves = {  # round the base (the tool moves fast), about the tool's axis, everything
        "base": start + np.array([0.6, 0.0, 0.0, 0.0, 0.0, 0.0]),
        "wrist": start + np.array([0.0, 0.0, 0.0, 0.0, 0.0, 2.0]),
        "all": start + np.array([-0.3, 0.2, -0.3, 0.5, 0.4, -1.0]),
    }
    for name, end in moves.items():
        move = plan.joint_move(start, end, Obstacles.none(), name)
        assert move.kind == "joints"
        assert 0.0 < move.speed_m_s <= joint_limit_rad_s
        # At that speed the fastest joint takes `seconds`: the tool's fastest point (flange
        # travel plus the tool's reach turning) keeps the TCP speed limit, and the speed is
        # below the joint limit only as far as that needs.
        seconds = float(np.max(np.abs(end - start))) / move.speed_m_s
        path = joint_path(start, end)
        tool_speed = max(
            np.linalg.norm(after[:3, 3] - before[:3, 3])
            + TOOL_REACH_M * rotation_angle_between(before[:3, :3], after[:3, :3])
            for before, after in itertools.pairwise(path)
        ) / (seconds / (len(path) - 1))
        assert tool_speed <= limits.max_tcp_speed_m_s * 1.01
        if move.speed_m_s < joint_limit_rad_s:
            assert tool_speed >= limits.max_tcp_speed_m_s * 0.95
        elif name == "wrist":
            assert move.speed_m_s == joint_limit_rad_s
    strict = ArmConfig(max_joint_speed_rad_s=joint_limit_rad_s)
    world, arm = await sim_arm_at(start, trimesh.creation.box((0.01, 0.01, 0.01)), strict)
    for name in ("base", "all"):
        move = plan.joint_move(world.joints_rad, moves[name], Obstacles.none(), name)
        await arm.move_joints(
            move.joints_rad, speed_rad_s=move.speed_m_s, acceleration_rad_s2=1.0, timeout_s=60
        )
        np.testing.assert_allclose(world.joints_rad, moves[name], atol=1e-9)


async def test_a_transit_line_near_the_wrist_singularity_becomes_a_joint_move() -> None:
    """Between two touches from above, the fingers nearly level along x (the approaches tilt
    2 mrad): the straight line across passes the wrist singularity 2 mrad off, so the transit
    moves the joints instead, and the sim arm runs it to the next approach start."""
    plan = planner()
    direction = (0.002, 0.0, -1.0)
    here = plan.touch_geometry((0.12, 0.0, 0.1), direction)
    there = plan.touch_geometry((0.24, 0.0, 0.1), direction)
    start = here.pose_world_tcp_start
    joints = check_reachable(start, POSE_WORLD_BASE, HOME)
    goal = there.pose_world_tcp_start
    speed = LIMITS.max_tcp_speed_m_s
    with pytest.raises(SingularityViolation):
        plan.line(start, goal, joints, Obstacles.none(), speed_m_s=speed, label="across")

    (across,) = plan.plan_transit(start, joints, there, Obstacles.none())

    assert (across.label, across.kind) == ("across", "joints")
    np.testing.assert_allclose(across.pose_world_tcp, goal)
    world, arm = await sim_arm_at(joints, trimesh.creation.box((0.01, 0.01, 0.01)))
    await executor_for(arm, world, plan, MotionLog()).move(across)
    assert at_pose(world.pose_world_tcp(), goal)
    # Only a singularity: a line an obstacle blocks is refused, not moved around.
    middle = (start[:3, 3] + goal[:3, 3]) / 2
    with pytest.raises(SafetyViolation) as refusal:
        plan.line_or_joints(
            start, goal, joints, Obstacles(middle[None]), speed_m_s=speed, label="across"
        )
    assert "joint move" not in str(refusal.value)
    assert not isinstance(refusal.value, SingularityViolation)


def test_a_retreat_from_an_interrupted_joint_move_reverses_its_joint_path() -> None:
    """Stopped halfway through a joint move, the arm goes back along the same joint path (the
    way it came), not along a straight line it never swept."""
    plan = planner()
    start = check_reachable(tool_down_at(0.0, -0.1, 0.3), POSE_WORLD_BASE, HOME)
    halfway = start + np.array([0.3, 0.0, 0.0, 0.0, 0.5, 0.0])
    (retreat,) = plan.plan_retreat(
        flange(halfway), halfway, back_to_world_tcp=flange(start), back_to_joints_rad=start
    )
    assert (retreat.label, retreat.kind) == ("retreat", "joints")
    np.testing.assert_allclose(retreat.joints_rad, start)


async def test_a_joint_move_starts_only_from_the_joints_it_was_checked_from() -> None:
    """Elsewhere, moveJ would sweep a path nobody checked: the executor refuses to move."""
    plan = planner()
    start = check_reachable(tool_down_at(0.0, -0.1, 0.3), POSE_WORLD_BASE, HOME)
    move = plan.joint_move(
        start, start + np.array([0.3, 0.0, 0.0, 0.0, 0.0, 0.5]), Obstacles.none(), "test"
    )
    elsewhere = start + np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.05])
    world, arm = await sim_arm_at(elsewhere, trimesh.creation.box((0.01, 0.01, 0.01)))
    log = MotionLog()
    with pytest.raises(SafetyViolation, match="checked from"):
        await executor_for(arm, world, plan, log).move(move)
    np.testing.assert_allclose(world.joints_rad, elsewhere)
    assert log.motions == []


def test_a_line_shorter_than_a_millimetre_is_timed_by_its_distance() -> None:
    """A retreat from one 0.5 mm approach step back to where the steps began: a short straight
    line, not a "singularity" (timed by a turn it does not make, its speed would be 0)."""
    plan = planner()
    touch = plan.touch_geometry((0.02, -0.06, 0.1), (-0.17, 0.98, 0.0))
    start = touch.pose_world_tcp_start
    stepped = start.copy()
    stepped[:3, 3] += 0.0005 * touch.direction_world
    joints = check_reachable(stepped, POSE_WORLD_BASE, HOME)
    back = plan.line(
        stepped, start, joints, Obstacles.none(), speed_m_s=LIMITS.max_tcp_speed_m_s, label="back"
    )
    assert back.speed_m_s > 0.01


def test_a_transit_line_the_joint_rates_slow_to_a_crawl_becomes_the_faster_joint_move() -> None:
    """Two touches from above, tilted 10 mrad: the line passes the wrist singularity
    10 mrad off, allowed, but its joint rates hold the TCP to ~4 mm/s (12 cm in ~29 s). The
    transit moves the joints instead (~0.5 s), checked as every joint move. A line the joint
    rates do not slow (between two side touches 4 cm apart) stays a line."""
    plan = planner()
    speed = LIMITS.max_tcp_speed_m_s
    for direction, kind in (((0.01, 0.0, -1.0), "joints"), ((0.0, 1.0, 0.0), "line")):
        start = plan.touch_geometry((0.12, 0.0, 0.1), direction).pose_world_tcp_start
        goal = plan.touch_geometry((0.12, 0.0, 0.14), direction).pose_world_tcp_start
        if kind == "joints":
            goal = plan.touch_geometry((0.24, 0.0, 0.1), direction).pose_world_tcp_start
        joints = check_reachable(start, POSE_WORLD_BASE, HOME)
        line = plan.line(start, goal, joints, Obstacles.none(), speed_m_s=speed, label="across")
        move = plan.line_or_joints(
            start, goal, joints, Obstacles.none(), speed_m_s=speed, label="across"
        )
        assert move.kind == kind
        np.testing.assert_allclose(move.pose_world_tcp, goal)
        if kind == "joints":
            assert line.speed_m_s < 0.005
            assert duration_s(start, joints, move) < duration_s(start, joints, line) / 10
        else:
            assert move.speed_m_s == line.speed_m_s == speed
