"""A geometric stand-in for the learned perception, for testing the controller alone.

It "sees" a cylinder 1 cm wider than the object's ground-truth bounding radius, proposes touches
around it at mid-height, turns a contact into occupied voxels at the measured points and a miss
into an emptied segment. Real geometry, no learning: the controller's flows are what is tested.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from controller.config import Config
from controller.perception.protocol import (
    ShapeEstimate,
    TouchMeasurement,
    TouchOutcome,
    TouchTarget,
)
from controller.request import ExploreRequest
from drivers.base import RGBDFrame
from drivers.factory import Devices
from models.prior.auto import AUTO
from models.prior.shape_prior import available_priors


class CylinderPerception:
    def __init__(self, config: Config, devices: Devices) -> None:
        assert devices.world is not None
        self.mesh = devices.world.object_mesh_world
        camera_position = config.cameras.rgbd.pose_world_camera()[:3, 3]
        self.grid = config.voxel_grid.grid(tuple(camera_position))
        self.reconstruct_calls = 0
        self.weights_dir = config.models.weights_dir

    def prior_names(self) -> frozenset[str]:
        # The names the learned perception would accept; the cylinder does not depend on them.
        return frozenset(available_priors(self.weights_dir or None)) | {AUTO}

    def reconstruct(self, frame: RGBDFrame, request: ExploreRequest) -> ShapeEstimate:
        self.reconstruct_calls += 1
        centres = self.grid.voxel_centres_world()
        # 1 cm too large, as a vision estimate may be: touches then carve it (voxels flip).
        # Outside it the object is unlikely (below the planner's "may be there" level).
        radius = np.max(np.linalg.norm(self.mesh.vertices[:, :2], axis=1)) + 0.01
        height = self.mesh.bounds[1, 2]
        inside = (np.linalg.norm(centres[..., :2], axis=-1) <= radius) & (centres[..., 2] <= height)
        probabilities = np.where(inside, 0.7, 0.05).astype(np.float32)
        return ShapeEstimate(self.grid, probabilities)

    def select(
        self,
        estimate: ShapeEstimate,
        request: ExploreRequest,
        outcomes: list[TouchOutcome],
        allowed: Callable[[TouchTarget], bool],
        feasible: object = None,
        robot_seconds: object = None,
    ) -> TouchTarget | None:
        occupied = estimate.occupied_points_world()
        radius = np.max(np.linalg.norm(occupied[:, :2], axis=1))
        height = occupied[:, 2].max() * 0.6
        for yaw_deg in (-90, -45, -135, 0, 180, 45, 135, 90):
            yaw = np.radians(yaw_deg + 10 * len(outcomes))
            outward = np.array([np.cos(yaw), np.sin(yaw), 0.0])
            target = TouchTarget(radius * outward + [0, 0, height], -outward)
            if allowed(target):
                return target
        return None

    def interpret(self, measurement: TouchMeasurement) -> TouchOutcome:
        pad = measurement.pose_world_pad
        points = pad[:3, 3][None] if measurement.contact else np.zeros((0, 3))
        return TouchOutcome(measurement, points, None, touch=None)

    def refine(
        self, estimate: ShapeEstimate, outcomes: list[TouchOutcome], request: ExploreRequest
    ) -> ShapeEstimate:
        probabilities = estimate.probabilities.copy()
        outcome = outcomes[-1]
        start = outcome.measurement.pad_start_world
        end = (
            outcome.contact_point_world
            if outcome.contact_point_world is not None
            else outcome.measurement.pose_world_pad[:3, 3]
        )
        for fraction in np.linspace(0, 1, 50):
            ijk = np.floor(self.grid.world_to_voxel(start + fraction * (end - start))).astype(int)
            if np.all((ijk >= 0) & (ijk < self.grid.resolution)):
                contact_end = fraction == 1 and outcome.contact_point_world is not None
                probabilities[tuple(ijk)] = 1.0 if contact_end else 0.0
        return ShapeEstimate(self.grid, probabilities)


def make_cylinder_perception(config: Config, devices: Devices) -> CylinderPerception:
    return CylinderPerception(config, devices)
