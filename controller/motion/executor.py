"""Drives the arm and the gripper through checked plans for one session.

The session decides what to do; this module does it: straight (or joint) moves to checked
waypoints, the force-watched approach, going home, and making the robot safe after a fault or an
abort. Every arm motion is appended to the session's ``motions.jsonl``.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable
from dataclasses import replace
from functools import partial
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

from controller.config import Config
from controller.motion.planner import MotionPlanner, Waypoint
from controller.motion.poses import at_pose
from controller.motion.safety import Obstacles, SafetyViolation
from controller.recording import SessionRecorder
from controller.session_times import SessionTimes
from drivers.base import ArmState, DeviceError, GripperState
from drivers.factory import Devices
from models.geometry import invert_transform, matrix_to_ur_pose, ur_pose_to_matrix

if TYPE_CHECKING:
    from controller.perception.protocol import TouchTarget

log = logging.getLogger(__name__)

T = TypeVar("T")

MOVE_TIMEOUT_S = 180.0
"""A single straight move that takes longer than this has failed."""
ACCELERATION_M_S2 = 0.5
JOINT_ACCELERATION_RAD_S2 = 1.0
"""Of a joint move (a waypoint of kind "joints")."""
JOINT_START_TOLERANCE_RAD = 0.01
"""A joint move starts only from within this of the joints its path was checked from (well above
the arm's joint readings' noise): from elsewhere, moveJ would sweep a path nobody checked."""
APPROACH_STEP_M = 0.0005
"""Arm travel between force readings on an approach. On a face tilted to the pad, or an edge or
corner meeting the gel, the force grows slowly: the gel must show ``approach_contact_force_n``
before it has given the 1.5 mm that bring the rigid window behind it onto the object."""
APPROACH_FINE_STEP_M = 0.0001
APPROACH_FINE_FORCE_FRACTION = 0.25
"""Once the force reaches this fraction of ``approach_contact_force_n`` the approach goes on in
``APPROACH_FINE_STEP_M`` steps: a corner pressing the gel shows only a fraction of the contact
force one coarse step before the window behind the gel would reach it (docs/controller.md)."""


class HomeError(RuntimeError):
    """The arm cannot go home, or did not arrive there."""


class UnexpectedForceError(RuntimeError):
    """On an approach, the arm felt a force the gel does not explain: a rigid part of the tool
    met the object. The arm has stopped where it felt it."""

    def __init__(self, force_n: float, finger_force_n: float, travelled_m: float) -> None:
        super().__init__(
            f"unexpected force on the approach: the TCP force rose by {force_n:.1f} N with"
            f" {finger_force_n:.1f} N on the gel, {travelled_m * 1e3:.1f} mm along the line"
        )
        self.force_n = force_n
        self.finger_force_n = finger_force_n
        self.travelled_m = travelled_m

    def record(self, target: TouchTarget, backed_out_to_world_tcp: np.ndarray) -> dict[str, Any]:
        """The event as the session summary lists it: the target, the figures, and where the
        arm backed out to (the approach start)."""
        return {
            "target_world": np.round(target.target_world, 4).tolist(),
            "direction_world": np.round(target.direction_world, 4).tolist(),
            "tcp_force_rise_n": round(self.force_n, 2),
            "finger_force_n": round(self.finger_force_n, 2),
            "travelled_m": round(self.travelled_m, 4),
            "backed_out_to_world": np.round(backed_out_to_world_tcp[:3, 3], 4).tolist(),
        }


class MotionExecutor:
    """Moves the session's devices; counts device time as motion (``SessionTimes``)."""

    def __init__(
        self,
        *,
        devices: Devices,
        config: Config,
        planner: MotionPlanner,
        times: SessionTimes,
        recorder: SessionRecorder,
    ) -> None:
        self.devices = devices
        self.config = config
        self.planner = planner
        self.times = times
        self.recorder = recorder
        self.pose_world_base = planner.pose_world_base
        self.move_start_world_tcp: np.ndarray | None = None
        """Where the motion under way (or interrupted) started: a pose the arm reached without
        touching anything. For a touch, the approach start until the retract is back there;
        None between motions."""
        self.move_start_joints_rad: np.ndarray | None = None
        """The joints there when the motion under way (or interrupted) is a joint move: the
        way back is then the same joint path reversed. None otherwise."""

    def pose_world_tcp(self, arm: ArmState) -> np.ndarray:
        """The TCP pose of an arm state in the world frame (4x4)."""
        return self.pose_world_base @ ur_pose_to_matrix(arm.pose_base_tcp)

    async def device(self, call: Awaitable[T]) -> T:
        """Await a device command or query, counting its time as motion."""
        start = time.perf_counter()
        try:
            return await call
        finally:
            self.times.motion_s += time.perf_counter() - start

    @staticmethod
    async def compute(function: Callable[..., Any], *args: Any) -> Any:
        """Run planning (or perception) in a worker thread: the event loop stays responsive."""
        return await asyncio.to_thread(function, *args)

    async def arm_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """The arm's flange pose (world) and joints now."""
        arm = await self.device(self.devices.arm.state())
        return self.pose_world_tcp(arm), arm.joints_rad

    async def move(self, waypoint: Waypoint, *, new_motion: bool = True) -> None:
        """Move to a waypoint; ``new_motion=False`` continues a motion (an approach's steps),
        which a retreat then retraces to its start. A new motion is logged."""
        joint_move = waypoint.kind == "joints"
        if new_motion:
            start_world_tcp, start_joints = await self.arm_pose()
            if joint_move:
                _check_joint_start(waypoint, start_joints)
            self.move_start_world_tcp = start_world_tcp
            self.move_start_joints_rad = start_joints if joint_move else None
            self._log_motion(waypoint.label, start_world_tcp, waypoint, start_joints)
        if joint_move:
            move = self.devices.arm.move_joints(
                waypoint.joints_rad,
                speed_rad_s=waypoint.speed_m_s,  # rad/s for a joint move
                acceleration_rad_s2=JOINT_ACCELERATION_RAD_S2,
                timeout_s=MOVE_TIMEOUT_S,
            )
        else:
            pose_base_tcp = invert_transform(self.pose_world_base) @ waypoint.pose_world_tcp
            move = self.devices.arm.move_linear(
                matrix_to_ur_pose(pose_base_tcp),
                speed_m_s=waypoint.speed_m_s,
                acceleration_m_s2=ACCELERATION_M_S2,
                timeout_s=MOVE_TIMEOUT_S,
            )
        await self.device(move)
        if new_motion:
            self.move_start_world_tcp = None  # arrived: no motion to retreat from
            self.move_start_joints_rad = None

    def _log_motion(
        self,
        label: str,
        start_world_tcp: np.ndarray,
        end: Waypoint,
        start_joints_rad: np.ndarray | None = None,
    ) -> None:
        joint_move = end.kind == "joints"
        record: dict[str, Any] = {
            "label": label,
            "kind": end.kind,
            "start_world_tcp": np.round(start_world_tcp, 6).tolist(),
            "end_world_tcp": np.round(end.pose_world_tcp, 6).tolist(),
            ("speed_rad_s" if joint_move else "speed_m_s"): end.speed_m_s,
            "width_m": self.config.motion.touch_width_m,
            "time": time.time(),
        }
        if joint_move and start_joints_rad is not None:
            # A joint move's path is a straight line in the joints, not the TCP's: replayable.
            record["start_joints_rad"] = np.round(start_joints_rad, 6).tolist()
            record["end_joints_rad"] = np.round(end.joints_rad, 6).tolist()
        self.recorder.log_motion(record)

    async def move_until_contact(self, waypoint: Waypoint) -> bool:
        """The slow approach, watching the finger force: the surface may be nearer than the
        estimate said. The line is driven in ``APPROACH_STEP_M`` moves with a force reading
        after each, and in ``APPROACH_FINE_STEP_M`` moves once the gel feels anything, so the
        arm never travels further than the gel can give between checks. Returns True when
        the pad touched on the way (the arm then stays there). A retreat from anywhere on the
        line goes back to its start.

        It watches the arm's TCP force too: a rise over the reading at the start by more than
        the finger feels plus ``limits.unexpected_force_n`` is a rigid part meeting the object
        (a part of it the estimate and the bound missed). The arm stops there and
        ``UnexpectedForceError`` is raised: the caller backs out (``make_safe``)."""
        start, _ = await self.arm_pose()
        self.move_start_world_tcp = start
        self.move_start_joints_rad = None
        reached = [start]
        try:
            return await self._approach_steps(start, waypoint, reached)
        finally:  # the part of the line the arm drove, whatever ended it
            self._log_motion("approach", start, replace(waypoint, pose_world_tcp=reached[-1]))

    async def _approach_steps(
        self, start: np.ndarray, waypoint: Waypoint, reached: list[np.ndarray]
    ) -> bool:
        end = waypoint.pose_world_tcp
        distance = float(np.linalg.norm(end[:3, 3] - start[:3, 3]))
        limit_n = self.config.limits.approach_contact_force_n
        unexpected_n = self.config.limits.unexpected_force_n
        baseline = (await self.device(self.devices.arm.state())).tcp_wrench_base[:3]
        travelled, step_m = 0.0, APPROACH_STEP_M
        while travelled < distance - 1e-9:
            travelled = min(distance, travelled + step_m)
            pose = end.copy()
            if travelled < distance:
                pose[:3, 3] = start[:3, 3] + travelled / distance * (end[:3, 3] - start[:3, 3])
            step = Waypoint(pose, waypoint.joints_rad, waypoint.speed_m_s, "approach")
            await self.move(step, new_motion=False)
            reached.append(pose)
            force_n = (await self.device(self.devices.gripper.state())).force_n
            wrench = (await self.device(self.devices.arm.state())).tcp_wrench_base
            rise_n = float(np.linalg.norm(wrench[:3] - baseline))
            if rise_n > force_n + unexpected_n:
                await self.device(self.devices.arm.stop())
                raise UnexpectedForceError(rise_n, force_n, travelled)
            if force_n >= limit_n:
                return True
            if force_n >= APPROACH_FINE_FORCE_FRACTION * limit_n:
                step_m = APPROACH_FINE_STEP_M
        return False

    async def go_home(self, home_world_tcp: np.ndarray, obstacles: Obstacles) -> None:
        """To the home pose through the planner's checks, then check the arm is there."""
        pose, joints = await self.arm_pose()
        try:
            plan = await self.compute(
                self.planner.plan_home, pose, joints, home_world_tcp, obstacles
            )
        except SafetyViolation as violation:
            raise HomeError(f"cannot go home before the capture: {violation}") from None
        for waypoint in plan:
            await self.move(waypoint)
        pose, _ = await self.arm_pose()
        if not at_pose(pose, home_world_tcp):
            raise HomeError(f"the arm stopped at {np.round(pose[:3, 3], 3)} m, not at home")

    async def press_fingers(self, *, timeout_s: float) -> GripperState:
        """The touch: the fingers open slowly to the full stroke, pushing the pad onto the
        surface, and stop at ``limits.contact_force_n`` (or where any rigid part meets
        something: the gripper's motor stalls)."""
        return await self.device(
            self.devices.gripper.move(
                self.config.gripper.stroke_m,
                speed_m_s=self.config.motion.finger_speed_m_s,
                force_limit_n=self.config.limits.contact_force_n,
                timeout_s=timeout_s,
            )
        )

    async def open_fingers_to_touch_width(self) -> None:
        """Fingers to the approach width (closing them draws the pad back from a surface)."""
        await self.device(
            self.devices.gripper.move(
                self.config.motion.touch_width_m,
                speed_m_s=0.05,
                force_limit_n=self.config.limits.max_force_n,
                timeout_s=10.0,
            )
        )

    async def make_safe(
        self, obstacles: Obstacles, *, report_failure: bool = True, lift: bool = True
    ) -> str | None:
        """Stop all motion, pull the pad back, take the tool back to where the interrupted
        motion started (the way it came; with none interrupted it stays) and, with ``lift``,
        up above ``obstacles``. Only ever to those poses, so repeated faults cannot walk the
        arm away.
        Errors here are logged, never raised: this runs on faults, and must not hide the first
        error. Returns why the retreat failed (None when it did not, or ``report_failure`` is
        False)."""
        devices = self.devices
        for stop in (devices.arm.stop, devices.gripper.stop):
            try:
                await stop()
            except DeviceError as error:
                log.error("stop failed: %s", error)
        back_to = self.move_start_world_tcp
        back_to_joints = self.move_start_joints_rad
        try:
            arm = await devices.arm.state()
            if arm.protective_stopped:
                await devices.arm.recover_protective_stop()
                arm = await devices.arm.state()
            gripper = await devices.gripper.state()
            if gripper.width_m > self.config.motion.touch_width_m + 1e-4:
                await self.open_fingers_to_touch_width()
            pose_world_tcp = self.pose_world_tcp(arm)
            joints = arm.joints_rad
            retreat = partial(
                self.planner.plan_retreat,
                back_to_world_tcp=back_to,
                back_to_joints_rad=back_to_joints,
            )
            for waypoint in await self.compute(retreat, pose_world_tcp, joints):
                await self.move(waypoint)
                pose_world_tcp, joints = waypoint.pose_world_tcp, waypoint.joints_rad
        except (DeviceError, SafetyViolation) as error:
            if not report_failure:
                log.warning("stayed at the last approach start: %s", error)
                return None
            log.error("could not retreat to a safe pose: %s", error)
            return f"retreat failed: {error}"
        # Back where the motion started, a pose the arm reached without touching anything:
        # safe. Going up above the object is a courtesy a wrong estimate may refuse.
        if not lift:
            return None
        try:
            lift_plan = await self.compute(
                self.planner.plan_lift, pose_world_tcp, joints, obstacles
            )
            for waypoint in lift_plan:
                await self.move(waypoint)
        except (DeviceError, SafetyViolation) as error:
            log.warning("stayed where the interrupted motion started: %s", error)
        return None


def _check_joint_start(waypoint: Waypoint, joints_rad: np.ndarray) -> None:
    """Refuse a joint move from joints other than those its path was checked from."""
    if waypoint.start_joints_rad is None:
        return
    off_rad = float(np.max(np.abs(joints_rad - waypoint.start_joints_rad)))
    if off_rad > JOINT_START_TOLERANCE_RAD:
        raise SafetyViolation(
            f"{waypoint.label}: the arm's joints are {off_rad:.3f} rad from those the joint move"
            " was checked from"
        )
