"""`touchshape bench sim`: per-frame times of the simulated bench, the Kinect render and the
GelSight simulation, as JSON (reported in docs/benchmarks.md, never asserted)."""

from __future__ import annotations

import platform
from collections.abc import Callable
from typing import Any

import numpy as np

from controller.benchmarks.timing import Stopwatch, machine, repeated
from controller.config import Config
from controller.motion.poses import pad_pose_facing
from drivers.sim.gelsight import gel_pad_spec
from drivers.sim.world import SimWorld
from models.camera import CameraIntrinsics
from models.render import apply_kinect_depth_noise, render
from models.tactile.sim import GelSightSimulator


def benchmark_sim(config: Config, *, frames: int = 20) -> dict[str, Any]:
    """Per-frame times of the bench: Kinect render (+ depth noise) and GelSight simulation."""
    world = SimWorld.from_config(config.sim, config.robot.arm, config.gripper, config.sensor)
    camera = config.cameras.rgbd
    intrinsics = CameraIntrinsics.kinect_v2_colour(camera.colour_scale)
    pose_world_camera = camera.pose_world_camera()
    rng = np.random.default_rng(0)

    bvh_build = Stopwatch()
    bvh_build(world.scene.build)

    def render_frame() -> None:
        output = render(world.scene, intrinsics, pose_world_camera, rng=rng)
        apply_kinect_depth_noise(output.depth_m, output.normals_camera, rng, intrinsics=intrinsics)

    gel = GelSightSimulator(gel_pad_spec(config.sensor))
    toward_camera = -pose_world_camera[:3, 2]
    height_m = float(world.object_mesh_world.bounds[1, 2]) / 2
    point, normal = world.surface_point_toward(toward_camera, height_m)
    pose_world_pad = pad_pose_facing(point, normal, -0.0005)  # pressed 0.5 mm into the surface
    indentation = gel.indentation_mm(world.scene_mesh_world, pose_world_pad)

    def per_frame(function: Callable[[], object]) -> dict[str, float]:
        return {**repeated(function, frames).milliseconds(), "frames": frames}

    return {
        "benchmark": "sim",
        "object": config.sim.object,
        "object_faces": len(world.object_mesh_world.faces),
        "machine": machine(python=platform.python_version()),
        "kinect_render": {
            "resolution": [intrinsics.width, intrinsics.height],
            "bvh_build_ms": round(bvh_build.wall_s[0] * 1e3, 3),
            **per_frame(render_frame),
        },
        "gelsight_indentation": {
            "resolution": [gel.spec.image_width_px, gel.spec.image_height_px],
            "contact_px": int(np.count_nonzero(indentation)),
            **per_frame(lambda: gel.indentation_mm(world.scene_mesh_world, pose_world_pad)),
        },
        "gelsight_render": per_frame(lambda: gel.render_bgr(indentation, rng)),
    }
