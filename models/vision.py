"""The shape a session starts from, before any touch: vision's estimate.

1. The priors predict the object's occupancy from the colour image, the sensor's depth replacing
   the predicted depth where it returned; with several priors (``auto``) the one whose shape best
   covers the seen silhouette is used (:mod:`models.prior.auto`). Space the camera saw empty is
   carved out of every prediction (:mod:`models.prior.carving`).
2. With depth (``input = "rgbd"``, or ``"auto"`` when the frame has depth) the visible side's
   depth points become surface and free-space observations
   (:func:`models.touch.observations.camera_observations`) of the fused field that touches update
   later, with the prior as its mean (:mod:`models.touch.fused`); the field passes through them
   (the prior's pose is fitted to them first only when ``VisionSettings.fusion.pose_fit``). So
   the session, the benchmarks and ``eval prior`` start from one estimate.
3. Symmetry completion (:mod:`models.symmetry`): the seen points mirrored about the best-supported
   vertical plane (or turned about the best vertical axis) are added as weaker observations
   where they do not fall into space the camera saw empty.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
import trimesh

from models.camera import CameraIntrinsics
from models.geometry import VoxelGrid
from models.object_bound import object_depth_points
from models.prior.auto import choose_prior
from models.prior.carving import CameraView
from models.prior.shape_prior import PriorPrediction, ShapePrior
from models.symmetry import SymmetryFit, complete_by_symmetry
from models.touch.fused import FusedShape, FusionSettings, prior_surface
from models.touch.observations import SurfaceObservations, camera_observations

InputMode = Literal["auto", "rgb", "rgbd"]


def resolve_input(mode: InputMode, depth_m: np.ndarray | None) -> Literal["rgb", "rgbd"]:
    """``auto``: RGB-D when the frame has depth returns, RGB otherwise."""
    if mode != "auto":
        return mode
    has_depth = depth_m is not None and bool(np.any(np.asarray(depth_m) > 0))
    return "rgbd" if has_depth else "rgb"


@dataclass(frozen=True)
class VisionSettings:
    """How the session's starting estimate is made from one frame."""

    fusion: FusionSettings = field(default_factory=FusionSettings)
    """The fused field of the depth points. No pose fit: fitted to the visible side, the prior's
    scale and yaw absorbed its shape errors there and moved its unseen side (on 20 real-object
    meshes, Chamfer 16.0 mm with the fit, 12.5 mm without; docs/prior.md)."""
    symmetry: bool = True
    """Complete the unseen side by the best-supported symmetry (RGB-D only), when one is."""
    use_variance: bool = True
    """The fused field's P(inside) with its uncertainty (``FusedShape.probabilities``), as the
    session's ``fusion_policy = "variance"`` (or ``"committee"``) reads it."""


@dataclass
class VisionEstimate:
    """What vision makes of one frame: the chosen prior's prediction, the camera's
    observations, the fused field (RGB-D) and its probabilities on the prediction's grid."""

    prediction: PriorPrediction
    input: Literal["rgb", "rgbd"]
    probabilities: np.ndarray
    """(N, N, N) occupancy on ``prediction.grid``: the fused field's P(inside) with depth,
    the prediction's otherwise."""
    camera_observations: SurfaceObservations = field(default_factory=SurfaceObservations.none)
    """The visible side's depth points and the free space before them (source -1), and the
    symmetry's mirrored points (source -2); touches are fused with them."""
    fused: FusedShape | None = None
    prior_scores: dict[str, float] = field(default_factory=dict)
    symmetry: SymmetryFit | None = None

    @property
    def grid(self) -> VoxelGrid:
        return self.prediction.grid

    def surface_mesh(self) -> trimesh.Trimesh:
        """The estimate's surface (world metres) through the extraction every estimate uses."""
        if self.fused is not None:
            return self.fused.mesh()
        return prior_surface(self.probabilities, self.grid)


def estimate_from_frame(
    priors: Mapping[str, ShapePrior],
    colour_rgb: np.ndarray,
    intrinsics: CameraIntrinsics,
    pose_world_camera: np.ndarray,
    grid: VoxelGrid,
    *,
    depth_m: np.ndarray | None = None,
    input_mode: InputMode = "auto",
    settings: VisionSettings | None = None,
) -> VisionEstimate:
    """The estimate a session starts from (see the module docstring). ``grid`` is the
    registered grid; the estimate's is the prediction's (fitted to the object for a prior of
    the object frame). ``depth_m`` is used only in RGB-D mode (``input_mode`` "rgbd", or
    "auto" with depth returns)."""
    settings = settings or VisionSettings()
    mode = resolve_input(input_mode, depth_m)
    depth = depth_m if mode == "rgbd" else None
    prediction, scores = choose_prior(
        priors, colour_rgb, intrinsics, pose_world_camera, grid, depth_m=depth
    )
    estimate = VisionEstimate(prediction, mode, prediction.probabilities, prior_scores=scores)
    if depth is None:
        return estimate
    points = object_depth_points(depth, intrinsics, pose_world_camera, prediction.grid)
    observations = camera_observations(points, pose_world_camera[:3, 3])
    if observations.is_empty:
        return estimate
    symmetry = None
    if settings.symmetry:
        view = CameraView.from_image(intrinsics, pose_world_camera, depth_m=depth)
        symmetry = complete_by_symmetry(observations, view)
        if symmetry is not None:
            observations = SurfaceObservations.merged([observations, symmetry.observations])
    fused = FusedShape.from_prior(
        prediction.probabilities, prediction.grid, observations, settings.fusion
    )
    return replace(
        estimate,
        probabilities=fused.probabilities(prediction.grid, use_variance=settings.use_variance),
        camera_observations=observations,
        fused=fused,
        symmetry=symmetry,
    )
