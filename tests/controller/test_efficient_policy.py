"""The efficient policy (most expected uncertainty reduction per robot-second) and the robot
time it weighs: the planner's seconds for a touch, and the bench's planned arm."""

from __future__ import annotations

import numpy as np
import pytest

from controller.benchmarks.explore_summary import robot_seconds_curve
from controller.benchmarks.robot_time import PlannedArm
from controller.config import Config
from controller.motion.lines import duration_s
from controller.motion.planner import MotionPlanner
from controller.motion.poses import home_pose_world_tcp
from controller.motion.safety import Obstacles
from controller.perception.learned import (
    EFFICIENT_CANDIDATES,
    REPEAT_ANGLE_DEG,
    REPEAT_RADIUS_M,
    LearnedPerception,
)
from controller.perception.protocol import (
    ShapeEstimate,
    TouchMeasurement,
    TouchOutcome,
    TouchTarget,
)
from controller.request import ExploreRequest
from drivers.base import TactileFrame
from drivers.tool import ToolModel
from models.geometry import ur_pose_to_matrix

SIDE_TARGET = TouchTarget(np.array([0.0, -0.04, 0.05]), np.array([0.0, 1.0, 0.0]))
FAR_SIDE_TARGET = TouchTarget(np.array([0.0, 0.04, 0.05]), np.array([0.0, -1.0, 0.0]))
UNDER_THE_TABLE = TouchTarget(np.array([0.0, -0.04, -0.02]), np.array([0.0, 1.0, 0.0]))


def planner_and_home(config: Config) -> tuple[MotionPlanner, np.ndarray, np.ndarray]:
    tool = ToolModel(config.gripper, config.sensor)
    base = ur_pose_to_matrix(config.robot.arm.pose_world_base)
    joints = np.asarray(config.robot.arm.home_joints_rad, dtype=float)
    return (
        MotionPlanner.for_config(config, tool, base),
        home_pose_world_tcp(config.robot.arm),
        joints,
    )


def test_a_touchs_seconds_add_up_its_planned_motions_and_the_press() -> None:
    config = Config()
    planner, pose, joints = planner_and_home(config)
    plan = planner.plan_touch(
        pose, joints, SIDE_TARGET.target_world, SIDE_TARGET.direction_world, Obstacles.none()
    )
    moves, at, at_joints = 0.0, pose, joints
    for move in (*plan.transit, plan.approach):
        moves += duration_s(at, at_joints, move)
        at, at_joints = move.pose_world_tcp, move.joints_rad
    motion = config.motion
    press = 2 * motion.standoff_m / (motion.finger_speed_m_s / 2)
    retract = np.linalg.norm(plan.touch.pad_start_world - plan.touch.target_world)
    expected = moves + press + retract / config.limits.max_tcp_speed_m_s
    assert planner.touch_seconds(plan, pose, joints) == pytest.approx(expected)
    assert plan.transit and moves > 0
    seconds = planner.seconds_to_touch(
        pose, joints, Obstacles.none(), [], SIDE_TARGET.target_world, SIDE_TARGET.direction_world
    )
    assert seconds == pytest.approx(expected)
    # Refused: no time.
    assert (
        planner.seconds_to_touch(
            pose,
            joints,
            Obstacles.none(),
            [],
            UNDER_THE_TABLE.target_world,
            UNDER_THE_TABLE.direction_world,
        )
        is None
    )


def test_the_planned_arm_pays_the_transit_once() -> None:
    """A bench run's arm: after a touch it waits at that touch's approach start, so touching
    there again costs no transit, and the far side of the object costs more."""
    config = Config()
    tool = ToolModel(config.gripper, config.sensor)
    arm = PlannedArm(config, tool, ur_pose_to_matrix(config.robot.arm.pose_world_base))
    grid = config.voxel_grid.grid(tuple(config.cameras.rgbd.pose_world_camera()[:3, 3]))
    empty = ShapeEstimate(grid, np.zeros((grid.resolution,) * 3, np.float32))
    arm.set_estimate(empty)
    first = arm.touch(SIDE_TARGET)
    assert first is not None
    start = arm.planner.touch_geometry(
        SIDE_TARGET.target_world, SIDE_TARGET.direction_world
    ).pose_world_tcp_start
    assert np.allclose(arm.pose_world_tcp, start)
    again, far = arm.seconds(SIDE_TARGET), arm.seconds(FAR_SIDE_TARGET)
    assert again is not None and far is not None
    assert again < first and again < far
    assert not arm.allowed(UNDER_THE_TABLE) and arm.touch(UNDER_THE_TABLE) is None
    assert np.allclose(arm.pose_world_tcp, start)  # a refused touch does not move it


def test_robot_seconds_curve_is_the_running_sum() -> None:
    result = {"chamfer_mm": [5.0, 4.0, 3.0, 3.0], "robot_s": [8.0, 2.0]}
    assert robot_seconds_curve(result) == [0.0, 8.0, 10.0, None]
    assert robot_seconds_curve({"chamfer_mm": [5.0, 4.0], "robot_s": [None]}) == [None, None]


def sphere_with_uncertain_patches(config: Config) -> ShapeEstimate:
    """A 4 cm ball on the table, confident everywhere but two side patches: a very uncertain
    one facing -y and a less uncertain one facing +y."""
    grid = config.voxel_grid.grid(tuple(config.cameras.rgbd.pose_world_camera()[:3, 3]))
    centres = grid.voxel_centres_world()
    centre = np.array([0.0, 0.0, 0.05])
    distance = np.linalg.norm(centres - centre, axis=-1)
    probabilities = np.where(distance <= 0.04, 0.95, 0.02).astype(np.float32)
    shell = np.abs(distance - 0.04) < 0.012
    height = np.abs(centres[..., 2] - centre[2]) < 0.012
    along_x = np.abs(centres[..., 0]) < 0.012
    probabilities[shell & height & along_x & (centres[..., 1] < 0)] = 0.5
    probabilities[shell & height & along_x & (centres[..., 1] > 0)] = 0.35
    return ShapeEstimate(grid, probabilities)


def perception_for_select(config: Config) -> LearnedPerception:
    """A perception whose ``select`` runs without a GelSight calibration (it reads none)."""
    return LearnedPerception(
        config,
        camera_position_world=config.cameras.rgbd.pose_world_camera()[:3, 3],
        calibration=None,  # type: ignore[arg-type]
    )


def test_the_efficient_policy_trades_uncertainty_for_robot_time() -> None:
    config = Config()
    perception = perception_for_select(config)
    estimate = sphere_with_uncertain_patches(config)

    def select(policy: str, seconds: object) -> TouchTarget:
        request = ExploreRequest(policy=policy)  # type: ignore[arg-type]
        chosen = perception.select(estimate, request, [], lambda t: True, robot_seconds=seconds)
        assert chosen is not None
        return chosen

    def cost(target: TouchTarget) -> float:
        """The most uncertain window is far away (the first timed), every other near."""
        return 100.0 if np.allclose(target.target_world, timed[0].target_world) else 10.0

    def far_first(target: TouchTarget) -> float:
        timed.append(target)
        return cost(target)

    timed: list[TouchTarget] = []
    active = select("active", far_first)
    assert not timed  # the paper's policy times nothing
    efficient = select("efficient", far_first)
    assert len(timed) == EFFICIENT_CANDIDATES
    assert np.allclose(timed[0].target_world, active.target_world)
    rates = [t.uncertainty / cost(t) for t in timed]
    assert efficient is timed[int(np.argmax(rates))]
    assert efficient is not timed[0]  # the far window is not worth its time
    # Time the same everywhere: the most uncertain window, as the paper's policy.
    same = select("efficient", lambda target: 10.0)
    assert np.allclose(same.target_world, active.target_world)

    # A target the planner refuses is never taken.
    def only_the_cheap_one(target: TouchTarget) -> float | None:
        return 1.0 if np.allclose(target.target_world, efficient.target_world) else None

    assert np.allclose(select("efficient", only_the_cheap_one).target_world, efficient.target_world)


def first_and_second_targets(
    config: Config, estimate: ShapeEstimate, *, imprint: bool
) -> tuple[TouchTarget, TouchTarget]:
    """The active policy's first target, and its second after a touch there stopped by force,
    with an imprint at the target or without one. The estimate is not refined in between."""
    perception = perception_for_select(config)
    request = ExploreRequest(policy="active")
    first = perception.select(estimate, request, [], lambda t: True)
    assert first is not None
    frame = TactileFrame(np.zeros((4, 4, 3), np.uint8), 0.0)
    stop = TouchMeasurement(
        first, True, frame, frame, np.eye(4), first.target_world, config.limits.contact_force_n
    )
    points = first.target_world[None] if imprint else np.zeros((0, 3))
    second = perception.select(
        estimate, request, [TouchOutcome(stop, points, None, None)], lambda t: True
    )
    assert second is not None
    return first, second


@pytest.mark.parametrize("imprint", [False, True])
def test_a_target_beside_a_force_only_stop_is_not_chosen_again(imprint: bool) -> None:
    """The next target avoids the same mistake: after a touch stopped by force without an
    imprint, no target within 15 mm of it from within 30 degrees of its direction is chosen
    (the touch itself swept nothing: the estimate stays as it was). After an imprint there
    the policy may go back nearby."""
    config = Config()
    first, second = first_and_second_targets(
        config, sphere_with_uncertain_patches(config), imprint=imprint
    )
    near = np.linalg.norm(second.target_world - first.target_world) < 0.015
    similar = second.direction_world @ first.direction_world > np.cos(np.radians(30.0))
    assert (near and similar) == imprint


def test_a_touched_patch_is_not_pressed_again_from_a_neighbouring_direction() -> None:
    """One small uncertain patch (16 mm square) on a confident ball; after an imprint there the
    estimate here stays as it was, so the patch stays the least confident window from several
    directions. The policy must not aim within 5 mm of the touch again from within 25 degrees
    (at 10 degrees it took the same patch from the neighbouring direction, 20 degrees off)."""
    config = Config()
    grid = config.voxel_grid.grid(tuple(config.cameras.rgbd.pose_world_camera()[:3, 3]))
    centres = grid.voxel_centres_world()
    distance = np.linalg.norm(centres - np.array([0.0, 0.0, 0.05]), axis=-1)
    probabilities = np.where(distance <= 0.04, 0.95, 0.02).astype(np.float32)
    patch = (
        (np.abs(distance - 0.04) < 0.012)
        & (np.abs(centres[..., 2] - 0.05) < 0.008)
        & (np.abs(centres[..., 0]) < 0.008)
        & (centres[..., 1] < 0)
    )
    probabilities[patch] = 0.5
    first, second = first_and_second_targets(
        config, ShapeEstimate(grid, probabilities), imprint=True
    )
    near = np.linalg.norm(second.target_world - first.target_world) < REPEAT_RADIUS_M
    angle = np.degrees(np.arccos(np.clip(second.direction_world @ first.direction_world, -1, 1)))
    assert not (near and angle < REPEAT_ANGLE_DEG)
