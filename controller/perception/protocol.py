"""What the controller needs from perception, as a protocol: reconstruct a shape from an image,
choose a touch, interpret a touch, refine the shape. ``controller.perception.learned`` implements
it with the shape prior, the GelSight reconstruction, the touch constraints and the policy."""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import trimesh
from numpy.typing import NDArray

from controller.request import ExploreRequest
from drivers.base import RGBDFrame, TactileFrame
from models.geometry import VoxelGrid
from models.touch.fused import prior_surface
from models.touch.observations import SurfaceObservations
from models.touch.policy import TargetFilter

FloatArray = NDArray[np.float64]


@dataclass
class ShapeEstimate:
    """Occupancy probabilities on a voxel grid, indexed [i, j, k] (see docs/conventions.md),
    and what produced them. The grid is the registered one or, for a prior of the object frame,
    the one fitted to the object in this session's image."""

    grid: VoxelGrid
    probabilities: NDArray[np.float32]
    latent: Any | None = None
    """The prior's latent code (a torch tensor) when a prior made this estimate."""
    prior: str = ""
    """The prior that made the estimate: its decoder refines it (``auto`` chose it)."""
    sketches: dict[str, NDArray] = field(default_factory=dict)
    vision_probabilities: NDArray[np.float32] | None = None
    """The estimate from vision alone (what Direct Edit edits)."""
    vision_latent: Any | None = None
    """The prior's latent code from vision alone (what the refinement stays near)."""
    camera_observations: SurfaceObservations = field(default_factory=SurfaceObservations.none)
    """The camera's depth points of the visible side (RGB-D input), fused like touches."""
    fused: Any | None = None
    """The fused shape (``models.touch.fused.FusedShape``) when the fused update made this
    estimate: ``probabilities`` are then its P(inside) at the voxel centres."""
    seen_empty: NDArray[np.bool_] | None = None
    """Voxels of ``grid`` the camera saw empty (``models.prior.carving``): no update fills them."""
    input: str = "rgb"
    """What vision used: "rgb" or "rgbd" (an ``auto`` request resolved by the frame)."""
    global_state: Any | None = None
    """The global update's mean, candidate and guard verdicts
    (``models.touch.global_fit.GlobalState``) when that update made this estimate."""
    _surface: trimesh.Trimesh | None = field(default=None, init=False, repr=False, compare=False)
    _surface_lock: threading.Lock = field(
        default_factory=threading.Lock, init=False, repr=False, compare=False
    )

    def surface_mesh(self) -> trimesh.Trimesh:
        """The estimate's surface (world metres), extracted at ``EXTRACTION_SPACING_M``: the
        fused field's, or the voxel estimate's through the same extraction, so estimates of
        every update compare like with like. Extracted once (~1 s): the recording, the score
        and the artifacts share it; an estimate is not changed once made."""
        with self._surface_lock:  # the recording and the score ask for it from two threads
            if self._surface is None:
                fused = self.fused
                self._surface = (
                    fused.mesh()
                    if fused is not None
                    else prior_surface(self.probabilities, self.grid)
                )
            return self._surface

    def occupied_points_world(self, threshold: float = 0.5) -> FloatArray:
        """Centres of the voxels whose probability is above ``threshold`` (world, metres)."""
        occupied = np.argwhere(self.probabilities > threshold)
        return self.grid.voxel_to_world(occupied + 0.5)


@dataclass(frozen=True)
class TouchTarget:
    """A chosen touch: the point on the (predicted) surface and the approach direction."""

    target_world: FloatArray
    direction_world: FloatArray
    score: float = 0.0
    uncertainty: float = 1.0
    """The policy's uncertainty about the touched window, 0 (certain) to 1 (every probe at
    v = 0.5); 1 when the policy does not measure it (random)."""
    roll_rad: float = 0.0
    """The tool's roll about the approach line to try first (``controller.targets.
    window_leading_roll``: where the estimate leaves the housing and fingers clearest)."""


RobotSeconds = Callable[[TouchTarget], "float | None"]
"""A touch's robot time from where the arm is (transit, approach, press, retract; seconds), or
None when the planner refuses it (``MotionPlanner.touch_seconds``)."""


@dataclass(frozen=True)
class TouchMeasurement:
    """What the robot measured on one touch, before interpretation."""

    target: TouchTarget
    contact: bool
    tactile: TactileFrame
    reference: TactileFrame
    pose_world_pad: FloatArray
    """Pad pose when the fingers stopped (contact) or at the end of their stroke (miss)."""
    pad_start_world: FloatArray
    """Pad centre where the approach began: the swept segment starts here."""
    force_n: float
    gripper_width_m: float | None = None
    """The fingers' opening where they stopped (where the other finger was); None where not
    known, and then a stop without an imprint is taken as its sweep alone."""


@dataclass
class TouchOutcome:
    """An interpreted touch: contact points on the object or a swept empty segment."""

    measurement: TouchMeasurement
    contact_points_world: FloatArray
    height_map_mm: NDArray[np.float32] | None
    touch: Any
    """What the touch says of space, in the world frame and independent of any voxel grid
    (``models.touch.constraints.TouchResult``: rays ending on contact points or swept free);
    None when the perception keeps nothing."""

    @property
    def contact_point_world(self) -> FloatArray | None:
        points = self.contact_points_world
        return points.mean(axis=0) if len(points) else None


def contact_counts(outcomes: Sequence[TouchOutcome]) -> dict[str, int]:
    """How many touches met the object (the gripper stalled), and how many of those left no
    imprint on the gel: a rigid part of the tool (the gel window's frame, the finger) met
    the object first, so the touch gives free space but no contact points."""
    contacts = [o for o in outcomes if o.measurement.contact]
    return {
        "contacts": len(contacts),
        "contacts_without_imprint": sum(len(o.contact_points_world) == 0 for o in contacts),
    }


class Perception(Protocol):
    def prior_names(self) -> frozenset[str]:
        """The shape priors ``reconstruct`` accepts (``request.prior``): requests naming
        another are refused before a session starts."""
        ...

    def reconstruct(self, frame: RGBDFrame, request: ExploreRequest) -> ShapeEstimate: ...

    def select(
        self,
        estimate: ShapeEstimate,
        request: ExploreRequest,
        outcomes: list[TouchOutcome],
        allowed: Callable[[TouchTarget], bool],
        feasible: TargetFilter | None = None,
        robot_seconds: RobotSeconds | None = None,
    ) -> TouchTarget | None:
        """The next touch among those ``allowed`` accepts; None when nothing is worth touching.
        ``feasible`` (vectorised, cheap) narrows the candidates first: a policy that searches
        many windows uses it to pick among those that pass. ``robot_seconds`` (the planner's)
        is what a touch would cost the robot, for a policy that weighs it."""
        ...

    def interpret(self, measurement: TouchMeasurement) -> TouchOutcome: ...

    def refine(
        self, estimate: ShapeEstimate, outcomes: list[TouchOutcome], request: ExploreRequest
    ) -> ShapeEstimate: ...
