"""Benchmarks that print JSON: measured here, reported in docs/benchmarks.md, never asserted."""

from __future__ import annotations

import os
import platform
import statistics
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from controller.config import Config
from controller.motion import pad_pose_facing
from drivers.sim.gelsight import gel_pad_spec
from drivers.sim.world import SimWorld
from models.render import CameraIntrinsics, apply_kinect_depth_noise, render
from models.tactile_sim import GelSightSimulator


def _timed_ms(function: Callable[[], Any], frames: int) -> dict[str, float]:
    """Median and spread of ``frames`` calls after one warm-up call, in milliseconds."""
    function()
    samples = []
    for _ in range(frames):
        start = time.perf_counter()
        function()
        samples.append((time.perf_counter() - start) * 1e3)
    return {
        "median_ms": round(statistics.median(samples), 3),
        "min_ms": round(min(samples), 3),
        "max_ms": round(max(samples), 3),
        "frames": frames,
    }


def benchmark_sim(config: Config, *, frames: int = 20) -> dict[str, Any]:
    """Per-frame times of the bench: Kinect render (+ depth noise) and GelSight simulation."""
    world = SimWorld.from_config(config.sim, config.robot.arm, config.gripper, config.sensor)
    camera = config.cameras.rgbd
    intrinsics = CameraIntrinsics.kinect_v2_colour(camera.colour_scale)
    pose_world_camera = camera.pose_world_camera()
    rng = np.random.default_rng(0)

    start = time.perf_counter()
    world.scene.build()
    bvh_build_ms = (time.perf_counter() - start) * 1e3

    def render_frame() -> None:
        output = render(world.scene, intrinsics, pose_world_camera, rng=rng)
        apply_kinect_depth_noise(output.depth_m, output.normals_camera, rng, intrinsics=intrinsics)

    gel = GelSightSimulator(gel_pad_spec(config.sensor))
    toward_camera = -pose_world_camera[:3, 2]
    height_m = float(world.object_mesh_world.bounds[1, 2]) / 2
    point, normal = world.surface_point_toward(toward_camera, height_m)
    pose_world_pad = pad_pose_facing(point, normal, -0.0005)  # pressed 0.5 mm into the surface
    indentation = gel.indentation_mm(world.scene_mesh_world, pose_world_pad)

    return {
        "benchmark": "sim",
        "object": config.sim.object,
        "object_faces": len(world.object_mesh_world.faces),
        "machine": {
            "cpu_count": os.cpu_count(),
            "processor": platform.processor() or platform.machine(),
            "python": platform.python_version(),
        },
        "kinect_render": {
            "resolution": [intrinsics.width, intrinsics.height],
            "bvh_build_ms": round(bvh_build_ms, 3),
            **_timed_ms(render_frame, frames),
        },
        "gelsight_indentation": {
            "resolution": [gel.spec.image_width_px, gel.spec.image_height_px],
            "contact_px": int(np.count_nonzero(indentation)),
            **_timed_ms(lambda: gel.indentation_mm(world.scene_mesh_world, pose_world_pad), frames),
        },
        "gelsight_render": _timed_ms(lambda: gel.render_bgr(indentation, rng), frames),
    }
