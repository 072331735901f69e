"""`shape.png`: one picture of what a session did to the shape, for a person scanning sessions.

Panels side by side, each the same view of the same part of the world: the vision estimate, the
estimate after the touches (the touch points numbered in order), and, in simulation, the true
object. Lets a reviewer see at a glance where the robot touched and whether the shape got
better, without opening the Rerun recording.

The meshes are drawn by the project's one renderer (:mod:`models.render`: Embree ray casting,
Lambert shading, shadows) from one virtual camera; matplotlib only composes the panels and
draws what is projected with that same camera: the touch numbers, and a checkered floor of
10 mm squares at the meshes' lowest point that gives the view its scale. Saved with 256
colours, a picture is 50-130 KB.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import trimesh
from PIL import Image

from models.camera import CameraIntrinsics, look_at_pose
from models.files import write_atomically
from models.render import DirectionalLight, Lighting, RenderOutput, Scene, SceneObject, render

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

# One panel is PANEL_WIDTH_PX wide; the whole picture PANEL_WIDTH_PX times the panel count by
# PICTURE_HEIGHT_PX, of which the rendered view takes VIEW_HEIGHT_PX (the rest holds the titles).
PANEL_WIDTH_PX = 500
PICTURE_HEIGHT_PX = 550
VIEW_HEIGHT_PX = 480
_DPI = 100
# The view's pinhole camera: 30 degrees of vertical field of view, a gentle perspective (the
# Kinect's ~53 would bulge the near side of a close-up).
VIEW_INTRINSICS = CameraIntrinsics(
    width=PANEL_WIDTH_PX,
    height=VIEW_HEIGHT_PX,
    fx=VIEW_HEIGHT_PX / 2 / math.tan(math.radians(15.0)),
    fy=VIEW_HEIGHT_PX / 2 / math.tan(math.radians(15.0)),
    cx=(PANEL_WIDTH_PX - 1) / 2,
    cy=(VIEW_HEIGHT_PX - 1) / 2,
)

# The view: from the camera's side of the table (the RGB-D camera stands on -x looking along
# +x, see drivers.config.CameraConfig) turned 30 degrees towards -y for a 3/4 view, and from
# 30 degrees above the table, about the Kinect's own 36: tops and sides both show.
VIEW_AZIMUTH_DEG = 210.0
VIEW_ELEVATION_DEG = 30.0

# The meshes' bounding box fills this fraction of the view (in its tighter direction).
_FILL = 0.9
# A touch point more than this behind the surface drawn at its pixel is hidden by the shape.
_HIDDEN_TOLERANCE_M = 0.005
_CHECKER_M = 0.01
_MAX_FLOOR_HALF_M = 1.0
_FLOOR_GREYS = (0.93, 0.85)  # light, dark squares

_VISION_ALBEDO = (0.42, 0.58, 0.85)
_FINAL_ALBEDO = (0.92, 0.58, 0.28)
_TRUE_ALBEDO = (0.72, 0.72, 0.72)
_TOUCH_COLOUR = "#c81e1e"
# The renderer's default key light (above, behind the camera on -x, from the left of this view)
# with more ambient: the side facing away from it still shows its shape.
_LIGHTING = Lighting(
    ambient_rgb=(0.45, 0.45, 0.45), lights=(DirectionalLight((-0.5, 0.35, 1.0), (0.6, 0.6, 0.6)),)
)


def save_shape_picture(
    path: Path,
    vision_mesh: trimesh.Trimesh,
    final_mesh: trimesh.Trimesh,
    touch_points_world: np.ndarray,
    true_mesh: trimesh.Trimesh | None,
    *,
    touch_numbers: Sequence[int] | None = None,
    touches: int | None = None,
    title: str = "",
) -> Path:
    """Write the session's shape picture to ``path`` (PNG, atomically) and return ``path``.

    Meshes and ``touch_points_world`` ((N, 3), touch order, N may be 0) are in the world frame
    (z up, metres). Panels: "vision estimate", "after N touches" with the touch points numbered
    1..N, and "true object (sim)" unless ``true_mesh`` is None (a real robot: two panels). All
    panels share one camera framed on the union of the meshes' bounds and the touch points, so
    they compare one to one. An empty mesh leaves its panel blank but for "(no surface)".
    ``touch_numbers`` label the points (default 1..N: a session whose touches missed passes the
    numbers of those that met the object); ``touches`` is the count in the title (default N).
    """
    points = np.asarray(touch_points_world, dtype=np.float64).reshape(-1, 3)
    meshes = [vision_mesh, final_mesh] + ([true_mesh] if true_mesh is not None else [])
    albedos = [_VISION_ALBEDO, _FINAL_ALBEDO, _TRUE_ALBEDO]
    numbers = list(range(1, len(points) + 1)) if touch_numbers is None else list(touch_numbers)
    if len(numbers) != len(points):
        raise ValueError(f"{len(numbers)} touch numbers for {len(points)} touch points")
    count = len(points) if touches is None else touches
    titles = ["vision estimate", f"after {count} touch{'' if count == 1 else 'es'}"]
    titles.append("true object (sim)")

    low, high = _bounds(meshes, points)
    intrinsics, pose = _view_camera(low, high)
    views = [
        _render_view(mesh, albedo, intrinsics, pose)
        for mesh, albedo in zip(meshes, albedos, strict=False)
    ]
    floor = _floor_squares(low, high, intrinsics, pose)
    figure = _compose(views, titles[: len(meshes)], title, intrinsics, pose, floor, points, numbers)
    figure.canvas.draw()
    rgb = Image.fromarray(np.asarray(figure.canvas.buffer_rgba())[..., :3])
    # 256 colours by median cut: indistinguishable from the full colour picture here (only text
    # edges change) and half the bytes or less; a noisy estimate's full colour picture can
    # exceed 200 KB.
    picture = rgb.quantize(256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    return write_atomically(path, lambda temp: picture.save(temp, format="PNG"))


def _project(
    points: np.ndarray, intrinsics: CameraIntrinsics, pose: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel coordinates u, v and camera-frame depth z of world ``points`` (N, 3)."""
    camera = (points - pose[:3, 3]) @ pose[:3, :3]
    z = camera[:, 2]
    return (
        intrinsics.fx * camera[:, 0] / z + intrinsics.cx,
        intrinsics.fy * camera[:, 1] / z + intrinsics.cy,
        z,
    )


def _bounds(meshes: Sequence[trimesh.Trimesh], points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World (min, max) corners of every non-empty mesh and the touch points."""
    corners = [mesh.bounds for mesh in meshes if len(mesh.faces) > 0]
    if len(points):
        corners.append(np.array([points.min(axis=0), points.max(axis=0)]))
    if not corners:  # nothing to frame: a 10 cm cube on the table at the origin
        return np.array([-0.05, -0.05, 0.0]), np.array([0.05, 0.05, 0.1])
    stacked = np.concatenate(corners)
    low, high = stacked.min(axis=0), stacked.max(axis=0)
    # A flat or tiny shape still gets a few millimetres of room.
    pad = np.maximum(0.0, 0.005 - (high - low)) / 2
    return low - pad, high + pad


def _view_camera(low: np.ndarray, high: np.ndarray) -> tuple[CameraIntrinsics, np.ndarray]:
    """The view's camera (``VIEW_INTRINSICS``) and its pose: looking at the box (low, high) from
    the 3/4 view, at the distance and sideways offset at which the box's projection fills the
    image, centred. The zoom is the camera's distance, not its focal length: the intrinsics stay
    the same, so the renderer's per-intrinsics cache of pixel rays holds one more entry only."""
    azimuth, elevation = math.radians(VIEW_AZIMUTH_DEG), math.radians(VIEW_ELEVATION_DEG)
    towards_eye = np.array(
        [
            math.cos(elevation) * math.cos(azimuth),
            math.cos(elevation) * math.sin(azimuth),
            math.sin(elevation),
        ]
    )
    corners = np.array(list(itertools.product(*zip(low, high, strict=True))))
    target = (low + high) / 2
    distance = 4.0 * float(np.linalg.norm(high - low)) / 2
    k = VIEW_INTRINSICS
    # Fixed-point iteration: moving the camera changes the projection only by the perspective,
    # so a few steps settle it to well under a pixel.
    for _ in range(4):
        pose = look_at_pose(target + distance * towards_eye, target)
        camera = (corners - pose[:3, 3]) @ pose[:3, :3]
        x, y = camera[:, 0] / camera[:, 2], camera[:, 1] / camera[:, 2]
        target = target + distance * (
            pose[:3, 0] * (x.min() + x.max()) / 2 + pose[:3, 1] * (y.min() + y.max()) / 2
        )
        fitting_focal = _FILL * min(k.width / np.ptp(x), k.height / np.ptp(y))
        distance *= k.fx / fitting_focal
    return k, look_at_pose(target + distance * towards_eye, target)


def _floor_squares(
    low: np.ndarray, high: np.ndarray, intrinsics: CameraIntrinsics, pose: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Pixel corners (M, 4, 2) of the squares of a checkered floor tile under the meshes (at
    their lowest point), and which are dark (M,). Drawn under the rendered shapes rather than
    ray cast: the floor lies below everything, so a shape always hides it, and it costs nothing.
    """
    half = 0.8 * float(max(high[0] - low[0], high[1] - low[1]))
    if half > _MAX_FLOOR_HALF_M:  # no object is this large: a stray fragment; no floor
        return np.zeros((0, 4, 2)), np.zeros(0, dtype=bool)
    centre = (low + high) / 2
    first = np.floor((centre[:2] - half) / _CHECKER_M).astype(int)
    last = np.ceil((centre[:2] + half) / _CHECKER_M).astype(int)
    i, j = np.meshgrid(np.arange(first[0], last[0]), np.arange(first[1], last[1]), indexing="ij")
    dark = (i + j).ravel() % 2 == 0
    steps = np.array([[0, 0], [1, 0], [1, 1], [0, 1]])
    squares_xy = (np.stack([i.ravel(), j.ravel()], axis=1)[:, None, :] + steps) * _CHECKER_M
    squares = np.concatenate([squares_xy, np.full((*squares_xy.shape[:2], 1), low[2])], axis=2)
    u, v, z = _project(squares.reshape(-1, 3), intrinsics, pose)
    if np.any(z <= 1e-6):  # behind the camera: the fixed view keeps the tile in front
        return np.zeros((0, 4, 2)), np.zeros(0, dtype=bool)
    return np.stack([u, v], axis=1).reshape(-1, 4, 2), dark


def _render_view(
    mesh: trimesh.Trimesh,
    albedo: tuple[float, float, float],
    intrinsics: CameraIntrinsics,
    pose: np.ndarray,
) -> RenderOutput | None:
    """The mesh alone, ray cast; None for an empty mesh (its panel stays blank)."""
    if len(mesh.faces) == 0:
        return None
    scene = Scene(objects=[SceneObject(mesh=mesh, albedo_rgb=albedo)])
    return render(scene, intrinsics, pose, lighting=_LIGHTING)


def _compose(
    views: Sequence[RenderOutput | None],
    panel_titles: Sequence[str],
    title: str,
    intrinsics: CameraIntrinsics,
    pose: np.ndarray,
    floor: tuple[np.ndarray, np.ndarray],
    points: np.ndarray,
    numbers: Sequence[int],
) -> Figure:
    """A matplotlib Figure of the panels, equal width and edge to edge, titles above them."""
    # Imported here: matplotlib adds ~0.3 s to every CLI start and only pictures need it.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import PolyCollection
    from matplotlib.figure import Figure

    panels = len(views)
    figure = Figure(figsize=(PANEL_WIDTH_PX * panels / _DPI, PICTURE_HEIGHT_PX / _DPI), dpi=_DPI)
    FigureCanvasAgg(figure)
    squares, dark = floor
    greys = np.where(dark, _FLOOR_GREYS[1], _FLOOR_GREYS[0])
    width, height = intrinsics.width, intrinsics.height
    first_drawn = next((i for i, view in enumerate(views) if view is not None), -1)
    for index, (view, panel_title) in enumerate(zip(views, panel_titles, strict=True)):
        axes = figure.add_axes(
            (index / panels, 0.0, 1.0 / panels, VIEW_HEIGHT_PX / PICTURE_HEIGHT_PX)
        )
        axes.set_axis_off()
        if view is None:
            axes.text(width / 2, height / 2, "(no surface)", ha="center", va="center", color="0.5")
        else:
            axes.add_collection(
                PolyCollection(
                    squares, facecolors=np.repeat(greys[:, None], 3, axis=1), linewidths=0, zorder=0
                )
            )
            # Only the shape's pixels: the floor shows through everything else.
            alpha = np.where(view.hit_mask, 255, 0).astype(np.uint8)
            axes.imshow(
                np.dstack([view.colour_rgb, alpha]),
                interpolation="nearest",
                aspect="auto",
                zorder=1,
            )
        axes.set_xlim(-0.5, width - 0.5)
        axes.set_ylim(height - 0.5, -0.5)
        if index == 1 and _draw_touches(axes, points, numbers, view, intrinsics, pose):
            axes.text(
                8, height - 8, "hollow number: touch behind the shape", fontsize=8, color="0.35"
            )
        if view is not None and index == first_drawn and len(squares):
            axes.text(8, height - 8, "floor squares: 10 mm", fontsize=8, color="0.35")
        figure.text(
            (index + 0.5) / panels,
            (VIEW_HEIGHT_PX + 6) / PICTURE_HEIGHT_PX,
            panel_title,
            ha="center",
            va="bottom",
            fontsize=13,
        )
    if title:
        figure.text(0.5, 1 - 6 / PICTURE_HEIGHT_PX, title, ha="center", va="top", fontsize=11)
    return figure


def _draw_touches(
    axes: Axes,
    points: np.ndarray,
    numbers: Sequence[int],
    view: RenderOutput | None,
    intrinsics: CameraIntrinsics,
    pose: np.ndarray,
) -> bool:
    """Number the touch points where the camera sees them: filled where in view, hollow where
    the drawn shape hides them. Returns whether any is hidden."""
    any_hidden = False
    u, v, z = _project(points, intrinsics, pose)
    for number, x, y, depth in zip(numbers, u, v, z, strict=True):
        col, row = round(x), round(y)
        hidden = (
            view is not None
            and 0 <= col < intrinsics.width
            and 0 <= row < intrinsics.height
            and 0.0 < view.depth_m[row, col] < depth - _HIDDEN_TOLERANCE_M
        )
        any_hidden |= hidden
        axes.text(
            x,
            y,
            str(number),
            ha="center",
            va="center",
            fontsize=8,
            fontweight="bold",
            color=_TOUCH_COLOUR if hidden else "white",
            zorder=3,
            bbox={
                "boxstyle": "circle,pad=0.25",
                "facecolor": "white" if hidden else _TOUCH_COLOUR,
                "edgecolor": _TOUCH_COLOUR,
                "alpha": 0.8 if hidden else 1.0,
                "linewidth": 1.0,
            },
        )
    return any_hidden
