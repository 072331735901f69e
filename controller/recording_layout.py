"""The viewer layout of session recordings: one blueprint file, ``logs/touchshape.rbl``
(``rerun logs/touchshape.rbl logs/<session>.rrd``, or ``touchshape review``), and the legend the
recordings carry. The entity paths it shows are ``controller.recording``'s.

The file is written once per process: Rerun 0.41 keeps every blueprint stream it makes for the
life of the process (rerun-io/rerun#2116), so one per session grew a long-running service by
~1.5 MB a session.
"""

from __future__ import annotations

import threading
from pathlib import Path

import rerun.blueprint as rrb

STD_RANGE_MM = (0.0, 4.0)
"""The colour scale of the fused shape's posterior std: 4 mm is the fusion's prior std
(``FusionSettings.prior_std_m``), what the surface far from every touch keeps."""
STD_COLORMAP = "viridis"
LEGEND = f"""\
**world**: over the camera's shoulder: its frustum and image, the object's voxels (red: unsure,
green: sure) in the grid's box, the arm's pad, the last touch (target arrow, rays, contact).

**vision estimate** / **current estimate**: the surface before any touch and after the last
refine, over the ground truth (grey, faint). Colour: the fused shape's posterior std,
{STD_COLORMAP} {STD_RANGE_MM[0]:.0f} mm (dark purple) to {STD_RANGE_MM[1]:.0f} mm (yellow);
blue where the update gives none. Orange points, cyan arrows: every touch's contact patch and
its outward normals.

Timeline: `touch` (0: the camera alone).
"""

# The 3D views look from the object frame (``world/object``, logged by ``log_setup``: the
# grid's bottom centre, x towards the camera, z up), so the layout file frames the object
# whatever the configured object point and camera.
OBJECT_FRAME = "world/object"
_OBJECT_CENTRE = (0.0, 0.0, 0.05)
_ESTIMATE_EYE = (0.2, 0.15, 0.17)
"""Close on the object, from the camera's side and above."""
_WORLD_LOOK_AT = (0.15, 0.0, 0.12)
_WORLD_EYE = (0.95, -0.45, 0.7)
"""Over the camera's shoulder (it stands ~0.75 m off along x): its frustum and image in front,
the object behind them, the arm's pad and the touches around it."""


def _view_3d(
    name: str,
    contents: list[str],
    eye: tuple[float, float, float],
    look_at: tuple[float, float, float] = _OBJECT_CENTRE,
) -> rrb.View:
    return rrb.Spatial3DView(
        name=name,
        origin=OBJECT_FRAME,
        contents=contents,
        eye_controls=rrb.EyeControls3D(position=eye, look_target=look_at, eye_up=(0, 0, 1)),
    )


def _blueprint() -> rrb.Blueprint:
    low, high = STD_RANGE_MM
    vision = _view_3d(
        "vision estimate", ["/world/estimate/vision", "/world/ground_truth"], _ESTIMATE_EYE
    )
    current = _view_3d(
        f"current estimate (std {low:.0f}-{high:.0f} mm)",
        [
            "/world/estimate/current",
            "/world/ground_truth",
            "/world/contacts/**",
            "/world/touch/contact",
        ],
        _ESTIMATE_EYE,
    )
    # Not the depth image: under the pinhole it is a depth-coloured cloud over the table that
    # hides the object (the kinect view shows the RGB image).
    world = _view_3d(
        "world",
        ["/world/**", "- /world/estimate/**", "- /world/kinect/depth"],
        _WORLD_EYE,
        _WORLD_LOOK_AT,
    )
    images = rrb.Horizontal(
        rrb.Spatial2DView(name="kinect", origin="world/kinect", contents="/world/kinect/rgb"),
        rrb.Spatial2DView(name="GelSight image", origin="gelsight/image"),
        rrb.Spatial2DView(name="GelSight height (mm)", origin="gelsight/height_mm"),
    )
    metrics = rrb.Vertical(
        rrb.TimeSeriesView(name="Chamfer distance (mm)", origin="metrics/chamfer_mm"),
        rrb.TimeSeriesView(
            name="F-score @2 mm / @5 mm (0-1)",
            origin="metrics/fscore",
            axis_y=rrb.ScalarAxis(range=(0.0, 1.0)),
        ),
        rrb.TimeSeriesView(name="voxels flipped (count)", origin="metrics/voxels_flipped"),
        rrb.Tabs(
            rrb.TextDocumentView(name="legend", origin="legend"),
            rrb.TextLogView(name="log", origin="log"),
            active_tab="legend",
        ),
    )
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Horizontal(world, vision, current, column_shares=[4, 3, 3]),
                images,
                row_shares=[3, 2],
            ),
            metrics,
            column_shares=[3, 1],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        # Following: a review opens on the last touch, and the bar steps back through them.
        rrb.TimePanel(state="collapsed", timeline="touch", play_state="following"),
    )


BLUEPRINT_FILE = "touchshape.rbl"
_blueprints_written: set[Path] = set()
_blueprints_lock = threading.Lock()


def save_blueprint(logs_dir: Path) -> Path:
    """The viewer layout in ``logs_dir`` (written once per process and folder)."""
    path = (logs_dir / BLUEPRINT_FILE).resolve()
    with _blueprints_lock:
        if path not in _blueprints_written or not path.exists():
            _blueprint().save("touchshape", str(path))
            _blueprints_written.add(path)
    return path
