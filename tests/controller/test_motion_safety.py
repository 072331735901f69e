"""Safety checks and touch motion planning: every pose checked, detours around the object, and
planned motions that the simulated arm executes without a protective stop."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from controller.config import Config, LimitsConfig
from controller.motion.planner import MotionPlanner
from controller.motion.poses import at_pose, home_pose_world_tcp
from controller.motion.safety import (
    Obstacles,
    SafetyViolation,
    check_clearance,
    check_force,
    check_pose,
    check_reachable,
    check_speed,
    check_workspace,
)
from drivers.config import ArmConfig, GripperConfig, SensorConfig, SimConfig
from drivers.sim.arm import SimUR5
from drivers.sim.gelsight import gel_pad_spec
from drivers.sim.gripper import SimWSG50
from drivers.sim.world import SimWorld
from drivers.tool import ToolModel
from drivers.ur5.kinematics import forward_kinematics
from models.geometry import (
    make_transform,
    matrix_to_ur_pose,
    radial_angle_about_vertical,
    rotation_angle_between,
    ur_pose_to_matrix,
)
from models.object_bound import ObjectBound
from models.tactile.sim import GelSightSimulator

CONFIG = Config()
TOOL = ToolModel(GripperConfig(), SensorConfig())
POSE_WORLD_BASE = ur_pose_to_matrix(ArmConfig().pose_world_base)
HOME = np.asarray(ArmConfig().home_joints_rad)
DOWN = make_transform(np.diag([1.0, -1.0, -1.0]))  # tool z pointing down


def tool_down_at(x: float, y: float, z: float) -> np.ndarray:
    pose = DOWN.copy()
    pose[:3, 3] = (x, y, z)
    return pose


def box_obstacles(mesh: trimesh.Trimesh, pitch_m: float = 0.004) -> Obstacles:
    """Occupied points of a mesh, as a perfect shape estimate would give them."""
    return Obstacles(mesh.voxelized(pitch_m).fill().points)


def planner() -> MotionPlanner:
    return MotionPlanner(
        tool=TOOL,
        limits=CONFIG.limits,
        motion=CONFIG.motion,
        pose_world_base=POSE_WORLD_BASE,
        stroke_m=GripperConfig().stroke_m,
    )


def test_limits_are_enforced() -> None:
    limits = LimitsConfig()
    check_workspace(tool_down_at(0.0, 0.0, 0.3), limits)
    with pytest.raises(SafetyViolation, match="workspace"):
        check_workspace(tool_down_at(0.0, 0.0, 0.9), limits)
    with pytest.raises(SafetyViolation, match="TCP speed"):
        check_speed(0.5, limits.max_tcp_speed_m_s)
    with pytest.raises(SafetyViolation):
        check_speed(0.0, limits.max_tcp_speed_m_s)
    check_force(limits.max_force_n - 1, limits)
    with pytest.raises(SafetyViolation, match="force"):
        check_force(limits.max_force_n + 1, limits)
    with pytest.raises(SafetyViolation, match="reach"):
        check_reachable(tool_down_at(1.5, 0.0, 0.3), POSE_WORLD_BASE, HOME)


def test_table_clearance_uses_the_lowest_tool_point() -> None:
    limits = LimitsConfig()
    tip_m = TOOL.finger_tip_z_m  # with the tool down, the fingertips are the lowest point
    check_clearance(tool_down_at(0, 0, tip_m + 0.011), 0.08, TOOL, Obstacles.none(), limits)
    with pytest.raises(SafetyViolation, match="above the table"):
        check_clearance(tool_down_at(0, 0, tip_m + 0.009), 0.08, TOOL, Obstacles.none(), limits)


def test_shape_clearance_and_exempt_parts() -> None:
    limits = LimitsConfig()
    pose = tool_down_at(0.0, 0.0, 0.4)
    near_body = Obstacles(np.array([[0.0, 0.0, 0.4 - 0.005]]))  # 5 mm past the flange face
    with pytest.raises(SafetyViolation, match="gripper_body"):
        check_clearance(pose, 0.08, TOOL, near_body, limits)
    # 5 mm in front of the gel's rigid backing: only the sensor parts may be that close.
    pad = pose @ TOOL.pose_tcp_pad(0.08)
    in_front_of_pad = Obstacles(pad[:3, 3][None] + 0.005 * pad[:3, 2])
    with pytest.raises(SafetyViolation, match="gelsight_window"):
        check_clearance(pose, 0.08, TOOL, in_front_of_pad, limits)
    check_clearance(
        pose,
        0.08,
        TOOL,
        in_front_of_pad,
        limits,
        exempt_parts=("gelsight_window", "gelsight_housing", "finger_sensor_side"),
    )


def test_touch_geometry_faces_the_target() -> None:
    touch = planner().touch_geometry((0.0, -0.04, 0.05), (0.0, 1.0, 0.0))
    pad = touch.pose_world_tcp_standoff @ TOOL.pose_tcp_pad(CONFIG.motion.touch_width_m)
    np.testing.assert_allclose(pad[:3, 2], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(pad[:3, 3], [0.0, -0.045, 0.05], atol=1e-12)
    np.testing.assert_allclose(touch.pad_start_world, [0.0, -0.1, 0.05], atol=1e-12)
    # The fingers open 15 mm more on each side: the pad can reach 10 mm past the target.
    np.testing.assert_allclose(touch.pad_reach_world, [0.0, -0.03, 0.05], atol=1e-12)


def test_far_targets_detour_above_the_object_and_near_ones_move_directly() -> None:
    mesh = trimesh.creation.cylinder(
        radius=0.04, height=0.1, transform=make_transform(None, (0, 0, 0.05))
    )
    obstacles = box_obstacles(mesh)
    plan = planner()
    first = plan.touch_geometry((0.0, -0.04, 0.06), (0.0, 1.0, 0.0))
    joints = check_reachable(first.pose_world_tcp_start, POSE_WORLD_BASE, HOME)
    # A target a quarter turn around the object: detour.
    side = plan.touch_geometry((0.04, 0.0, 0.06), (-1.0, 0.0, 0.0))
    assert radial_angle_about_vertical(first.target_world, side.target_world) > np.radians(80)
    waypoints = plan.plan_transit(first.pose_world_tcp_start, joints, side, obstacles)
    assert [w.label for w in waypoints] == ["lift", "across", "descend"]
    top = mesh.bounds[1, 2]
    lowest = min(w.pose_world_tcp[2, 3] for w in waypoints[:2]) - TOOL.finger_tip_z_m
    assert lowest >= top + CONFIG.motion.safe_height_margin_m - 1e-9
    # A target 15 degrees further round: straight there.
    angle = np.radians(15)
    near = plan.touch_geometry(
        (0.04 * np.sin(angle), -0.04 * np.cos(angle), 0.06), (-np.sin(angle), np.cos(angle), 0.0)
    )
    waypoints = plan.plan_transit(first.pose_world_tcp_start, joints, near, obstacles)
    assert [w.label for w in waypoints] == ["direct"]


def test_unreachable_touch_is_rejected_before_moving() -> None:
    """Far out, the workspace box refuses the path first; inside the box but beyond the arm's
    reach (the far top corner, 1 m from the base), the inverse kinematics does."""
    plan = planner()
    start = tool_down_at(0.0, -0.2, 0.4)
    touch = plan.touch_geometry((0.0, 0.9, 0.05), (0.0, -1.0, 0.0))
    with pytest.raises(SafetyViolation, match=r"TCP \[.*\] m outside the workspace box"):
        plan.plan_transit(start, HOME, touch, Obstacles.none())
    touch = plan.touch_geometry((0.25, 0.3, 0.4), (1.0, 0.0, 0.0))
    check_workspace(touch.pose_world_tcp_start, CONFIG.limits)  # its approach start is inside
    with pytest.raises(SafetyViolation, match=r"out of the arm's reach \(no IK solution\)"):
        plan.plan_transit(start, HOME, touch, Obstacles.none())


def test_a_retreat_goes_back_to_where_the_motion_started_or_nowhere() -> None:
    """Never to a pose relative to where the arm is: faults in a row must not walk it away."""
    plan = planner()
    pose = tool_down_at(0.0, -0.2, 0.3)
    joints = check_reachable(pose, POSE_WORLD_BASE, HOME)
    assert plan.plan_retreat(pose, joints, back_to_world_tcp=None) == []
    assert plan.plan_retreat(pose, joints, back_to_world_tcp=pose.copy()) == []
    back = tool_down_at(0.0, -0.25, 0.35)
    (retreat,) = plan.plan_retreat(pose, joints, back_to_world_tcp=back)
    assert np.allclose(retreat.pose_world_tcp, back)


def test_the_way_home_is_checked_and_ends_at_home() -> None:
    plan = planner()
    home = home_pose_world_tcp(ArmConfig())
    mesh = trimesh.creation.cylinder(
        radius=0.04, height=0.1, transform=make_transform(None, (0, 0, 0.05))
    )
    obstacles = box_obstacles(mesh)
    assert plan.plan_home(home, HOME, home, obstacles) == []
    # From beside the object, as a fault on an approach leaves the arm.
    touch = plan.touch_geometry((0.0, -0.04, 0.06), (0.0, 1.0, 0.0))
    start = touch.pose_world_tcp_start
    joints = check_reachable(start, POSE_WORLD_BASE, HOME)
    way = plan.plan_home(start, joints, home, obstacles)
    assert at_pose(way[-1].pose_world_tcp, home)
    assert way[0].pose_world_tcp[2, 3] > start[2, 3]  # up first, not across the object
    # An estimate reaching up to the tool at home: no way home is allowed.
    tall = trimesh.creation.box((0.1, 0.1, 0.5), transform=make_transform(None, (0, 0, 0.25)))
    with pytest.raises(SafetyViolation):
        plan.plan_home(start, joints, home, box_obstacles(tall, 0.01))


async def test_planned_touch_runs_on_the_sim_arm_without_protective_stop() -> None:
    mesh = trimesh.creation.cylinder(
        radius=0.04, height=0.1, transform=make_transform(None, (0, 0, 0.05))
    )
    world = SimWorld(
        mesh, sim=SimConfig(), arm=ArmConfig(), gripper=GripperConfig(), sensor=SensorConfig()
    )
    arm = SimUR5(world, ArmConfig())
    gel = GelSightSimulator(gel_pad_spec(SensorConfig()))
    gripper = SimWSG50(world, GripperConfig(), gel)
    await arm.connect()
    await gripper.connect()
    await gripper.home()
    await gripper.move(CONFIG.motion.touch_width_m, speed_m_s=0.1, force_limit_n=40, timeout_s=5)
    obstacles = box_obstacles(mesh)
    plan = planner()
    pose = world.pose_world_tcp()
    joints = world.joints_rad
    for target, direction in (((0.0, -0.04, 0.07), (0, 1, 0)), ((0.04, 0.0, 0.07), (-1, 0, 0))):
        touch = plan.touch_geometry(target, direction)
        waypoints = plan.plan_transit(pose, joints, touch, obstacles)
        waypoints.append(plan.plan_approach(touch, waypoints[-1].joints_rad, obstacles))
        for waypoint in waypoints:
            pose_base = np.linalg.inv(POSE_WORLD_BASE) @ waypoint.pose_world_tcp
            await arm.move_linear(
                matrix_to_ur_pose(pose_base),
                speed_m_s=waypoint.speed_m_s,
                acceleration_m_s2=1.0,
                timeout_s=60,
            )
            assert not (await arm.state()).protective_stopped
        result = await gripper.move(0.11, speed_m_s=0.005, force_limit_n=5.0, timeout_s=30)
        assert result.blocked, "the pad should touch the cylinder"
        await gripper.move(
            CONFIG.motion.touch_width_m, speed_m_s=0.05, force_limit_n=40, timeout_s=5
        )
        retract = plan.plan_retract(touch, world.pose_world_tcp(), world.joints_rad)
        await arm.move_linear(
            matrix_to_ur_pose(np.linalg.inv(POSE_WORLD_BASE) @ retract.pose_world_tcp),
            speed_m_s=retract.speed_m_s,
            acceleration_m_s2=1.0,
            timeout_s=60,
        )
        pose, joints = world.pose_world_tcp(), world.joints_rad


def test_clearance_from_where_the_object_may_be() -> None:
    """Parts keep the margin from the possible points (v above a low probability), not only
    from the estimate; on an approach the gel's window may come up to the estimate itself and
    the sensor's housing and finger keep a quarter of the margin."""
    limits = LimitsConfig()
    pose = tool_down_at(0.0, 0.0, 0.4)
    beside_body = np.array([[0.0, 0.0, 0.4 - 0.005]])
    check_clearance(pose, 0.08, TOOL, Obstacles(np.zeros((0, 3))), limits)
    with pytest.raises(SafetyViolation, match=r"gripper_body.*where the object may be"):
        check_clearance(pose, 0.08, TOOL, Obstacles(np.zeros((0, 3)), beside_body), limits)
    pad = pose @ TOOL.pose_tcp_pad(0.08)
    ahead = pad[:3, 3][None] + 0.004 * pad[:3, 2]  # 4 mm in front of the gel
    possible_ahead = Obstacles(np.zeros((0, 3)), ahead)
    approach = {
        "exempt_parts": ("gelsight_window",),
        "near_parts": ("gelsight_housing", "finger_sensor_side"),
    }
    check_clearance(pose, 0.08, TOOL, possible_ahead, limits, **approach)
    with pytest.raises(SafetyViolation, match=r"gelsight_window.*the shape estimate"):
        check_clearance(pose, 0.08, TOOL, Obstacles(ahead - 0.006 * pad[:3, 2]), limits, **approach)
    # 2 mm beside the housing's outer side: inside the near parts' 2.5 mm.
    housing = next(b for b in TOOL.rigid_boxes(0.08) if b.name == "gelsight_housing")
    pose_box = pose @ housing.pose_tcp_box
    side = pose_box[:3, 3] + (housing.half_extents_m[1] + 0.002) * pose_box[:3, 1]
    with pytest.raises(SafetyViolation, match="gelsight_housing"):
        check_clearance(
            pose, 0.08, TOOL, Obstacles(np.zeros((0, 3)), side[None]), limits, **approach
        )


async def test_a_half_turn_across_the_object_runs_on_the_sim_arm() -> None:
    """From a top touch to a side touch the tool turns 180 degrees: the planner splits the
    turn (a half-turn has no unique shortest rotation) and finds the joint-rate peak near the
    wrist singularity between its checked poses, so the arm executes what was checked (the
    single line planned before ran a wrist joint over 3.14 rad/s on the sim arm)."""
    joints = np.array([-1.5708, -1.5638286814745541, 1.440842183114267, -1.4478135016230427,
                       -1.5708, 0.0])  # fmt: skip
    world = SimWorld(
        trimesh.creation.box((0.01, 0.01, 0.01)),
        sim=SimConfig(),
        arm=ArmConfig(),
        gripper=GripperConfig(),
        sensor=SensorConfig(),
    )
    world.joints_rad = joints
    world.pose_base_flange = forward_kinematics(joints)
    start = world.pose_world_tcp()
    goal = make_transform(
        np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]), (-0.185, -0.006, 0.48)
    )
    waypoints = planner().plan_detour(start, joints, goal, Obstacles.none())
    assert [w.label for w in waypoints] == ["across", "across"]
    arm = SimUR5(world, ArmConfig())
    await arm.connect()
    previous = start
    for waypoint in waypoints:
        assert rotation_angle_between(previous[:3, :3], waypoint.pose_world_tcp[:3, :3]) <= (
            np.pi / 2 + 1e-9
        )
        if waypoint.kind == "joints":  # where the line would crawl near the singularity
            await arm.move_joints(
                waypoint.joints_rad,
                speed_rad_s=waypoint.speed_m_s,
                acceleration_rad_s2=1.0,
                timeout_s=60,
            )
        else:
            await arm.move_linear(
                matrix_to_ur_pose(np.linalg.inv(POSE_WORLD_BASE) @ waypoint.pose_world_tcp),
                speed_m_s=waypoint.speed_m_s,
                acceleration_m_s2=0.5,
                timeout_s=60,
            )
        previous = waypoint.pose_world_tcp
    np.testing.assert_allclose(world.pose_world_tcp(), goal, atol=1e-6)


def test_detour_backs_out_when_the_way_up_is_blocked() -> None:
    """After a side touch under an overhang the way straight up is blocked: the detour first
    backs out along the approach line, then lifts."""
    mesh = trimesh.creation.cylinder(
        radius=0.04, height=0.1, transform=make_transform(None, (0, 0, 0.05))
    )
    plan = planner()
    touch = plan.touch_geometry((0.0, -0.04, 0.05), (0.0, 1.0, 0.0))
    start = touch.pose_world_tcp_start
    joints = check_reachable(start, POSE_WORLD_BASE, HOME)
    roof = trimesh.creation.box((0.1, 0.1, 0.004))
    roof.apply_translation((0.0, -0.07, start[2, 3] + 0.06))
    points = np.concatenate([box_obstacles(mesh).occupied_points_world, roof.sample(2000)])
    obstacles = Obstacles(points)
    other = plan.touch_geometry((0.04, 0.0, 0.05), (-1.0, 0.0, 0.0))
    waypoints = plan.plan_transit(start, joints, other, obstacles)
    assert [w.label for w in waypoints][:2] == ["back", "lift"]
    back = waypoints[0].pose_world_tcp
    np.testing.assert_allclose(back[:3, :3], start[:3, :3], atol=1e-12)
    assert back[1, 3] < start[1, 3]  # away from the object, along -y


def test_transit_retraces_the_way_the_arm_came_when_every_way_out_is_blocked() -> None:
    """The refined estimate now says the object may be (v above the low level, not 0.5) above
    the approach start and behind it, where the arm came down: no lift or back-out is clear.
    The arm came down through there, so it goes back up the same way (only the table
    checked), then detours."""
    mesh = trimesh.creation.cylinder(
        radius=0.04, height=0.1, transform=make_transform(None, (0, 0, 0.05))
    )
    plan = planner()
    touch = plan.touch_geometry((0.0, -0.04, 0.05), (0.0, 1.0, 0.0))
    start = touch.pose_world_tcp_start
    joints = check_reachable(start, POSE_WORLD_BASE, HOME)
    roof = trimesh.creation.box((0.1, 0.25, 0.004))
    roof.apply_translation((0.0, -0.15, start[2, 3] + 0.06))
    occupied = box_obstacles(mesh).occupied_points_world
    obstacles = Obstacles(occupied, np.concatenate([occupied, roof.sample(4000)]))
    above = start.copy()
    above[2, 3] += 0.15  # where the arm came down from
    other = plan.touch_geometry((0.04, 0.0, 0.05), (-1.0, 0.0, 0.0))
    with pytest.raises(SafetyViolation):
        plan.plan_transit(start, joints, other, obstacles)
    waypoints = plan.plan_transit(start, joints, other, obstacles, came_from=[above])
    assert waypoints[0].label == "retrace"
    np.testing.assert_allclose(waypoints[0].pose_world_tcp, above)
    np.testing.assert_allclose(waypoints[-1].pose_world_tcp, other.pose_world_tcp_start)


def test_a_part_deep_inside_where_the_object_may_be_is_refused() -> None:
    """Clearance is measured to the bound's surface; a part whose centre lies deep inside the
    bound, far from that surface, is refused too (the bound is solid, not a shell)."""
    grid = ObjectBound.cube((0.0, 0.0, 0.0))
    possible = np.zeros((grid.resolution,) * 3, dtype=bool)
    possible[10:90, 10:90, 0:90] = True  # a 32 cm block: its surface is far from the tool
    bound = ObjectBound(grid, possible, np.zeros_like(possible))
    obstacles = Obstacles(np.zeros((0, 3)), bound=bound)
    assert len(obstacles.near(np.array([0.0, 0.0, 0.2]), 0.1)) == 0
    with pytest.raises(SafetyViolation, match="inside where the object may be"):
        check_clearance(tool_down_at(0.0, 0.0, 0.3), 0.08, TOOL, obstacles, LimitsConfig())
    check_clearance(tool_down_at(0.0, 0.0, 0.55), 0.08, TOOL, obstacles, LimitsConfig())


def block_bound(k_top: int, *, around_xy: int = 8) -> ObjectBound:
    """A bound that is a block of voxels on the table up to voxel layer ``k_top``, ``around_xy``
    voxels either side of the cube's centre."""
    grid = ObjectBound.cube((0.0, 0.0, 0.0))
    possible = np.zeros((grid.resolution,) * 3, dtype=bool)
    low, high = 50 - around_xy, 50 + around_xy
    possible[low:high, low:high, :k_top] = True
    return ObjectBound(grid, possible, np.zeros_like(possible))


def test_a_lift_from_inside_the_estimates_margin_still_keeps_clear_of_the_measured_bound() -> None:
    """A refined estimate spread over the arm's pose: the lift keeps the margin from the
    estimate itself and from the measured bound (the arm was clear of it), not from nothing."""
    plan = planner()
    pose = tool_down_at(0.1, 0.0, 0.3)
    joints = check_reachable(pose, POSE_WORLD_BASE, np.array(ArmConfig().home_joints_rad))
    grown = block_bound(80, around_xy=40)  # the estimate's additions reach around the tool
    low = block_bound(20)  # measured: an 8 cm block well below the tool
    obstacles = Obstacles(np.zeros((0, 3)), bound=grown, measured_bound=low)
    with pytest.raises(SafetyViolation):
        check_pose(
            pose,
            CONFIG.motion.touch_width_m,
            tool=TOOL,
            obstacles=obstacles,
            limits=CONFIG.limits,
            pose_world_base=POSE_WORLD_BASE,
            joints_near_rad=joints,
        )
    assert plan.plan_lift(pose, joints, obstacles) is not None
    # Measured to reach around the tool too: no lift there.
    tall = Obstacles(np.zeros((0, 3)), bound=grown, measured_bound=block_bound(80, around_xy=40))
    with pytest.raises(SafetyViolation):
        plan.plan_lift(pose, joints, tall)
