"""GelSight simulation: rigid object pressed into the elastomer pad -> raw BGR tactile image.

Pipeline, per frame:

1. **Geometry** (:meth:`GelSightSimulator.geometric_indentation_mm`): rays cast along the pad's
   +z from the rigid backing plane give, per pixel, how far the object surface has crossed the
   undeformed gel plane z=0 toward the camera.
2. **Elastomer** (:meth:`GelSightSimulator.elastic_deformation_mm`): the gel surface follows the
   object where it touches and sinks smoothly around it (a Gaussian "skirt").
3. **Optics** (:meth:`GelSightSimulator.render_bgr`): the surface slopes go through the real
   calibrated per-pixel polynomial model of Taxim (Si & Yuan, RA-L 2022; the PyPI ``taxim``
   package ships the tables) and are added to the sensor's real no-contact frame, plus noise.
4. **Force** (:meth:`GelSightSimulator.contact_force_n`): elastic-foundation (Winkler) model.

Frames and units: the world is in metres (z-up); everything on the pad is in millimetres. The
pad frame (``pose_world_pad`` maps pad -> world) has its origin at the centre of the undeformed
gel surface and +z along the gel's outward normal, i.e. toward the object. Pixel (row r, col c)
sits at pad x = (c - (W-1)/2) * mm_per_px, y = (r - (H-1)/2) * mm_per_px: +x is along image
columns (the 19 mm side), +y along image rows. Images are 480x640, BGR like the real camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from importlib.resources import files
from importlib.resources.abc import Traversable
from pathlib import Path

import numpy as np
import trimesh
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

FloatImage = NDArray[np.float32]
ImageBGR = NDArray[np.uint8]

# Rays are cast on a grid with this pixel spacing and bilinearly interpolated in between: over
# 4 px (0.12 mm) a gently sloped surface curved with radius >= 2 mm is linear to ~1 um.
_RAY_STRIDE_PX = 4
# ...except in grid cells that touch the contact and whose corners differ by more than this
# (steep or discontinuous surface) or straddle the contact boundary: there every pixel gets its
# own ray, so silhouettes and contact edges stay pixel-exact.
_REFINE_SPREAD_MM = 0.05
# The membrane Gaussian is cut at 3 sigma (weights beyond are < 1.2 %).
_ELASTIC_TRUNCATE = 3.0


@dataclass(frozen=True)
class GelPadSpec:
    """Geometry and material of the GelSight pad (defaults: the sensor Taxim was calibrated on).

    Pixels are square with pitch ``mm_per_px`` = width_mm / image_width_px, so the 480 image rows
    span 14.25 mm; ``height_mm`` is the nominal short side and must agree with that to 5 %.
    """

    width_mm: float = 19.0
    height_mm: float = 14.0
    image_width_px: int = 640
    image_height_px: int = 480
    # Elastomer thickness between the gel surface and the rigid acrylic backing.
    gel_thickness_mm: float = 2.0
    # Deepest the gel can be compressed: beyond this the object bottoms out on the backing.
    max_indentation_mm: float = 1.5
    # Width of the sink-in skirt around a contact, fitted to the ring around the real ball
    # presses of Taxim's dataPack.
    elastic_sigma_mm: float = 0.5
    # Silicone elastomers of GelSight pads are ~0.1-0.5 MPa.
    youngs_modulus_mpa: float = 0.3
    # Per-channel camera noise in 8-bit units, as in the frame-to-frame differences of the real
    # dataPack frames.
    noise_sigma: float = 1.5

    def __post_init__(self) -> None:
        if min(self.width_mm, self.height_mm, self.gel_thickness_mm) <= 0:
            raise ValueError("pad dimensions must be positive")
        if min(self.image_width_px, self.image_height_px) < 2:
            raise ValueError("the image needs at least 2x2 pixels")
        if not 0 < self.max_indentation_mm < self.gel_thickness_mm:
            raise ValueError("max_indentation_mm must lie in (0, gel_thickness_mm)")
        if self.elastic_sigma_mm < 0 or self.youngs_modulus_mpa <= 0 or self.noise_sigma < 0:
            raise ValueError("elastic_sigma_mm, noise_sigma must be >= 0, youngs_modulus_mpa > 0")
        rows_span_mm = self.image_height_px * self.mm_per_px
        if abs(rows_span_mm - self.height_mm) > 0.05 * self.height_mm:
            raise ValueError(
                f"pixels must be square: {self.image_height_px} rows span {rows_span_mm:.2f} mm,"
                f" not height_mm={self.height_mm}"
            )

    @property
    def mm_per_px(self) -> float:
        """Pixel pitch on the gel surface, mm (same along rows and columns)."""
        return self.width_mm / self.image_width_px

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape (rows, cols)."""
        return self.image_height_px, self.image_width_px

    def pixel_to_pad_mm(
        self, rows: ArrayLike, cols: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Pad-frame (x, y) in mm of pixel centres at (rows, cols); z=0 is the undeformed gel."""
        x = (np.asarray(cols, dtype=np.float64) - (self.image_width_px - 1) / 2) * self.mm_per_px
        y = (np.asarray(rows, dtype=np.float64) - (self.image_height_px - 1) / 2) * self.mm_per_px
        return x, y


def default_calib_dir() -> Traversable:
    """Taxim's GelSight calibration folder inside the installed ``taxim`` package."""
    return files("taxim") / "calib" / "gelsight"


def sphere_cap_indentation_mm(
    spec: GelPadSpec,
    centre_px: tuple[float, float],
    radius_mm: float,
    depth_mm: float,
) -> FloatImage:
    """Analytic geometric indentation (mm, float32 HxW) of a sphere pressed into the flat gel.

    ``centre_px`` is the (x=col, y=row) pixel under the sphere's lowest point and ``depth_mm``
    how far that point is past the gel plane. Each pixel gets depth - R + sqrt(R^2 - rho^2) at
    distance rho (mm) from the centre, clipped to [0, spec.max_indentation_mm] like
    :meth:`GelSightSimulator.geometric_indentation_mm`.
    """
    rows, cols = np.indices(spec.shape, dtype=np.float64)
    rho2 = ((cols - centre_px[0]) ** 2 + (rows - centre_px[1]) ** 2) * spec.mm_per_px**2
    inside = rho2 < radius_mm**2
    cap = depth_mm - radius_mm + np.sqrt(np.where(inside, radius_mm**2 - rho2, 0.0))
    cap = np.where(inside, cap, 0.0)
    return np.clip(cap, 0.0, spec.max_indentation_mm).astype(np.float32)


class GelSightSimulator:
    """Indentation, contact force and raw image of a GelSight pad touching a rigid mesh.

    Construction loads Taxim's polynomial table and the real no-contact frame once; every method
    afterwards is pure (the noise comes from the caller's generator).
    """

    def __init__(self, spec: GelPadSpec = GelPadSpec(), calib_dir: Path | None = None) -> None:
        self.spec = spec
        calib = default_calib_dir() if calib_dir is None else Path(calib_dir)
        with (calib / "polycalib.npz").open("rb") as file, np.load(file) as poly:
            # Taxim fitted the image *difference* from the background as one quadratic
            # polynomial in the pixel position per (slope magnitude, slope direction) bin. Its
            # arrays are named after RGB but were fitted on OpenCV frames, so grad_r drives BGR
            # channel 0 (blue) - taxim_torch swaps them for its RGB output. Rendering the real
            # dataPack presses confirms it: the swapped order errs 4-7x more.
            self._n_bins = int(poly["bins"])
            coeffs = np.stack([poly["grad_r"], poly["grad_g"], poly["grad_b"]], axis=2)
        if coeffs.shape != (self._n_bins, self._n_bins, 3, 6):
            raise ValueError(f"unexpected polycalib table shape {coeffs.shape}")
        with (calib / "dataPack.npz").open("rb") as file, np.load(file) as pack:
            self._f0 = np.ascontiguousarray(pack["f0"], dtype=np.uint8)
        if self._f0.shape != (*spec.shape, 3):
            raise ValueError(f"background is {self._f0.shape}, spec wants {(*spec.shape, 3)}")

        # Taxim's binning: magnitude = atan(|grad z|) in [0, pi/2], direction =
        # atan2(dz/drow, dz/dcol) in [-pi, pi], each split into (bins - 1) equal steps.
        self._mag_step = 0.5 * math.pi / (self._n_bins - 1)
        self._dir_step = 2.0 * math.pi / (self._n_bins - 1)
        # Where the gel is flat the real frame f0 is exact, but the fit's flat-bin prediction is
        # not zero (a few units on average, up to 38 near the image corners, where the quadratic
        # extrapolates). Rendering the difference to the flat bin keeps untouched and uniformly
        # pressed gel equal to f0 and leaves no step at the edge of a contact's skirt.
        flat_dir_bin = math.floor(math.pi / self._dir_step)
        self._coeffs = (coeffs - coeffs[0, flat_dir_bin]).reshape(-1, 3, 6)
        # Polynomial features [x^2, y^2, xy, x, y, 1] with x = column, y = row in pixels.
        rows, cols = np.indices(spec.shape, dtype=np.float64)
        x, y = cols.ravel(), rows.ravel()
        self._features = np.stack([x * x, y * y, x * y, x, y, np.ones_like(x)], axis=1)

        # Membrane pyramid: elastic_sigma halved down to one pixel (a single level if it is
        # already below a pixel, none if zero).
        sigma_px = spec.elastic_sigma_mm / spec.mm_per_px
        levels = max(1, math.floor(math.log2(sigma_px)) + 1) if sigma_px > 0 else 0
        self._elastic_sigmas_px = [sigma_px / 2**k for k in range(levels)]

        self._build_ray_grid()

    # --- geometry ------------------------------------------------------------------------------

    def _build_ray_grid(self) -> None:
        """Coarse ray sample positions and per-pixel bilinear interpolation indices/weights."""
        height, width = self.spec.shape
        self._sample_rows = np.unique(np.r_[np.arange(0, height, _RAY_STRIDE_PX), height - 1])
        self._sample_cols = np.unique(np.r_[np.arange(0, width, _RAY_STRIDE_PX), width - 1])
        self._row_cell, self._row_weight = _cell_weights(self._sample_rows, height)
        self._col_cell, self._col_weight = _cell_weights(self._sample_cols, width)

    def _cast_mm(
        self,
        mesh: trimesh.Trimesh,
        pose_world_pad: NDArray[np.float64],
        rows: NDArray[np.intp],
        cols: NDArray[np.intp],
    ) -> NDArray[np.float64]:
        """Signed penetration (mm) of the object past the gel plane at pixels (rows, cols).

        Rays start on the rigid backing (pad z = -gel_thickness) and run along +z; the first
        hit at pad z = z_hit gives -z_hit (negative: the object is still in front of the gel).
        A first hit on a back face means the ray started inside the object, i.e. the object
        reaches through the whole gel: it reports gel_thickness (deeper than any valid
        indentation). Misses report -gel_thickness. Objects wholly behind the backing (inside
        the sensor body) are not seen; colliding with the sensor is the caller's concern.
        """
        thickness = self.spec.gel_thickness_mm
        x_mm, y_mm = self.spec.pixel_to_pad_mm(rows, cols)
        origins_pad_m = np.stack([x_mm, y_mm, np.full_like(x_mm, -thickness)], axis=1) * 1e-3
        rotation, translation = pose_world_pad[:3, :3], pose_world_pad[:3, 3]
        origins = origins_pad_m @ rotation.T + translation
        direction = rotation[:, 2] / np.linalg.norm(rotation[:, 2])
        directions = np.broadcast_to(direction, origins.shape)

        penetration = np.full(len(origins), -thickness)
        tri = mesh.ray.intersects_first(origins, directions)
        hit = np.flatnonzero(tri >= 0)
        if hit.size == 0:
            return penetration
        # Embree only reports which triangle; the distance is recomputed here in float64 as a
        # ray-plane intersection (embree works in float32).
        normals = mesh.face_normals[tri[hit]]
        corner = mesh.vertices[mesh.faces[tri[hit], 0]]
        facing = normals @ direction
        safe = np.where(np.abs(facing) > 1e-12, facing, 1e-12)
        dist_mm = np.einsum("ij,ij->i", normals, corner - origins[hit]) / safe * 1e3
        penetration[hit] = np.where(facing > 0, thickness, thickness - dist_mm)
        return penetration

    def geometric_indentation_mm(
        self, scene_mesh: trimesh.Trimesh, pose_world_pad: NDArray[np.float64]
    ) -> FloatImage:
        """How far the rigid object crosses the undeformed gel plane, per pixel (mm, HxW float32).

        ``scene_mesh`` is in world metres and should be watertight with outward normals (a ray
        starting inside it is recognised by hitting a back face first). Values are >= 0 and
        clamped to ``max_indentation_mm`` where the object bottoms out on the backing (see
        :meth:`bottomed_out`). No elastomer effect: this is the pure geometric intersection.
        """
        pose = np.asarray(pose_world_pad, dtype=np.float64)
        if pose.shape != (4, 4):
            raise ValueError(f"pose_world_pad must be 4x4, got {pose.shape}")
        sample_r, sample_c = np.meshgrid(self._sample_rows, self._sample_cols, indexing="ij")
        coarse = self._cast_mm(scene_mesh, pose, sample_r.ravel(), sample_c.ravel())
        coarse = coarse.reshape(sample_r.shape)

        # Interpolating the signed penetration (not the clipped one) keeps the zero crossing,
        # i.e. the contact edge, between samples instead of snapping it to the grid.
        along_cols = (
            coarse[:, self._col_cell] * (1.0 - self._col_weight)
            + coarse[:, self._col_cell + 1] * self._col_weight
        )
        dense = (
            along_cols[self._row_cell] * (1.0 - self._row_weight)[:, None]
            + along_cols[self._row_cell + 1] * self._row_weight[:, None]
        )

        corners = np.stack([coarse[:-1, :-1], coarse[1:, :-1], coarse[:-1, 1:], coarse[1:, 1:]])
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        refine_cell = (hi > 0) & ((lo <= 0) | (hi - lo > _REFINE_SPREAD_MM))
        if refine_cell.any():
            rows, cols = np.nonzero(refine_cell[self._row_cell][:, self._col_cell])
            dense[rows, cols] = self._cast_mm(scene_mesh, pose, rows, cols)
        return np.clip(dense, 0.0, self.spec.max_indentation_mm).astype(np.float32)

    # --- elastomer -----------------------------------------------------------------------------

    def elastic_deformation_mm(self, geometric_mm: NDArray[np.floating]) -> FloatImage:
        """Gel surface displacement toward the backing (mm, HxW float32) for a geometric field.

        Membrane model, a cheap stand-in for the elastic contact (obstacle) problem: starting
        from u = d, repeat u <- max(d, G_s * u) for s = elastic_sigma, sigma/2, sigma/4, ...
        down to one pixel (Taxim's Gaussian pyramid, with the constraint applied everywhere).
        The gel cannot pass through the rigid object, so u >= d; inside the contact the
        smoothed field is lower and the surface is exactly the object's; around the contact
        the smoothed field wins and the gel sinks in a skirt of width ~sigma. Near the rim of
        the geometric intersection the gel has already lifted off the object, as in Hertz
        contact: for balls of 2-6 mm pressed 0.5-1 mm the true contact (u == d) has 0.74-0.82
        of the geometric radius (Hertz, elastic half-space: 0.71), and at the geometric radius,
        where the gel departs most from the object, it lies 0.12-0.22 d deep (Hertz: 0.32 d).
        The finer levels make the skirt meet the object without a step even at vertical walls
        (a box edge), where the gel wraps the edge over a few pixels. The peak indentation is
        kept exactly, the contact keeps its shape, and a uniform press stays uniform (the
        image border is padded with the nearest value: the gel continues beyond the view).
        """
        geometric = np.asarray(geometric_mm, dtype=np.float32)
        if geometric.shape != self.spec.shape:
            raise ValueError(f"indentation must be {self.spec.shape}, got {geometric.shape}")
        surface = geometric.copy()
        rows, cols = np.nonzero(geometric > 0)
        if rows.size == 0 or not self._elastic_sigmas_px:
            return surface
        # Truncated kernels are exactly zero beyond their reach, so filtering only the contact's
        # bounding box grown by the summed reaches equals filtering the whole image, and is
        # much faster for small contacts.
        reach = sum(math.ceil(_ELASTIC_TRUNCATE * s) for s in self._elastic_sigmas_px)
        height, width = self.spec.shape
        window = (
            slice(max(rows.min() - reach, 0), min(rows.max() + reach + 1, height)),
            slice(max(cols.min() - reach, 0), min(cols.max() + reach + 1, width)),
        )
        obstacle = geometric[window]
        deformed = obstacle
        for sigma_px in self._elastic_sigmas_px:
            smoothed = ndimage.gaussian_filter(
                deformed, sigma_px, mode="nearest", truncate=_ELASTIC_TRUNCATE
            )
            deformed = np.maximum(obstacle, smoothed)
        surface[window] = deformed
        return surface

    def indentation_mm(
        self, scene_mesh: trimesh.Trimesh, pose_world_pad: NDArray[np.float64]
    ) -> FloatImage:
        """Deformed gel surface (mm toward the backing, HxW float32 >= 0) for a mesh at a pose.

        :meth:`elastic_deformation_mm` of :meth:`geometric_indentation_mm`; this is what the
        camera sees and what :meth:`render_bgr` and :meth:`contact_force_n` take.
        """
        return self.elastic_deformation_mm(
            self.geometric_indentation_mm(scene_mesh, pose_world_pad)
        )

    def bottomed_out(self, indentation_mm: NDArray[np.floating]) -> bool:
        """True if any pixel reached ``max_indentation_mm``: the object rests on the backing.

        Works on either the geometric or the elastic field (both keep the clamped maximum).
        """
        limit = np.float32(self.spec.max_indentation_mm) - np.float32(1e-6)
        return bool(np.any(np.asarray(indentation_mm) >= limit))

    def contact_force_n(self, indentation_mm: NDArray[np.floating]) -> float:
        """Normal contact force (N) from an elastic-foundation (Winkler) model of the gel.

        Each pixel is an independent spring of the gel column under it:
        F = sum(E * d / h * dA), E in MPa (= N/mm^2), d the pixel's indentation and h the gel
        thickness in mm, dA = mm_per_px^2 in mm^2. With the defaults a 2 mm ball pressed 0.5 mm
        gives ~0.3 N, a flat face pressed 0.5 mm over the whole pad ~20 N. It ignores the
        in-plane coupling and incompressibility of the gel (real thin bonded layers are
        stiffer), so treat it as an order-of-magnitude, monotonic force estimate.
        """
        spec = self.spec
        volume_mm3 = float(np.sum(indentation_mm, dtype=np.float64)) * spec.mm_per_px**2
        return spec.youngs_modulus_mpa * volume_mm3 / spec.gel_thickness_mm

    # --- optics --------------------------------------------------------------------------------

    def background_bgr(self) -> ImageBGR:
        """The sensor's real no-contact frame (HxWx3 uint8 BGR), a copy."""
        return self._f0.copy()

    def render_bgr(
        self, indentation_mm: NDArray[np.floating], rng: np.random.Generator
    ) -> ImageBGR:
        """Raw tactile image (HxWx3 uint8 BGR) of the gel deformed by ``indentation_mm``.

        Taxim's optical model: per pixel the slope of the gel surface, with the height in
        pixel units so the slope is dimensionless, gives magnitude atan(|grad z|) and direction
        atan2(dz/drow, dz/dcol) (central differences). They select a bin (floor of value over
        bin step) of the calibrated table, whose 3x6 coefficients are dotted with the
        features [x^2, y^2, xy, x, y, 1] of the pixel position (x column, y row, pixels) to
        give the BGR intensity change, added to the real background frame. Flat gel (the
        lowest slope bin, < 0.7 deg) changes nothing. Gaussian noise with sigma
        ``noise_sigma`` from ``rng`` is added to every pixel before rounding to uint8.
        Taxim's shadow model is not reproduced.
        """
        height_px = np.asarray(indentation_mm, dtype=np.float64) / self.spec.mm_per_px
        if height_px.shape != self.spec.shape:
            raise ValueError(f"indentation must be {self.spec.shape}, got {height_px.shape}")
        d_row, d_col = np.gradient(height_px)
        magnitude = np.arctan(np.hypot(d_row, d_col)).ravel()
        mag_bin = np.minimum((magnitude / self._mag_step).astype(np.intp), self._n_bins - 1)
        sloped = np.flatnonzero(mag_bin > 0)

        image = rng.standard_normal(self._f0.shape, dtype=np.float32)
        image *= np.float32(self.spec.noise_sigma)
        image += self._f0
        if sloped.size:
            direction = np.arctan2(d_row.ravel()[sloped], d_col.ravel()[sloped])
            dir_bin = np.minimum(
                ((direction + math.pi) / self._dir_step).astype(np.intp), self._n_bins - 1
            )
            coeffs = self._coeffs[mag_bin[sloped] * self._n_bins + dir_bin]
            change = np.einsum("nck,nk->nc", coeffs, self._features[sloped])
            image.reshape(-1, 3)[sloped] += change.astype(np.float32)
        return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def _cell_weights(
    samples: NDArray[np.intp], size: int
) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """For pixels 0..size-1: index of the sample interval holding each, and the weight of its
    upper end (linear interpolation between samples[i] and samples[i + 1])."""
    pixels = np.arange(size)
    cell = np.clip(np.searchsorted(samples, pixels, side="right") - 1, 0, len(samples) - 2)
    weight = (pixels - samples[cell]) / (samples[cell + 1] - samples[cell])
    return cell, weight
