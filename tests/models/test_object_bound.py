"""Where the object may be, from the sim camera's depth: it holds the whole object (thin parts,
dropped pixels and the hidden back included), stays clear of the space the camera sees free, is
carved by touches and only grows with an estimate."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh
from scipy import ndimage

from controller.config import Config
from drivers.base import RGBDFrame
from drivers.factory import make_devices
from models.object_bound import ObjectBound


async def capture(object_spec: str) -> tuple[RGBDFrame, trimesh.Trimesh]:
    """A noisy Kinect frame of the sim bench with this object, and the true mesh (world)."""
    config = Config()
    sim = dataclasses.replace(config.sim, object=object_spec)
    devices = make_devices(
        arm=config.robot.arm,
        gripper=config.gripper,
        sensor=config.sensor,
        camera=config.cameras.rgbd,
        sim=sim,
        rng=np.random.default_rng(0),
        max_object_extent_m=0.34,
    )
    await devices.connect()
    try:
        frame = await devices.camera.read()
        assert devices.world is not None
        return frame, devices.world.object_mesh_world
    finally:
        await devices.close()


def bound_of(frame: RGBDFrame) -> ObjectBound:
    return ObjectBound.from_depth(
        frame.depth_m, frame.intrinsics, frame.pose_world_camera, (0.0, 0.0, 0.0)
    )


def outside_fraction(bound: ObjectBound, mesh: trimesh.Trimesh) -> float:
    """The fraction of the object's surface (above the lowest 4 mm, which no tool part can
    reach) outside the bound grown by one voxel (voxel centres stand for the bound)."""
    points = mesh.sample(20000, seed=0)
    points = points[points[:, 2] > 0.004]
    grown = dataclasses.replace(bound, possible=ndimage.binary_dilation(bound.possible))
    return float(np.mean(~grown.contains(points)))


@pytest.mark.parametrize("object_spec", ["mug", "bottle", "camera"])
async def test_the_bound_holds_the_whole_object(object_spec: str) -> None:
    """The mug's thin handle drops out of a time-of-flight image at its edges; the back of every
    object is hidden: the bound still holds all of the object's surface."""
    frame, mesh = await capture(object_spec)
    bound = bound_of(frame)
    assert outside_fraction(bound, mesh) == 0.0


async def test_the_bound_keeps_out_of_what_the_camera_sees_free() -> None:
    """Space in front of the object's seen side and high above it is free: transits may go
    there. The bound is the object and its shadow, not the whole cube."""
    frame, mesh = await capture("mug")
    bound = bound_of(frame)
    camera = frame.pose_world_camera[:3, 3]
    front = mesh.bounds.mean(axis=0)
    toward_camera = (camera - front) * [1.0, 1.0, 0.0]
    toward_camera /= np.linalg.norm(toward_camera)
    nearest_front = front + (0.5 * mesh.extents[:2].max() + 0.03) * toward_camera
    above = front + np.array([0.0, 0.0, 0.5 * mesh.extents[2] + 0.05])
    assert not bound.contains(np.array([nearest_front, above])).any()
    hull_voxels = mesh.convex_hull.volume / bound.grid.voxel_size_m**3
    assert bound.possible.sum() < 6 * hull_voxels


async def test_dropped_depth_over_the_object_is_not_taken_as_free() -> None:
    """A patch of 19 x 19 pixels with no return over the object (a dark or shiny spot) keeps the
    object inside the bound: the nearest return around stands in."""
    frame, mesh = await capture("bottle")
    depth = frame.depth_m.copy()
    rows, cols = np.nonzero(frame.silhouette)
    v, u = int(np.median(rows)), int(np.median(cols))
    depth[v - 9 : v + 10, u - 9 : u + 10] = 0.0
    bound = bound_of(dataclasses.replace(frame, depth_m=depth))
    assert outside_fraction(bound, mesh) == 0.0


async def test_the_hidden_part_is_what_the_camera_did_not_see() -> None:
    """The hidden part (what the tool parts behind the gel keep clear of) holds the object's
    back, which the camera cannot see, but mostly not the band the depth noise keeps in front
    of the measured surface (the surface points speak for it; where the 7-pixel window's
    nearest return lies in front of a pixel's own, the band stays hidden: conservative); it
    lies within the bound, and touches carve it too."""
    frame, mesh = await capture("mug")
    bound = bound_of(frame)
    assert bound.hidden is not None and not np.any(bound.hidden & ~bound.possible)
    camera = frame.pose_world_camera[:3, 3]
    points, faces = trimesh.sample.sample_surface(mesh, 20000, seed=0)
    facing_away = np.einsum("ij,ij->i", mesh.face_normals[faces], points - camera) > 0.3 * (
        np.linalg.norm(points - camera, axis=1)
    )
    back = points[facing_away & (points[:, 2] > 0.004)]
    grown = dataclasses.replace(bound, hidden=ndimage.binary_dilation(bound.hidden))
    assert np.mean(grown.contains(back, hidden=True)) == 1.0
    toward_camera = camera - bound.surface_points_world
    toward_camera /= np.linalg.norm(toward_camera, axis=1, keepdims=True)
    band = bound.surface_points_world + 0.004 * toward_camera
    assert np.all(bound.contains(band))  # where the object may be...
    assert np.mean(bound.contains(band, hidden=True)) < 0.5  # ...but mostly seen
    # A gel's sweep 5 voxels wide through the back: its core is no longer hidden.
    core = np.argwhere(ndimage.binary_erosion(bound.hidden, iterations=2))[0]
    swept = np.argwhere(np.ones((5, 5, 5), dtype=bool)) + core - 2
    carved = bound.carve(swept)
    assert carved.hidden is not None and not carved.hidden[tuple(core)]
    assert np.all(carved.hidden <= bound.hidden)


def test_touches_carve_it_and_the_estimate_only_adds() -> None:
    grid = ObjectBound.cube((0.0, 0.0, 0.0))
    shape = (grid.resolution,) * 3
    possible = np.zeros(shape, dtype=bool)
    possible[40:60, 40:60, 0:20] = True
    bound = ObjectBound(grid, possible, np.zeros(shape, dtype=bool))

    # A sweep 5 voxels wide through the block: its rim is only partly swept and stays.
    swept = np.argwhere(np.ones((5, 5, 30), dtype=bool)) + np.array([48, 48, 0])
    carved = bound.carve(swept)
    assert not carved.possible[50, 50, 10] and not carved.possible[49, 49, 5]
    assert carved.possible[48, 50, 10] and carved.possible[40, 40, 10]

    # The estimate adds elsewhere, never back where a touch proved the space free.
    point_in_sweep = grid.voxel_to_world(np.array([[50.5, 50.5, 10.5]]))
    point_beside = grid.voxel_to_world(np.array([[70.5, 50.5, 10.5]]))
    grown = carved.with_points(np.concatenate([point_in_sweep, point_beside]))
    assert not grown.contains(point_in_sweep)[0] and grown.contains(point_beside)[0]
    assert np.all(grown.possible[carved.possible])


def test_without_depth_the_object_fitted_cube_stands_in() -> None:
    box = dataclasses.replace(ObjectBound.cube((0.0, 0.0, 0.0)), resolution=32, extent_m=0.1)
    bound = ObjectBound.from_box(box, (0.0, 0.0, 0.0))
    inside = np.array([[0.0, 0.0, 0.05], [0.045, -0.045, 0.095]])
    outside = np.array([[0.0, 0.0, 0.12], [0.07, 0.0, 0.05]])
    assert bound.contains(inside).all() and not bound.contains(outside).any()
    assert bound.top_m == pytest.approx(0.1, abs=bound.grid.voxel_size_m)
