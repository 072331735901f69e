"""The global step of a touch: the prior's latent (and, where asked, the object's pose) fitted
to every touch so far, taken only once the fit has predicted a touch it had not seen.

Why: the fused correction (``models.touch.fused``) follows the contacts exactly but reaches only
35 mm from them; where vision is wrong everywhere (a real object the prior never saw), only the
prior's latent moves the whole shape (docs/explore.md: run 6c, latent -29 % vs fused -17 % per
object; run 8, this step -25.1 % vs -15.8 % on 10 real meshes from RGB). The pose fit is off by
default: it took the prior's shape errors for pose (``GlobalSettings.pose_fit``). A latent
fitted to a few patches can also go wrong, so a step is guarded:

* after touch k the fit to touches 1..k (:func:`fit_mean`, from the previous fit) is made, and
  kept as the *candidate*;
* the candidate of touch k-1 never saw touch k. The new fit becomes the mean only when that
  predecessor predicted touch k (:func:`held_out_error_m`: its contacts, its free space and
  where a force stopped it) better than vision's shape did, by ``margin_m``, and no worse than
  the mean in use, and when the new fit keeps the camera's depth points (RGB-D) as close as
  vision's shape did, within ``camera_tolerance_m``, and puts
  no more of its volume where the camera saw empty space (``seen_empty_tolerance``): a pose
  moves the decoder's own carving with the shape.
  Otherwise the mean stays (nothing gets worse), and the candidate goes on to predict the next
  touch.

The first touch has no held-out prediction (the candidate before it is vision itself), so the
global step starts at the second. The fused correction is then applied on whichever mean holds.
Frames: the latent decodes on the estimate's grid (``base_grid``); the pose moves that grid
(``posed_grid``); observations and distances are world metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from numpy.typing import NDArray
from scipy.special import ndtr

from models.geometry import VoxelGrid
from models.touch.constraints import TouchResult, VoxelConstraints, constraints_from_touches
from models.touch.observations import SurfaceObservations, observations_of
from models.touch.posed_prior import Pose, SignedDistanceGrid, fit_pose, posed_grid
from models.touch.refinement import Decode, refine_latent

CAMERA_SOURCE = -1
"""``SurfaceObservations.surface_source`` of the camera's depth points."""


@dataclass(frozen=True)
class GlobalSettings:
    """How the latent and pose are fitted, and how much better a held-out touch must be
    predicted for a step to be taken."""

    rounds: int = 1
    """Alternations of pose fit and latent refinement per touch."""
    pose_fit: bool = False
    """Fit the pose (translation on the table, yaw, scale) too. Off: on 10 real meshes from RGB
    the pose fit took shape errors for pose (the dino 20.6 -> 32.2 mm, the teddy bear 24.1 ->
    42.9; the latent alone 19.2 and 21.3; docs/touch.md)."""
    learning_rate: float = 0.01
    iterations: int = 15
    """Adam steps on the latent per round (at most: see ``patience``)."""
    patience: int | None = None
    """Stop a round once this many steps in a row have not improved on its best fit, and keep
    that best (``refine_latent``); None: every step, the last fit (the default: faster, the
    early stop lowered the shapes a little; docs/touch.md, "Cost")."""
    anchor_weight: float = 0.03
    """Pull of the latent towards vision's (as the "prior" update)."""
    margin_m: float = 0.0002
    """A step needs its predecessor to predict the held-out touch this much better than vision
    (metres of mean error): below it the two are a tie, and a tie keeps the mean."""
    camera_constraints: bool = True
    """Whether the camera's depth points constrain the latent (as occupied voxels behind them)."""
    camera_tolerance_m: float = 0.0005
    """How much farther (mean) from the camera's depth points a step may put the surface."""
    seen_empty_tolerance: float = 0.02
    """How much more of its volume a step may put where the camera saw empty space (fraction)."""


@dataclass(frozen=True)
class ShapeMean:
    """A shape of the prior: its latent, its decoded occupancy and signed distance on the
    unposed ``base_grid``, and the pose that moves that grid onto the object."""

    latent: torch.Tensor
    probabilities: NDArray[np.float32]
    distance: SignedDistanceGrid
    pose: Pose = field(default_factory=Pose)

    @classmethod
    def of(cls, latent: torch.Tensor, probabilities: NDArray, grid: VoxelGrid) -> ShapeMean:
        volume = np.asarray(probabilities, dtype=np.float32)
        return cls(latent, volume, SignedDistanceGrid.from_probabilities(volume, grid))

    def posed_distance(self) -> SignedDistanceGrid:
        """The signed distance (metres) of the posed shape, in the world."""
        return self.distance.moved_to(posed_grid(self.distance.grid, self.pose))


@dataclass(frozen=True)
class GuardDecision:
    """One touch's verdict: the held-out touch's prediction error (metres) of vision's shape,
    of the mean in use and of the fit that had not seen it, how the new fit moved the surface
    from the camera's points, and whether the step was taken."""

    touch: int
    vision_error_m: float
    mean_error_m: float
    candidate_error_m: float
    camera_error_change_m: float
    """The new fit's mean distance to the camera's depth points minus vision's (0: no depth)."""
    seen_empty_change: float
    """The new fit's fraction of volume in space seen empty minus vision's."""
    pose: Pose
    """The new fit's pose."""
    taken: bool

    def summary(self) -> str:
        verdict = "taken" if self.taken else "refused"
        return (
            f"global step after touch {self.touch + 1} {verdict}: held-out touch predicted to "
            f"{1000 * self.candidate_error_m:.2f} mm (vision {1000 * self.vision_error_m:.2f}, "
            f"mean {1000 * self.mean_error_m:.2f}); camera points "
            f"{1000 * self.camera_error_change_m:+.2f} mm; volume seen empty "
            f"{100 * self.seen_empty_change:+.1f} %; fit's pose {self.pose.summary()}"
        )


@dataclass(frozen=True)
class GlobalState:
    """What the global step carries from touch to touch."""

    vision: ShapeMean
    """Vision's shape: the baseline a step must beat."""
    mean: ShapeMean
    """The mean the fused correction is applied on."""
    candidate: ShapeMean
    """The fit to every touch so far: it predicts the next touch."""
    decisions: tuple[GuardDecision, ...] = field(default_factory=tuple)

    @classmethod
    def start(cls, vision: ShapeMean) -> GlobalState:
        return cls(vision, vision, vision)

    @property
    def steps_taken(self) -> int:
        return sum(d.taken for d in self.decisions)

    @property
    def steps_refused(self) -> int:
        return sum(not d.taken for d in self.decisions)


def camera_constraints(camera: SurfaceObservations, grid: VoxelGrid) -> VoxelConstraints:
    """The camera's depth points as occupied voxels: the voxel holding the point sqrt(3)/2 voxel
    behind it (against its outward normal), whose centre lies inside the object (as for a
    contact: docs/touch.md). Space in front of them is carved already (``seen_empty``)."""
    points = camera.surface_points_world[camera.surface_source == CAMERA_SOURCE]
    normals = camera.surface_normals_world[camera.surface_source == CAMERA_SOURCE]
    if len(points) == 0:
        return VoxelConstraints.none(grid.resolution)
    behind = points - normals * (math.sqrt(3) / 2 * grid.voxel_size_m)
    ijk, inside = grid.voxel_index(behind)
    return VoxelConstraints.from_voxels(grid.resolution, np.zeros((0, 3)), ijk[inside])


def fit_mean(
    decode: Decode,
    start: ShapeMean,
    anchor_latent: torch.Tensor | None,
    touches: list[TouchResult],
    observations: SurfaceObservations,
    settings: GlobalSettings = GlobalSettings(),
) -> ShapeMean:
    """The latent and pose fitted to ``touches`` (their voxel constraints, in the posed grid)
    and to ``observations`` (the touches' and the camera's points: the pose fit), alternating
    from ``start``."""
    grid = start.distance.grid
    latent, pose, distance = start.latent, start.pose, start.distance
    probabilities = start.probabilities
    for round_index in range(settings.rounds):
        if settings.pose_fit:
            if round_index > 0:
                distance = SignedDistanceGrid.from_probabilities(probabilities, grid)
            # The pose answers to the touches alone: the camera's points cover the visible
            # side, where the fused correction follows them anyway, and fitted to them the pose
            # took the prior's shape errors there for pose (the mug's seen front made it 8 %
            # larger, its back too far).
            pose = fit_pose(distance, grid, observations_of(touches), pose)
        posed = posed_grid(grid, pose)
        constraints = constraints_from_touches(touches, posed)
        if settings.camera_constraints:
            constraints = constraints.merged(camera_constraints(observations, posed))
        result = refine_latent(
            decode,
            latent,
            constraints,
            learning_rate=settings.learning_rate,
            iterations=settings.iterations,
            loss="threshold",
            anchor_latent=anchor_latent,
            anchor_weight=settings.anchor_weight if anchor_latent is not None else 0.0,
            patience=settings.patience,
        )
        latent, probabilities = result.latent, result.voxels.numpy()
    return replace(ShapeMean.of(latent, probabilities, grid), pose=pose)


def prediction_error_m(distance: SignedDistanceGrid, touch: SurfaceObservations) -> float:
    """How far a shape (its posed signed distance, metres) is from what one touch measured:
    the mean |distance| at its contact points plus the mean depth inside the shape of the
    points its rays swept free. A touch with no contact is judged by its free points alone."""
    error = 0.0
    if len(touch.surface_points_world):
        error += float(np.mean(np.abs(distance(touch.surface_points_world))))
    if len(touch.free_points_world):
        error += float(np.mean(np.maximum(-distance(touch.free_points_world), 0.0)))
    return error


def stop_error_m(distance: SignedDistanceGrid, touch: TouchResult) -> float:
    """How far a shape stays from a stop by force without an imprint: the object reaches one
    of the tool's points there (``TouchResult.stop_points_world``), so the distance outside the
    shape of the nearest of them (0 for any other touch)."""
    if len(touch.stop_points_world) == 0:
        return 0.0
    return max(float(np.min(distance(touch.stop_points_world))), 0.0)


def held_out_error_m(distance: SignedDistanceGrid, touch: TouchResult, index: int) -> float:
    """How far a shape is from what touch ``index`` measured (:func:`prediction_error_m` and
    :func:`stop_error_m`)."""
    observed = SurfaceObservations.from_touch(touch, index)
    return prediction_error_m(distance, observed) + stop_error_m(distance, touch)


def seen_empty_fraction(mean: ShapeMean, seen_empty: NDArray[np.bool_] | None) -> float:
    """The fraction of a posed shape's occupied voxels whose centres lie where the camera saw
    empty space (``seen_empty`` on the unposed grid, which is vision's and fixed in the world).
    The decoder caps seen-empty voxels in its own grid, which a pose moves: this is the check
    in the world."""
    if seen_empty is None:
        return 0.0
    occupied = np.argwhere(mean.probabilities >= 0.5)
    if len(occupied) == 0:
        return 0.0
    grid = mean.distance.grid
    ijk, inside = grid.voxel_index(posed_grid(grid, mean.pose).voxel_to_world(occupied + 0.5))
    outside_grid = int(np.sum(~inside))
    hits = int(np.sum(seen_empty[tuple(ijk[inside].T)]))
    return (hits + outside_grid) / len(occupied)


def camera_error_m(distance: SignedDistanceGrid, observations: SurfaceObservations) -> float:
    """The mean |distance| (metres) of a shape at the camera's depth points (0 without)."""
    camera = observations.surface_points_world[observations.surface_source == CAMERA_SOURCE]
    return float(np.mean(np.abs(distance(camera)))) if len(camera) else 0.0


def global_step(
    state: GlobalState,
    decode: Decode,
    anchor_latent: torch.Tensor | None,
    touches: list[TouchResult],
    observations: SurfaceObservations,
    settings: GlobalSettings = GlobalSettings(),
    seen_empty: NDArray[np.bool_] | None = None,
) -> GlobalState:
    """After the newest of ``touches``: fit the candidate to all of them, and take it as the
    mean if the previous candidate (which had not seen the newest touch) predicted that touch
    better than the mean in use. ``observations`` hold every touch's and the camera's points;
    ``seen_empty`` the voxels of the unposed grid the camera saw empty."""
    candidate = fit_mean(decode, state.candidate, anchor_latent, touches, observations, settings)
    if len(touches) < 2:
        # The candidate before the first touch is vision itself: nothing was held out.
        return GlobalState(state.vision, state.mean, candidate, state.decisions)
    newest, index = touches[-1], len(touches) - 1
    vision_error = held_out_error_m(state.vision.posed_distance(), newest, index)
    mean_error = held_out_error_m(state.mean.posed_distance(), newest, index)
    candidate_error = held_out_error_m(state.candidate.posed_distance(), newest, index)
    camera_change = camera_error_m(candidate.posed_distance(), observations) - camera_error_m(
        state.vision.posed_distance(), observations
    )
    empty_change = seen_empty_fraction(candidate, seen_empty) - seen_empty_fraction(
        state.vision, seen_empty
    )
    taken = (
        candidate_error < vision_error - settings.margin_m
        and candidate_error <= mean_error
        and camera_change <= settings.camera_tolerance_m
        and empty_change <= settings.seen_empty_tolerance
    )
    decision = GuardDecision(
        len(touches) - 1,
        vision_error,
        mean_error,
        candidate_error,
        camera_change,
        empty_change,
        candidate.pose,
        taken,
    )
    mean = candidate if taken else state.mean
    return GlobalState(state.vision, mean, candidate, (*state.decisions, decision))


def committee_probabilities(
    state: GlobalState, probabilities: NDArray[np.float32], grid: VoxelGrid, std_m: float
) -> NDArray[np.float32]:
    """What the active policy reads when the fit to every touch (the candidate) is not the mean:
    the mean of ``probabilities`` (the estimate's P(inside) on ``grid``) and the candidate's
    own, Phi(-d / ``std_m``) of its posed signed distance d, cut by the table. Where the two
    disagree the mixture is near 0.5, so the least confident window is where the next touch
    tells them apart: the touch the guard's held-out test needs (query by committee). Where
    the candidate is the mean, ``probabilities`` unchanged."""
    if state.candidate is state.mean:
        return probabilities
    centres = grid.voxel_centres_world()
    distance = np.maximum(state.candidate.posed_distance().at_voxel_centres(grid), -centres[..., 2])
    candidate = ndtr(-distance / std_m)
    return (0.5 * (probabilities + candidate)).astype(np.float32)
