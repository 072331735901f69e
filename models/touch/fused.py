"""The fused shape: the prior's surface, posed by a similarity fit and bent through every tactile
measurement by a Gaussian-process correction with the prior as its mean (a Gaussian-process
implicit surface, as ShapeMap 3-D fuses GelSight and depth: Suresh et al., ICRA 2022).

The field is a signed distance in metres (> 0 outside):

    f(x) = d_prior(x) + c(x)

* ``d_prior`` is the distance to the prior's 0.5 surface (:class:`SignedDistanceGrid`: exact
  distances to the marching-cubes surface at the voxel centres, trilinear between them), on the
  prior's grid moved by the pose fit (:func:`fit_pose`: translation on the table, yaw, scale);
* ``c`` is the posterior mean of a zero-mean Gaussian process fitted to the residuals of the
  observations (``models.touch.observations``): contact points and the camera's depth points
  lie on the surface (f = 0), free points that the field would put inside are held just
  outside (an active set), and optionally points along the contacts' normals at f = +-offset.
  Its kernel is Wendland's compactly supported C2 function, so the correction is exactly zero
  beyond ``support_m`` from every observation: there the field is the prior's.

The posterior standard deviation ``s`` of the correction says how well the surface is known;
``P(inside) = Phi(-f / s)`` turns the field into the occupancy probabilities the rest of the
system (policy, safety bound, ``voxels.npz``) reads. See docs/touch.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import trimesh
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import cho_factor, cho_solve, solve_triangular
from scipy.ndimage import binary_dilation, map_coordinates
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist
from scipy.special import ndtr
from skimage.measure import marching_cubes

from models.geometry import VoxelGrid
from models.touch.observations import SurfaceObservations, thin_to_lattice
from models.touch.posed_prior import Pose, SignedDistanceGrid, fit_pose, posed_grid

FloatArray = NDArray[np.float64]

EXTRACTION_SPACING_M = 0.0015
"""The output mesh's lattice spacing: finer than the sensor's patch detail needs, and it lifts
the 64^3 grid's 4 mm floor (docs/explore.md)."""
_EXACT_NEAR_M = 0.005
"""The extraction evaluates the correction exactly this close to an observation."""


# --- the correction -------------------------------------------------------------------------------


@dataclass(frozen=True)
class FusionSettings:
    """The Gaussian process's kernel and noise (metres)."""

    support_m: float = 0.035
    """Wendland kernel radius: the correction is zero beyond it from every observation."""
    prior_std_m: float = 0.004
    """Standard deviation of the correction before any touch: how far the prior's surface may be
    off, and the field's uncertainty far from touches."""
    surface_noise_m: float = 0.0002
    camera_noise_m: float = 0.0015
    """The depth camera's points (RGB-D input): Kinect v2 noise at 0.6-0.8 m."""
    symmetry_noise_m: float = 0.004
    """Points a symmetry completed (``models.symmetry``): a guess about the unseen side, held
    loosely (a real object is symmetric only roughly)."""
    normal_offset_m: float = 0.0
    """Points this far along each contact's normal, outside and inside, held at +-offset so the
    field's gradient follows the measured normals; 0: none (a patch's dense points already
    orient the surface, and at edges the patch normals misled it: docs/touch.md)."""
    normal_noise_m: float = 0.0005
    free_target_m: float = 0.0005
    free_noise_m: float = 0.0005
    surface_spacing_m: float = 0.002
    """Surface points are thinned to this lattice for the process (the cost is cubic in them)."""
    variance_spacing_m: float = 0.004
    """The standard deviation conditions on surface points thinned to this lattice (cheaper, a
    slight over-estimate)."""
    free_rounds: int = 3
    pose_fit: bool = False


def wendland(distance_m: ArrayLike, support_m: float) -> FloatArray:
    """Wendland's C2 function (positive definite in 3-D): (1 - r)^4 (4 r + 1) for r < 1."""
    r = np.minimum(np.asarray(distance_m, dtype=float) / support_m, 1.0)
    fourth = (1.0 - r) ** 2
    fourth *= fourth  # squared twice: numpy's ** 4 calls pow per element, 3x slower
    return fourth * (4.0 * r + 1.0)


def _cross_kernel(a: FloatArray, b: FloatArray, support_m: float) -> FloatArray:
    """k(a_i, b_j) without the variance factor, (len(a), len(b))."""
    return wendland(cdist(a, b), support_m)


@dataclass
class Correction:
    """A fitted Gaussian-process correction: ``mean(x) = k(x, X) alpha``."""

    points_world: FloatArray
    alpha: FloatArray
    variance_points_world: FloatArray
    variance_whitening: FloatArray
    """prior_std^2 L^-1, L the lower Cholesky factor of the variance points' kernel matrix: the
    deviation at x is then sqrt(prior_std^2 - |W k(x)|^2), a matrix product instead of a
    triangular solve per evaluation (2.5x faster; the same to 1e-19 m^2)."""
    settings: FusionSettings
    residuals_m: FloatArray
    """The residuals it was fitted to (observed minus prior field)."""
    touched_world: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    """The touches' surface points it passes through (the extraction is exact near them)."""
    _tree: cKDTree | None = field(default=None, repr=False)

    @property
    def is_empty(self) -> bool:
        return len(self.points_world) == 0

    @property
    def largest_m(self) -> float:
        """How large the correction gets: 1.5 x its largest residual (an interpolant of
        residuals this smooth overshoots them by far less)."""
        return 1.5 * float(np.abs(self.residuals_m).max()) if len(self.residuals_m) else 0.0

    def near(self, points_world: FloatArray) -> NDArray[np.bool_]:
        """Points within the kernel's support of some observation (elsewhere c = 0, s = prior)."""
        if self.is_empty:
            return np.zeros(len(points_world), bool)
        if self._tree is None:
            self._tree = cKDTree(self.points_world)
        distance, _ = self._tree.query(points_world, distance_upper_bound=self.settings.support_m)
        return np.isfinite(distance)

    def mean(self, points_world: ArrayLike) -> FloatArray:
        points = np.asarray(points_world, dtype=float).reshape(-1, 3)
        if self.is_empty or len(points) == 0:
            return np.zeros(len(points))
        if self._tree is None:
            self._tree = cKDTree(self.points_world)
        # Only the pairs within the kernel's support (it is zero beyond).
        support = self.settings.support_m
        pairs = cKDTree(points).sparse_distance_matrix(self._tree, support, output_type="ndarray")
        weights = wendland(pairs["v"], support) * self.alpha[pairs["j"]]
        return self.settings.prior_std_m**2 * np.bincount(
            pairs["i"], weights=weights, minlength=len(points)
        )

    def std(self, points_world: ArrayLike) -> FloatArray:
        points = np.asarray(points_world, dtype=float).reshape(-1, 3)
        prior_std = self.settings.prior_std_m
        out = np.full(len(points), prior_std)
        if len(self.variance_points_world) == 0:
            return out
        near = self.near(points)
        if near.any():
            k = _cross_kernel(self.variance_points_world, points[near], self.settings.support_m)
            v = self.variance_whitening @ k
            variance = prior_std**2 - np.einsum("ij,ij->j", v, v)
            out[near] = np.sqrt(np.maximum(variance, 0.0))
        return out


@dataclass(frozen=True)
class _GramFactor:
    """The lower Cholesky factor of the observations' kernel matrix (noise on its diagonal).
    A round of free points extends it by their rows (a block update, O(n^2 m)) instead of
    factoring the grown matrix again (O((n + m)^3))."""

    points_world: FloatArray
    lower: FloatArray

    @classmethod
    def of(cls, points: FloatArray, noise_m: FloatArray, settings: FusionSettings) -> _GramFactor:
        gram = settings.prior_std_m**2 * _cross_kernel(points, points, settings.support_m)
        gram[np.diag_indices_from(gram)] += noise_m**2
        return cls(points, cho_factor(gram, lower=True)[0] if len(points) else gram)

    def extended(
        self, points: FloatArray, noise_m: FloatArray, settings: FusionSettings
    ) -> _GramFactor:
        if len(self.points_world) == 0:
            return _GramFactor.of(points, noise_m, settings)
        variance, n = settings.prior_std_m**2, len(self.points_world)
        across = variance * _cross_kernel(self.points_world, points, settings.support_m)
        below = solve_triangular(self.lower, across, lower=True, check_finite=False)
        corner = variance * _cross_kernel(points, points, settings.support_m) - below.T @ below
        corner[np.diag_indices_from(corner)] += noise_m**2
        lower = np.zeros((n + len(points), n + len(points)))
        lower[:n, :n] = np.tril(self.lower)
        lower[n:, :n] = below.T
        lower[n:, n:] = np.linalg.cholesky(corner)
        return _GramFactor(np.concatenate([self.points_world, points]), lower)

    def solve(self, residuals: FloatArray) -> FloatArray:
        return cho_solve((self.lower, True), residuals, check_finite=False)


def fit_correction(
    prior: SignedDistanceGrid, observations: SurfaceObservations, settings: FusionSettings
) -> Correction:
    """The process's posterior given the observations, around the prior's signed distance."""
    touched = observations.surface_source >= 0
    surface = observations.surface_points_world[touched]
    keep = thin_to_lattice(surface, settings.surface_spacing_m)
    surface, normals = surface[keep], observations.surface_normals_world[touched][keep]
    # The camera's points (source -1): on the surface, within the depth noise; the points a
    # symmetry completed (source -2) more loosely. Their normals are too rough for offsets.
    source = observations.surface_source
    seen = observations.surface_points_world[source == -1]
    mirrored = observations.surface_points_world[source < -1]
    offset = settings.normal_offset_m
    offsets = (offset, -offset) if offset > 0 else ()
    points = np.concatenate([surface, *(surface + o * normals for o in offsets), seen, mirrored])
    targets = np.concatenate(
        [
            np.zeros(len(surface)),
            *(np.full(len(surface), o) for o in offsets),
            np.zeros(len(seen) + len(mirrored)),
        ]
    )
    noise = np.concatenate(
        [
            np.full(len(surface), settings.surface_noise_m),
            np.full(len(offsets) * len(surface), settings.normal_noise_m),
            np.full(len(seen), settings.camera_noise_m),
            np.full(len(mirrored), settings.symmetry_noise_m),
        ]
    )
    # The standard deviation conditions on the surface points only, thinned (see settings).
    # The camera's (noisier, denser) points thinner still: the deviation near them stays at
    # about the camera's noise whatever their spacing below the kernel's reach.
    spacing = settings.variance_spacing_m
    touch_anchors = surface[thin_to_lattice(surface, spacing)]
    seen_anchors = seen[thin_to_lattice(seen, 3 * spacing)]
    mirrored_anchors = mirrored[thin_to_lattice(mirrored, 3 * spacing)]
    variance = _VarianceAnchors.factored(
        np.concatenate([touch_anchors, seen_anchors, mirrored_anchors]),
        np.concatenate(
            [
                np.full(len(touch_anchors), settings.surface_noise_m),
                np.full(len(seen_anchors), settings.camera_noise_m),
                np.full(len(mirrored_anchors), settings.symmetry_noise_m),
            ]
        ),
        settings,
    )
    residuals = targets - prior(points) if len(points) else targets
    factor = _GramFactor.of(points, noise, settings)
    correction = _correction(factor, residuals, variance, settings)
    free = observations.free_points_world
    prior_free = prior(free) if len(free) else np.zeros(0)
    # Free points farther outside the prior than the correction reaches stay outside.
    close = prior_free < correction.largest_m + settings.free_target_m
    free, prior_free = free[close], prior_free[close]
    held = np.zeros(len(free), bool)
    for _ in range(settings.free_rounds if len(free) else 0):
        # Free points the field puts inside (or on) the surface: hold them just outside.
        inside = (prior_free + correction.mean(free) < settings.free_target_m * 0.5) & ~held
        if not inside.any():
            break
        added = np.flatnonzero(inside)
        added = added[thin_to_lattice(free[added], settings.surface_spacing_m)]
        held[added] = True
        factor = factor.extended(free[added], np.full(len(added), settings.free_noise_m), settings)
        residuals = np.concatenate([residuals, settings.free_target_m - prior_free[added]])
        correction = _correction(factor, residuals, variance, settings)
    return replace(correction, touched_world=surface)


@dataclass(frozen=True)
class _VarianceAnchors:
    """The points the standard deviation conditions on, with their kernel matrix's whitening
    (``Correction.variance_whitening``): the same for every round of free points, so factored
    once."""

    points_world: FloatArray
    whitening: FloatArray

    @classmethod
    def factored(
        cls, points_world: FloatArray, noise_m: FloatArray, settings: FusionSettings
    ) -> _VarianceAnchors:
        gram = settings.prior_std_m**2 * _cross_kernel(
            points_world, points_world, settings.support_m
        )
        gram[np.diag_indices_from(gram)] += noise_m**2
        if len(gram) == 0:
            return cls(points_world, np.zeros((0, 0)))
        lower = np.linalg.cholesky(gram)
        inverse = solve_triangular(lower, np.eye(len(gram)), lower=True, check_finite=False)
        return cls(points_world, settings.prior_std_m**2 * inverse)


def _correction(
    factor: _GramFactor,
    residuals: FloatArray,
    anchors: _VarianceAnchors,
    settings: FusionSettings,
) -> Correction:
    points = factor.points_world
    if len(points) == 0:
        return Correction(
            np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)), np.zeros((0, 0)), settings, np.zeros(0)
        )
    alpha = factor.solve(residuals)
    return Correction(points, alpha, anchors.points_world, anchors.whitening, settings, residuals)


# --- the fused shape ------------------------------------------------------------------------------


@dataclass
class FusedShape:
    """The prior's signed distance (posed) plus the touches' correction; world metres."""

    prior: SignedDistanceGrid
    correction: Correction
    pose: Pose = Pose()

    @classmethod
    def from_prior(
        cls,
        probabilities: ArrayLike,
        prior_grid: VoxelGrid,
        observations: SurfaceObservations | None = None,
        settings: FusionSettings = FusionSettings(),
        start_pose: Pose = Pose(),
    ) -> FusedShape:
        """Fuse ``observations`` into the prior's estimate (``probabilities`` on ``prior_grid``):
        pose fit first (when enabled), then the correction around the posed prior."""
        prior = SignedDistanceGrid.from_probabilities(probabilities, prior_grid)
        return cls.from_distance(prior, observations, settings, start_pose)

    @classmethod
    def from_distance(
        cls,
        prior: SignedDistanceGrid,
        observations: SurfaceObservations | None = None,
        settings: FusionSettings = FusionSettings(),
        start_pose: Pose = Pose(),
    ) -> FusedShape:
        """:meth:`from_prior` from the prior's distance already computed (on its unposed grid):
        while the prior's shape stays the same, touches only refit the pose and correction."""
        observations = observations or SurfaceObservations.none()
        pose = start_pose
        if settings.pose_fit and len(observations.surface_points_world):
            pose = fit_pose(prior, prior.grid, observations, start_pose)
        posed = prior.moved_to(posed_grid(prior.grid, pose))
        return cls(posed, fit_correction(posed, observations, settings), pose)

    def sdf(self, points_world: ArrayLike) -> FloatArray:
        """The field (metres, > 0 outside), cut by the table: nothing lies below z = 0."""
        points = np.asarray(points_world, dtype=float)
        flat = points.reshape(-1, 3)
        field = self.prior(flat) + self.correction.mean(flat)
        return np.maximum(field, -flat[:, 2]).reshape(points.shape[:-1])

    def std(self, points_world: ArrayLike) -> FloatArray:
        points = np.asarray(points_world, dtype=float)
        return self.correction.std(points.reshape(-1, 3)).reshape(points.shape[:-1])

    def probabilities(
        self, grid: VoxelGrid, std_floor_m: float = 0.0003, *, use_variance: bool = True
    ) -> NDArray[np.float32]:
        """P(inside) = Phi(-f / s) at ``grid``'s voxel centres, (N, N, N); without
        ``use_variance``, s is the prior's deviation everywhere (touched or not). The
        correction and its deviation vary over the kernel's support (centimetres): they are
        evaluated on every other voxel centre and interpolated, and exactly within
        ``_EXACT_NEAR_M`` of the touches' points (where they follow the measured detail)."""
        n = grid.resolution
        centres = grid.voxel_centres_world()
        prior_values = self.prior.at_voxel_centres(grid)
        prior_field = np.maximum(prior_values, -centres[..., 2])
        prior_std = self.correction.settings.prior_std_m
        # Only near the surface can the correction change the sign or the probability: farther
        # than its largest value plus 4 prior deviations, P(inside) is 0 or 1 whatever it adds.
        band = np.abs(prior_field) < self.correction.largest_m + 4 * prior_std
        correction = np.zeros((n, n, n))
        std = np.full((n, n, n), prior_std)
        if band.any() and not self.correction.is_empty:
            lattice = np.unique(np.r_[np.arange(0, n, 2), n - 1])
            coarse_index = np.ix_(lattice, lattice, lattice)
            # Every coarse centre next to a band voxel is evaluated (the band grown by 2).
            wanted = binary_dilation(band, iterations=2)[coarse_index]
            coarse_points = centres[coarse_index][wanted]
            coarse_mean = np.zeros(wanted.shape)
            coarse_mean[wanted] = self.correction.mean(coarse_points)
            coarse_std = np.full(wanted.shape, prior_std)
            if use_variance:
                coarse_std[wanted] = self.correction.std(coarse_points)
            position = np.interp(np.arange(n), lattice, np.arange(len(lattice)))
            where = np.stack(np.meshgrid(position, position, position, indexing="ij"))[:, band]
            correction[band] = map_coordinates(coarse_mean, where, order=1)
            std[band] = map_coordinates(coarse_std, where, order=1)
            touched = self.correction.touched_world
            if len(touched):
                distance, _ = cKDTree(touched).query(
                    centres[band], distance_upper_bound=_EXACT_NEAR_M
                )
                exact = np.flatnonzero(band)[np.isfinite(distance)]
                exact_points = centres.reshape(-1, 3)[exact]
                correction.reshape(-1)[exact] = self.correction.mean(exact_points)
                if use_variance:
                    std.reshape(-1)[exact] = self.correction.std(exact_points)
        field = np.maximum(prior_values + correction, -centres[..., 2])
        field = np.where(band, field, prior_field)
        if not use_variance:
            std[:] = prior_std
        inside = ndtr(-field / np.hypot(std, std_floor_m))
        return inside.astype(np.float32)

    def mesh(self, spacing_m: float = EXTRACTION_SPACING_M) -> trimesh.Trimesh:
        """The zero surface, marching cubes on a ``spacing_m`` lattice around the object."""
        return extract_surface(self, spacing_m)


def _object_box(shape: FusedShape, margin_m: float) -> tuple[FloatArray, FloatArray] | None:
    """World box around the prior's inside voxels and the observations, plus a margin."""
    prior = shape.prior
    inside = np.argwhere(prior.values_voxels < 0.5)
    if len(inside) == 0 and shape.correction.is_empty:
        return None
    corners = [prior.grid.voxel_to_world(inside), prior.grid.voxel_to_world(inside + 1.0)]
    corners.append(shape.correction.points_world)
    points = np.concatenate([c for c in corners if len(c)])
    return points.min(axis=0) - margin_m, points.max(axis=0) + margin_m


def extract_surface(shape: FusedShape, spacing_m: float = EXTRACTION_SPACING_M) -> trimesh.Trimesh:
    """Marching cubes of the field at 0 on a world-axis lattice of ``spacing_m`` around the
    object; outward normals. The prior's distance is evaluated on the lattice; the correction
    exactly within ``_EXACT_NEAR_M`` of the touches' surface points (where it follows the
    measured surface's detail) and elsewhere on a lattice 3x coarser, interpolated (there it
    varies over the kernel's support, centimetres)."""
    box = _object_box(shape, 3 * spacing_m + 3 * shape.correction.settings.prior_std_m)
    if box is None:
        return trimesh.Trimesh()
    low, high = box
    counts = np.ceil((high - low) / spacing_m).astype(int) + 1
    axes = [low[a] + spacing_m * np.arange(counts[a]) for a in range(3)]
    lattice = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)
    values = shape.prior(lattice)
    if not shape.correction.is_empty:
        coarse_axes = [
            np.linspace(ax[0], ax[-1], max(2, math.ceil(len(ax) / 3) + 1)) for ax in axes
        ]
        coarse = np.stack(np.meshgrid(*coarse_axes, indexing="ij"), axis=-1)
        correction = shape.correction.mean(coarse.reshape(-1, 3)).reshape(coarse.shape[:-1])
        index = [
            np.interp(ax, cax, np.arange(len(cax)))
            for ax, cax in zip(axes, coarse_axes, strict=True)
        ]
        fine_index = np.stack(np.meshgrid(*index, indexing="ij"), axis=0)
        values = values + map_coordinates(correction, fine_index, order=1, mode="nearest")
        touched = shape.correction.touched_world
        exact = np.zeros(0, np.int64)
        if len(touched):
            distance, _ = cKDTree(touched).query(
                lattice.reshape(-1, 3), distance_upper_bound=_EXACT_NEAR_M
            )
            exact = np.flatnonzero(np.isfinite(distance))
        flat_values, flat_lattice = values.reshape(-1), lattice.reshape(-1, 3)
        flat_values[exact] = shape.prior(flat_lattice[exact]) + shape.correction.mean(
            flat_lattice[exact]
        )
    values = np.maximum(values, -lattice[..., 2])  # the table: nothing below z = 0
    values = np.pad(values, 1, constant_values=spacing_m)  # closed surface
    if values.min() >= 0 or values.max() <= 0:
        return trimesh.Trimesh()
    vertices, faces, _, _ = marching_cubes(values.astype(np.float32), 0.0, spacing=(spacing_m,) * 3)
    # A distance (low inside) on a right-handed lattice: skimage's winding is outward (tested).
    return trimesh.Trimesh(vertices - spacing_m + low, faces, process=False)


def prior_surface(
    probabilities: ArrayLike, grid: VoxelGrid, spacing_m: float = EXTRACTION_SPACING_M
) -> trimesh.Trimesh:
    """A voxel estimate's surface through the same extraction as a fused shape (no touches):
    what the vision estimate, the latent update and Direct Edit are measured on."""
    return FusedShape.from_prior(probabilities, grid).mesh(spacing_m)
