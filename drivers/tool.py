"""Geometry of the tool on the UR5 flange: WSG 50 body, two fingers, GelSight on the +x finger.

Tool (flange) frame: z points away from the flange along the fingers, the fingers open along
+-x, the GelSight sits on the outer face of the +x finger looking along +x. Opening the gripper
pushes the gel pad outward along +x: this is how the paper makes the final, gentle contact.

The pad frame (``pose_tcp_pad``) is the one the tactile simulation and reconstruction use:
origin at the centre of the undeformed gel surface, +z the gel's outward normal (tool +x),
+x along the finger toward its tip (the pad's 19 mm side, image columns), +y = z cross x.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from drivers.config import GripperConfig, SensorConfig
from models.geometry import make_transform


@dataclass(frozen=True)
class ToolBox:
    """An oriented box of the tool: centre pose in the tool frame and half extents (metres)."""

    name: str
    pose_tcp_box: NDArray[np.float64]
    half_extents_m: NDArray[np.float64]

    def lowest_world_z_m(self, pose_world_tcp: NDArray[np.float64]) -> float:
        """The box's lowest world z at a tool pose: the corner whose offsets all point down,
        |R[2, :]| . half extents below its centre."""
        pose_world_box = pose_world_tcp @ self.pose_tcp_box
        return float(pose_world_box[2, 3] - np.abs(pose_world_box[2, :3]) @ self.half_extents_m)

    def corners_tcp(self) -> NDArray[np.float64]:
        """The box's 8 corners in the tool frame (8, 3)."""
        signs = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T
        rotation, centre = self.pose_tcp_box[:3, :3], self.pose_tcp_box[:3, 3]
        return (signs * self.half_extents_m) @ rotation.T + centre


class ToolModel:
    """Width-dependent geometry of gripper, fingers and sensor, from their configs."""

    def __init__(self, gripper: GripperConfig, sensor: SensorConfig) -> None:
        self.gripper = gripper
        self.sensor = sensor

    @property
    def finger_tip_z_m(self) -> float:
        return self.gripper.body_size_m[2] + self.gripper.finger_size_m[2]

    def pad_offset_x_m(self, width_m: float) -> float:
        """Tool-frame x of the undeformed gel surface at a finger opening ``width_m``."""
        return width_m / 2 + self.gripper.finger_size_m[0] + self.sensor.housing_thickness_m

    def pose_tcp_pad(self, width_m: float) -> NDArray[np.float64]:
        """Pad frame in the tool frame (see module docstring) at a finger opening."""
        rotation = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])
        centre = [
            self.pad_offset_x_m(width_m),
            0.0,
            self.finger_tip_z_m - self.sensor.pad_centre_from_tip_m,
        ]
        return make_transform(rotation, centre)

    def rigid_boxes(self, width_m: float) -> list[ToolBox]:
        """The tool's rigid parts at a finger opening. The gel's soft layer is left out: it may
        be indented by up to ``max_indentation_mm``, the rigid window behind it may not. The
        window (the pad's footprint) protrudes ``housing_recess_m`` from the housing."""
        body_x, body_y, body_z = self.gripper.body_size_m
        finger_x, finger_y, finger_z = self.gripper.finger_size_m
        sensor = self.sensor
        finger_centre_z = body_z + finger_z / 2
        housing_start_x = width_m / 2 + finger_x
        housing_depth = sensor.housing_thickness_m - sensor.housing_recess_m
        housing_length = sensor.housing_length_m
        housing_y = sensor.pad_height_mm * 1e-3 + 0.006
        window_start_x = housing_start_x + housing_depth
        window_depth = sensor.housing_recess_m - sensor.max_indentation_mm * 1e-3
        pad_centre_z = self.finger_tip_z_m - sensor.pad_centre_from_tip_m

        def box(name: str, centre: tuple[float, float, float], size: tuple[float, ...]) -> ToolBox:
            return ToolBox(name, make_transform(None, centre), np.asarray(size) / 2)

        return [
            box("gripper_body", (0.0, 0.0, body_z / 2), (body_x, body_y, body_z)),
            box(
                "finger_sensor_side",
                (width_m / 2 + finger_x / 2, 0.0, finger_centre_z),
                (finger_x, finger_y, finger_z),
            ),
            box(
                "finger_other_side",
                (-width_m / 2 - finger_x / 2, 0.0, finger_centre_z),
                (finger_x, finger_y, finger_z),
            ),
            box(
                "gelsight_housing",
                (
                    housing_start_x + housing_depth / 2,
                    0.0,
                    self.finger_tip_z_m - housing_length / 2,
                ),
                (housing_depth, housing_y, housing_length),
            ),
            box(
                "gelsight_window",
                (window_start_x + window_depth / 2, 0.0, pad_centre_z),
                (window_depth, sensor.pad_height_mm * 1e-3, sensor.pad_width_mm * 1e-3),
            ),
        ]

    def leading_points_pad(
        self, width_m: float, spacing_m: float
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Where an object can first meet a finger as the fingers open, at an opening
        ``width_m``: points (M, 3) and the direction each moves (M, 3, unit), pad frame,
        metres. The sensor's finger moves along the pad's +z: the gel's surface (z = 0, the
        pad), then the housing's front around it (z = -``housing_recess_m``), then the finger's
        front beyond the housing, each face without the part the faces ahead of it cover. The
        other finger moves along -z: its outer face. Fingers stopped by force without an imprint
        met the object at one of them (or the table)."""
        pad_from_tcp = np.linalg.inv(self.pose_tcp_pad(width_m))

        def extent_pad(box: ToolBox) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
            corners = box.corners_tcp() @ pad_from_tcp[:3, :3].T + pad_from_tcp[:3, 3]
            return corners.min(axis=0), corners.max(axis=0)

        boxes = {box.name: box for box in self.rigid_boxes(width_m)}
        half_pad = np.array([self.sensor.pad_width_mm, self.sensor.pad_height_mm]) * 1e-3 / 2
        faces = [(0.0, -half_pad, half_pad)]  # (pad z, (x, y) min, max), front first
        for name in ("gelsight_housing", "finger_sensor_side"):
            low, high = extent_pad(boxes[name])
            faces.append((high[2], low[:2], high[:2]))
        points = [
            _face_points(z, low, high, [ahead[1:] for ahead in faces[:index]], spacing_m)
            for index, (z, low, high) in enumerate(faces)
        ]
        low, high = extent_pad(boxes["finger_other_side"])
        points.append(_face_points(low[2], low[:2], high[:2], [], spacing_m))
        directions = [np.tile([0.0, 0.0, 1.0], (len(p), 1)) for p in points[:-1]]
        directions.append(np.tile([0.0, 0.0, -1.0], (len(points[-1]), 1)))
        return np.concatenate(points), np.concatenate(directions)


def _face_points(
    z_m: float,
    low: NDArray[np.float64],
    high: NDArray[np.float64],
    covered_by: list[tuple[NDArray[np.float64], NDArray[np.float64]]],
    spacing_m: float,
) -> NDArray[np.float64]:
    """A grid at most ``spacing_m`` apart on the rectangle ``low``-``high`` (x, y) at height
    ``z_m``, without the points strictly inside any rectangle of ``covered_by``."""
    axes = [
        np.linspace(low[a], high[a], max(2, int(np.ceil((high[a] - low[a]) / spacing_m)) + 1))
        for a in range(2)
    ]
    x, y = (grid.ravel() for grid in np.meshgrid(*axes, indexing="ij"))
    covered = np.zeros(x.shape, bool)
    for ahead_low, ahead_high in covered_by:
        covered |= (
            (x > ahead_low[0]) & (x < ahead_high[0]) & (y > ahead_low[1]) & (y < ahead_high[1])
        )
    return np.column_stack([x[~covered], y[~covered], np.full(int((~covered).sum()), z_m)])
