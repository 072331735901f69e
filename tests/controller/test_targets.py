"""Targets follow what was measured: onto the measured surface, forward out of space seen free,
never along a path that cannot meet the object, never a near repeat of a miss."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from controller.config import Config
from controller.motion.poses import (
    TOUCH_ROLLS_RAD,
    pad_pose_facing,
    rolls_preferring,
    tcp_pose_for_pad,
)
from controller.perception.protocol import TouchMeasurement, TouchOutcome, TouchTarget
from controller.targets import (
    onto_measured,
    pad_paths_meet,
    repeat_reason,
    rolls_avoiding_rim_stops,
    window_leading_roll,
)
from drivers.base import TactileFrame
from drivers.tool import ToolModel
from models.object_bound import ObjectBound

PAD_PATH_M = (0.06, 0.015)
FROM_MINUS_X = np.array([1.0, 0.0, 0.0])


def block(x_from: float, x_to: float) -> ObjectBound:
    """A bound that is a block between two x (world), 8 cm wide and tall, with its measured
    surface on the face at ``x_from``."""
    grid = ObjectBound.cube((0.0, 0.0, 0.0))
    centres = grid.voxel_centres_world()
    inside = (
        (centres[..., 0] >= x_from)
        & (centres[..., 0] <= x_to)
        & (np.abs(centres[..., 1]) <= 0.04)
        & (centres[..., 2] <= 0.08)
    )
    y, z = np.meshgrid(np.arange(-0.04, 0.04, 0.002), np.arange(0.0, 0.08, 0.002))
    face = np.column_stack([np.full(y.size, x_from), y.ravel(), z.ravel()])
    return ObjectBound(grid, inside, np.zeros_like(inside), face)


def target_at(x: float) -> TouchTarget:
    return TouchTarget(np.array([x, 0.0, 0.04]), FROM_MINUS_X)


def test_a_target_behind_the_measured_surface_moves_back_onto_it() -> None:
    moved = onto_measured(target_at(0.0), block(-0.03, 0.03), PAD_PATH_M)
    assert moved is not None
    np.testing.assert_allclose(moved.target_world, [-0.03, 0.0, 0.04], atol=1e-3)


def test_a_target_in_space_seen_free_moves_forward_to_the_bound() -> None:
    """The estimate put the surface 1 cm in front of where the object may begin (within the
    fingers' reach: the pad would still get there)."""
    moved = onto_measured(target_at(-0.04), block(-0.03, 0.03), PAD_PATH_M)
    assert moved is not None
    assert -0.035 <= moved.target_world[0] <= -0.03


def test_a_target_whose_path_cannot_meet_the_object_is_a_sure_miss() -> None:
    bound = block(-0.03, 0.03)
    far = TouchTarget(np.array([-0.12, 0.0, 0.04]), FROM_MINUS_X)
    assert onto_measured(far, bound, PAD_PATH_M) is None
    targets = np.array([[-0.12, 0.0, 0.04], [-0.02, 0.0, 0.04]])
    assert pad_paths_meet(bound, targets, FROM_MINUS_X, PAD_PATH_M).tolist() == [False, True]


def test_near_repeats_of_a_miss_and_of_refused_targets_are_named() -> None:
    frame = TactileFrame(np.zeros((2, 2, 3), np.uint8), 0.0)
    miss = TouchMeasurement(target_at(-0.03), False, frame, frame, np.eye(4), np.zeros(3), 0.0)
    outcomes = [TouchOutcome(miss, np.zeros((0, 3)), None, None)]
    deeper = TouchTarget(np.array([-0.01, 0.005, 0.04]), FROM_MINUS_X)
    assert repeat_reason(deeper, [], outcomes) == "a near repeat of a touch that met nothing"
    from_above = TouchTarget(np.array([-0.01, 0.005, 0.04]), np.array([0.0, 0.0, -1.0]))
    assert repeat_reason(from_above, [], outcomes) is None
    refused = [np.array([-0.012, 0.0, 0.04])]
    assert repeat_reason(from_above, refused, []) == "near a target whose motions were refused"


def _side_target() -> TouchTarget:
    return TouchTarget(np.array([0.0, -0.04, 0.06]), np.array([0.0, 1.0, 0.0]))


def _points_in_the_housing_at_roll(roll_rad: float, tool: ToolModel, width: float) -> np.ndarray:
    """A ridge where the GelSight housing's lower end is when the window, rolled so, presses
    5 mm past the target: what an estimate with an edge beside the target puts there."""
    target = _side_target()
    pad = pad_pose_facing(target.target_world, -target.direction_world, -0.005, roll_rad)
    (housing,) = [b for b in tool.rigid_boxes(width) if b.name == "gelsight_housing"]
    pose = tcp_pose_for_pad(pad, tool, width) @ housing.pose_tcp_box
    local = np.random.default_rng(0).uniform(-1, 1, (200, 3)) * housing.half_extents_m * 0.9
    local[:, 2] = -np.abs(local[:, 2])  # its lower end (toward the finger tip: -z of the box)
    return (pose[:3, :3] @ local.T).T + pose[:3, 3]


def test_the_roll_keeps_the_housing_off_what_the_estimate_puts_beside_the_target() -> None:
    config = Config()
    tool = ToolModel(config.gripper, config.sensor)
    width = config.motion.touch_width_m
    target = _side_target()
    # Nothing near the target: the planner's first roll (best for the wrist).
    assert window_leading_roll(target, np.zeros((0, 3)), tool, width) == TOUCH_ROLLS_RAD[0]
    flat = np.array([[x, -0.04 + 0.0005, z] for x in np.linspace(-0.04, 0.04, 41)
                     for z in np.linspace(0.02, 0.1, 41)])  # fmt: skip
    assert window_leading_roll(target, flat, tool, width) == TOUCH_ROLLS_RAD[0]
    # A ridge where the housing would be at roll 0: another roll, at which fewer of its points
    # are inside the housing and the sensor-side finger.
    ridge = _points_in_the_housing_at_roll(0.0, tool, width)
    roll = window_leading_roll(target, np.vstack([flat, ridge]), tool, width)
    assert roll != 0.0
    assert rolls_preferring(roll)[0] == roll
    assert sorted(rolls_preferring(roll)) == sorted(TOUCH_ROLLS_RAD)


def test_a_touch_that_stopped_on_the_rim_is_not_repeated_at_its_roll() -> None:
    """A contact without an imprint (a rigid part met the object before the gel): a target
    along nearly the same line is tried at another roll, one elsewhere at any."""
    frame = TactileFrame(np.zeros((2, 2, 3), np.uint8), 0.0)
    stopped = _side_target()
    roll = TOUCH_ROLLS_RAD[3]
    pad = pad_pose_facing(stopped.target_world, -stopped.direction_world, 0.002, roll)
    rim = TouchMeasurement(stopped, True, frame, frame, pad, np.zeros(3), 4.0)
    outcomes = [TouchOutcome(rim, np.zeros((0, 3)), None, None)]
    nearby = stopped.target_world + np.array([0.005, 0.0, 0.003])
    again = TouchTarget(nearby, stopped.direction_world)
    left = rolls_avoiding_rim_stops(again, outcomes)
    assert roll not in left and sorted((*left, roll)) == sorted(TOUCH_ROLLS_RAD)
    elsewhere = TouchTarget(np.array([0.0, 0.04, 0.06]), np.array([0.0, -1.0, 0.0]))
    assert rolls_avoiding_rim_stops(elsewhere, outcomes) == TOUCH_ROLLS_RAD
    # With an imprint the roll worked: nothing to avoid.
    imprint = [TouchOutcome(rim, np.ones((5, 3)), None, None)]
    assert rolls_avoiding_rim_stops(again, imprint) == TOUCH_ROLLS_RAD
    # Every roll failed there: all are left (the choice falls back to the estimate's).
    every = [
        TouchOutcome(
            replace(rim, pose_world_pad=pad_pose_facing(
                stopped.target_world, -stopped.direction_world, 0.002, r)),
            np.zeros((0, 3)), None, None,
        )
        for r in TOUCH_ROLLS_RAD
    ]  # fmt: skip
    assert rolls_avoiding_rim_stops(again, every) == TOUCH_ROLLS_RAD
