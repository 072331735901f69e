"""Accuracy of GelSight height maps: against real ball presses of known radius, and in a closed
loop through the simulated sensor.

Each reconstructed press is compared with the analytic sphere cap at its annotated contact
centre and radius: the cap is R_ball - sqrt(...) deep at the centre and zero on the circle.
The gel around a real press sinks too (its skirt), so the reconstruction sits on a pedestal
that the annotation does not give; the shape figures are therefore taken after removing the
best constant offset inside the circle, and the absolute peak is reported beside them.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.optimize import minimize_scalar

from models.tactile.lut import BallPress, GelSightLUT
from models.tactile.reconstruction import FloatImage, TactileReconstructor
from models.tactile.sim import GelPadSpec, GelSightSimulator, sphere_cap_indentation_mm


@dataclass(frozen=True)
class PressAccuracy:
    """How well one height map matches the annotated press (lengths in mm, errors as fractions).

    ``peak_error``: peak after the best offset vs the cap depth; ``peak_error_rim``: peak minus
    the mean height on the annotated circle vs the cap depth; ``peak_error_absolute``: the raw
    peak (includes the skirt's pedestal) vs the cap depth. ``contact_iou``: contact mask vs the
    annotated circle.
    """

    frame: str
    fitted_radius_mm: float
    rmse_mm: float
    peak_error: float
    peak_error_rim: float
    peak_error_absolute: float
    cap_depth_mm: float
    offset_mm: float
    contact_iou: float


def fit_sphere_radius(points: NDArray[np.float64]) -> float:
    """Radius of the least-squares (algebraic) sphere through (N, 3) points, same unit."""
    x, y, z = points.T
    design = np.column_stack([2 * x, 2 * y, 2 * z, np.ones_like(x)])
    (a, b, c, d), *_ = np.linalg.lstsq(design, x * x + y * y + z * z, rcond=None)
    return float(math.sqrt(max(d + a * a + b * b + c * c, 0.0)))


def evaluate_press(
    height_mm: FloatImage,
    contact_mask: NDArray[np.bool_],
    press: BallPress,
    *,
    ball_radius_mm: float,
    mm_per_px: float,
) -> PressAccuracy:
    """Compare one reconstructed press with its analytic sphere cap (see the module doc)."""
    rows, cols = np.indices(height_mm.shape, dtype=np.float64)
    cx, cy = press.centre_px
    rho2_mm = ((cols - cx) ** 2 + (rows - cy) ** 2) * mm_per_px**2
    contact_mm = press.radius_px * mm_per_px
    inside = rho2_mm < contact_mm**2
    rim_height = math.sqrt(ball_radius_mm**2 - contact_mm**2)
    cap = np.sqrt(np.maximum(ball_radius_mm**2 - rho2_mm[inside], 0.0)) - rim_height
    cap_depth = ball_radius_mm - rim_height
    measured = height_mm[inside].astype(np.float64)
    offset = float(np.mean(measured - cap))
    rmse = float(np.sqrt(np.mean((measured - offset - cap) ** 2)))
    peak = float(measured.max())
    angles = np.linspace(0.0, 2.0 * math.pi, 360, endpoint=False)
    circle = [cy + press.radius_px * np.sin(angles), cx + press.radius_px * np.cos(angles)]
    rim = float(ndimage.map_coordinates(height_mm, circle, order=1).mean())
    points = np.column_stack([cols[inside] * mm_per_px, rows[inside] * mm_per_px, measured])
    union = np.count_nonzero(contact_mask | inside)
    return PressAccuracy(
        frame=press.name,
        fitted_radius_mm=fit_sphere_radius(points),
        rmse_mm=rmse,
        peak_error=(peak - offset - cap_depth) / cap_depth,
        peak_error_rim=(peak - rim - cap_depth) / cap_depth,
        peak_error_absolute=(peak - cap_depth) / cap_depth,
        cap_depth_mm=cap_depth,
        offset_mm=offset,
        contact_iou=np.count_nonzero(contact_mask & inside) / union if union else 0.0,
    )


def summarise(results: list[PressAccuracy], ball_radius_mm: float) -> dict[str, Any]:
    """Medians over frames (absolute values for the signed errors) and the worst frame.

    The worst frame is the one with the largest RMSE.
    """
    if not results:
        raise ValueError("no frames to summarise")

    def median(values: list[float]) -> float:
        return float(statistics.median(values))

    worst = max(results, key=lambda r: r.rmse_mm)
    return {
        "frames": len(results),
        "median_fitted_radius_mm": median([r.fitted_radius_mm for r in results]),
        "median_radius_error": median(
            [abs(r.fitted_radius_mm - ball_radius_mm) / ball_radius_mm for r in results]
        ),
        "median_rmse_mm": median([r.rmse_mm for r in results]),
        "median_abs_peak_error": median([abs(r.peak_error) for r in results]),
        "median_abs_peak_error_rim": median([abs(r.peak_error_rim) for r in results]),
        "median_abs_peak_error_absolute": median([abs(r.peak_error_absolute) for r in results]),
        "median_contact_iou": median([r.contact_iou for r in results]),
        "worst_frame": asdict(worst),
    }


def forward_model_simulator(mm_per_px: float, shape: tuple[int, int]) -> GelSightSimulator:
    """Noise-free simulated sensor at the data's pixel pitch, allowing presses up to 2 mm."""
    spec = GelPadSpec(
        width_mm=shape[1] * mm_per_px,
        height_mm=shape[0] * mm_per_px,
        image_width_px=shape[1],
        image_height_px=shape[0],
        gel_thickness_mm=2.5,
        max_indentation_mm=2.0,
        noise_sigma=0.0,
    )
    return GelSightSimulator(spec)


def forward_model_depth_mm(
    simulator: GelSightSimulator, press: BallPress, ball_radius_mm: float
) -> float:
    """How deep the ball was pressed (mm), by matching the press image with simulated ones.

    The annotation gives the contact radius but not the depth: the gel also sinks around the
    contact. This renders the ball at the annotated centre through the simulator (Taxim's
    optics, fitted on the same real presses, plus the elastic membrane) and returns the depth
    whose image best matches the press within two contact radii (least squares). It is a
    model-based estimate, a cross-check for absolute depth, not ground truth.
    """
    rows, cols = np.indices(simulator.spec.shape)
    cx, cy = press.centre_px
    region = (cols - cx) ** 2 + (rows - cy) ** 2 < (2.0 * press.radius_px) ** 2
    observed = press.image_bgr[region].astype(np.float32)
    rng = np.random.default_rng(0)  # its draws are scaled by noise_sigma = 0: no effect

    def mismatch(depth_mm: float) -> float:
        geometric = sphere_cap_indentation_mm(simulator.spec, (cx, cy), ball_radius_mm, depth_mm)
        image = simulator.render_bgr(simulator.elastic_deformation_mm(geometric), rng)
        return float(np.mean((image[region] - observed) ** 2))

    limit = min(simulator.spec.max_indentation_mm, ball_radius_mm)
    fit = minimize_scalar(mismatch, bounds=(0.1, limit), method="bounded", options={"xatol": 0.01})
    return float(fit.x)


# Spheres (radius mm, depth mm) pressed into the simulated pad for the closed-loop table: the
# calibration ball at the dataPack's depth and shallower, and larger, flatter objects.
SIM_SPHERES = ((2.0, 1.0), (2.0, 0.5), (3.0, 0.8), (5.0, 0.6), (10.0, 0.5))


def run_sim_closed_loop(lut: GelSightLUT, *, seed: int = 0) -> list[dict[str, float]]:
    """Reconstruct simulated sphere presses (models.tactile.sim) and compare with their truth.

    The simulator renders the gel surface (sphere cap plus its elastic skirt) through Taxim's
    optical model onto the real no-contact frame; the reference is the mean of 10 noisy
    no-contact renders, as the simulated sensor gives it. Errors are against that surface.
    """
    simulator = GelSightSimulator()
    rng = np.random.default_rng(seed)
    no_contact = np.zeros(simulator.spec.shape, dtype=np.float32)
    reference = np.mean([simulator.render_bgr(no_contact, rng) for _ in range(10)], axis=0)
    reconstructor = TactileReconstructor(lut, np.rint(reference).astype(np.uint8))
    centre_px = (360.0, 220.0)
    rows = []
    for radius_mm, depth_mm in SIM_SPHERES:
        geometric = sphere_cap_indentation_mm(simulator.spec, centre_px, radius_mm, depth_mm)
        surface = simulator.elastic_deformation_mm(geometric)
        result = reconstructor.reconstruct(simulator.render_bgr(surface, rng))
        touching = geometric > 0
        true_contact = touching & (surface == geometric)
        error = result.height_mm - surface
        union = np.count_nonzero(result.contact_mask | true_contact)
        rows.append(
            {
                "radius_mm": radius_mm,
                "depth_mm": depth_mm,
                "true_peak_mm": float(surface.max()),
                "peak_mm": result.peak_mm,
                "peak_error": result.peak_mm / float(surface.max()) - 1.0,
                "rmse_contact_mm": float(np.sqrt(np.mean(error[touching] ** 2))),
                "max_abs_error_mm": float(np.abs(error).max()),
                "contact_iou": np.count_nonzero(result.contact_mask & true_contact) / union,
            }
        )
    return rows


def sim_table(rows: list[dict[str, float]]) -> str:
    """Markdown table of :func:`run_sim_closed_loop`'s rows."""
    header = (
        "| sphere radius (mm) | pressed (mm) | true peak (mm) | reconstructed peak (mm) |"
        " peak error | RMSE in contact (mm) | max error (mm) | contact IoU |\n"
        "|---|---|---|---|---|---|---|---|\n"
    )
    return (
        header
        + "\n".join(
            f"| {r['radius_mm']:.1f} | {r['depth_mm']:.1f} | {r['true_peak_mm']:.3f} |"
            f" {r['peak_mm']:.3f} | {r['peak_error']:+.1%} | {r['rmse_contact_mm']:.3f} |"
            f" {r['max_abs_error_mm']:.3f} | {r['contact_iou']:.2f} |"
            for r in rows
        )
        + "\n"
    )
