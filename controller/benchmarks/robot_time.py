"""The robot time of a bench exploration's touches, from the session's own motion planner.

The bench touches without an arm (``sim_touch``). To weigh and compare policies by robot time,
a run keeps a planned arm: it starts at home, each touch is planned from where the previous one
left it (its approach start, after the retract) with the shape estimate as the obstacle, as a
session plans it, and takes ``MotionPlanner.touch_seconds``. A target the planner refuses is
not allowed, as in a session. The bench has no camera-measured bound of the object: only the
estimate is kept clear of.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from controller.config import Config
from controller.motion.planner import MotionPlanner, TouchPlan
from controller.motion.poses import home_pose_world_tcp
from controller.motion.safety import Obstacles, SafetyViolation
from controller.perception.protocol import ShapeEstimate, TouchTarget
from drivers.tool import ToolModel

FloatArray = NDArray[np.float64]


class PlannedArm:
    """Where a bench run's arm would be, and what each touch would cost it (module docstring).
    Plans are cached for the current step: the policy's checks, its timing and the touch made
    then share one plan per target."""

    def __init__(self, config: Config, tool: ToolModel, pose_world_base: FloatArray) -> None:
        self.planner = MotionPlanner.for_config(config, tool, pose_world_base)
        self.pose_world_tcp = home_pose_world_tcp(config.robot.arm)
        self.joints_rad = np.asarray(config.robot.arm.home_joints_rad, dtype=float)
        self._came_from: list[FloatArray] = []
        self._obstacles = Obstacles.none()
        self._plans: dict[bytes, TouchPlan | None] = {}

    def set_estimate(self, estimate: ShapeEstimate) -> None:
        """The shape the next touch's motions keep clear of."""
        self._obstacles = Obstacles.of_estimate(estimate)
        self._plans.clear()

    def plan(self, target: TouchTarget) -> TouchPlan | None:
        """The touch planned from the arm's pose, or None when the planner refuses it."""
        key = np.concatenate([target.target_world, target.direction_world]).tobytes()
        if key not in self._plans:
            try:
                self._plans[key] = self.planner.plan_touch(
                    self.pose_world_tcp,
                    self.joints_rad,
                    target.target_world,
                    target.direction_world,
                    self._obstacles,
                    came_from=self._came_from,
                )
            except SafetyViolation:
                self._plans[key] = None
        return self._plans[key]

    def allowed(self, target: TouchTarget) -> bool:
        return self.plan(target) is not None

    def seconds(self, target: TouchTarget) -> float | None:
        """The touch's robot time (``MotionPlanner.touch_seconds``), None when refused."""
        plan = self.plan(target)
        if plan is None:
            return None
        return self.planner.touch_seconds(plan, self.pose_world_tcp, self.joints_rad)

    def touch(self, target: TouchTarget) -> float | None:
        """Make the touch: its robot time; the arm is then at its approach start (None and
        the arm stays where it is when the planner refuses it)."""
        plan, seconds = self.plan(target), self.seconds(target)
        if plan is None:
            return None
        came_from = [self.pose_world_tcp, *(move.pose_world_tcp for move in plan.transit)]
        if plan.transit:
            self._came_from = came_from[:-1]
            self.joints_rad = plan.transit[-1].joints_rad
        self.pose_world_tcp = plan.touch.pose_world_tcp_start
        self._plans.clear()
        return seconds
