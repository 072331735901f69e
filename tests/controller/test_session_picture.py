"""shape.png: panels side by side, each showing its mesh, and the touches where they were."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image

from controller import session_picture
from controller.session_picture import (
    PANEL_WIDTH_PX,
    PICTURE_HEIGHT_PX,
    VIEW_HEIGHT_PX,
    save_shape_picture,
)

# A panel showing a shaded mesh on the floor has a grayscale variance in the thousands; a blank
# one (white, with only its title and maybe "(no surface)") about a hundred.
DRAWN_PANEL_MIN_VARIANCE = 1000.0


def _cylinder(radius: float, height: float, x: float = 0.0) -> trimesh.Trimesh:
    mesh = trimesh.creation.cylinder(radius=radius, height=height)
    mesh.apply_translation((x, 0.0, height / 2))  # standing on the table
    return mesh


@pytest.fixture
def meshes() -> dict[str, trimesh.Trimesh]:
    box = trimesh.creation.box(extents=(0.08, 0.08, 0.1))
    box.apply_translation((0.0, 0.0, 0.05))
    return {
        "true": _cylinder(0.04, 0.1),
        "vision": _cylinder(0.045, 0.09, x=0.005),
        "final": box,
    }


TOUCHES = np.array([[-0.04, 0.0, 0.05], [0.0, -0.04, 0.07], [0.0, 0.0, 0.1]])


def _panel_variances(path: Path, panels: int) -> list[float]:
    grey = np.asarray(Image.open(path).convert("L"), dtype=np.float64)
    width = grey.shape[1] // panels
    return [float(grey[:, i * width : (i + 1) * width].var()) for i in range(panels)]


def test_sim_picture_has_three_drawn_panels(tmp_path: Path, meshes: dict) -> None:
    path = save_shape_picture(
        tmp_path / "shape.png",
        meshes["vision"],
        meshes["final"],
        TOUCHES,
        meshes["true"],
        title="20261202-015846-005102  mug",
    )
    assert path == tmp_path / "shape.png"
    assert [p.name for p in tmp_path.iterdir()] == ["shape.png"]  # no temporary file left
    assert path.stat().st_size < 200_000
    with Image.open(path) as image:
        assert image.format == "PNG"
        assert image.size == (3 * PANEL_WIDTH_PX, PICTURE_HEIGHT_PX)
    variances = _panel_variances(path, 3)
    assert min(variances) > DRAWN_PANEL_MIN_VARIANCE, variances


def test_real_robot_picture_has_two_panels(tmp_path: Path, meshes: dict) -> None:
    path = save_shape_picture(
        tmp_path / "shape.png", meshes["vision"], meshes["final"], np.zeros((0, 3)), None
    )
    with Image.open(path) as image:
        assert image.size == (2 * PANEL_WIDTH_PX, PICTURE_HEIGHT_PX)
    variances = _panel_variances(path, 2)
    assert min(variances) > DRAWN_PANEL_MIN_VARIANCE, variances


def test_threshold_tells_a_blank_panel(tmp_path: Path, meshes: dict) -> None:
    """The variance threshold above fails a blank panel: an all-white one, and one the
    picture itself leaves blank (an empty vision mesh: title and "(no surface)" only)."""
    white = tmp_path / "white.png"
    Image.new("RGB", (3 * PANEL_WIDTH_PX, PICTURE_HEIGHT_PX), "white").save(white)
    assert max(_panel_variances(white, 3)) < DRAWN_PANEL_MIN_VARIANCE

    path = save_shape_picture(
        tmp_path / "shape.png", trimesh.Trimesh(), meshes["final"], TOUCHES, meshes["true"]
    )
    blank, final, true = _panel_variances(path, 3)
    assert blank < DRAWN_PANEL_MIN_VARIANCE / 4, blank
    assert min(final, true) > DRAWN_PANEL_MIN_VARIANCE


def test_overwrites_an_existing_picture(tmp_path: Path, meshes: dict) -> None:
    path = tmp_path / "shape.png"
    path.write_bytes(b"old")
    save_shape_picture(path, meshes["vision"], meshes["final"], TOUCHES[:1], None)
    with Image.open(path) as image:
        assert image.size == (2 * PANEL_WIDTH_PX, PICTURE_HEIGHT_PX)


def test_touch_numbers_are_placed_with_the_rendering_camera(meshes: dict) -> None:
    """A point on the box's front face projects to a pixel where the rendered box is, at the
    point's depth: the numbers sit on the surface they touched, in every panel alike."""
    points = np.array([[-0.04, -0.01, 0.06]])  # on the box's -x face, which faces the view
    low, high = session_picture._bounds([meshes["final"]], points)
    intrinsics, pose = session_picture._view_camera(low, high)
    view = session_picture._render_view(meshes["final"], (0.8, 0.8, 0.8), intrinsics, pose)
    assert view is not None
    u, v, depth = session_picture._project(points, intrinsics, pose)
    row, col = round(float(v[0])), round(float(u[0]))
    assert view.silhouette[row, col]
    assert view.depth_m[row, col] == pytest.approx(depth[0], abs=0.002)
    # The box fills the view (to the framing's 90 %) without being cut off.
    ys, xs = np.nonzero(view.silhouette)
    assert xs.min() > 0 and ys.min() > 0
    assert xs.max() < PANEL_WIDTH_PX - 1 and ys.max() < VIEW_HEIGHT_PX - 1
    assert np.ptp(ys) > 0.7 * VIEW_HEIGHT_PX or np.ptp(xs) > 0.7 * PANEL_WIDTH_PX
