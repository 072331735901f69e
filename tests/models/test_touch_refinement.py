"""Touch refinement: the paper's loss and gradients, latent updates, Direct Edit."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
import torch
from torch import nn

from models.geometry import VoxelGrid, frame_from_z_axis, make_transform
from models.touch.constraints import (
    TouchResult,
    VoxelConstraints,
    constraints_from_touches,
    pad_grid_world,
)
from models.touch.refinement import decode_volume, direct_edit, refine_latent, touch_loss

N = 8


class TinyDecoder(nn.Module):
    """A small random decoder with the prior's protocol: latent (1, 200) -> (N, N, N) in (0, 1)."""

    def __init__(self, seed: int = 0) -> None:
        super().__init__()
        torch.manual_seed(seed)
        self.layers = nn.Sequential(nn.Linear(200, 64), nn.Tanh(), nn.Linear(64, N**3))

    def forward(self, latent: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.layers(latent)).reshape(N, N, N)


def _constraints() -> VoxelConstraints:
    empty = [[i, 3, 4] for i in range(5, N)]
    occupied = [[4, 3, 4], [4, 4, 4]]
    return VoxelConstraints.from_voxels(N, empty, occupied)


def test_loss_value_and_gradient_match_the_paper() -> None:
    generator = torch.Generator().manual_seed(0)
    voxels = torch.rand(N, N, N, generator=generator, dtype=torch.float64, requires_grad=True)
    constraints = _constraints()
    loss = touch_loss(voxels, constraints)
    (gradient,) = torch.autograd.grad(loss, voxels)
    flat_v = voxels.detach().reshape(-1)
    expected_loss = (flat_v[constraints.empty] ** 2).sum() + (
        (1 - flat_v[constraints.occupied]) ** 2
    ).sum()
    assert float(loss.detach()) == pytest.approx(float(expected_loss))
    expected = torch.zeros(N**3, dtype=torch.float64)
    expected[constraints.empty] = 2 * flat_v[constraints.empty]  # dL/dv = 2 v in front
    expected[constraints.occupied] = 2 * (flat_v[constraints.occupied] - 1)  # 2 (v - 1) at contact
    torch.testing.assert_close(gradient.reshape(-1), expected)


def test_balanced_loss_weighs_empty_and_occupied_voxels_equally() -> None:
    generator = torch.Generator().manual_seed(1)
    voxels = torch.rand(N, N, N, generator=generator, dtype=torch.float64, requires_grad=True)
    constraints = _constraints()
    loss = touch_loss(voxels, constraints, "balanced")
    (gradient,) = torch.autograd.grad(loss, voxels)
    flat_v = voxels.detach().reshape(-1)
    empty, occupied = constraints.empty, constraints.occupied
    expected_loss = (flat_v[empty] ** 2).mean() + ((1 - flat_v[occupied]) ** 2).mean()
    assert float(loss.detach()) == pytest.approx(float(expected_loss))
    expected = torch.zeros(N**3, dtype=torch.float64)
    expected[empty] = 2 * flat_v[empty] / len(empty)
    expected[occupied] = 2 * (flat_v[occupied] - 1) / len(occupied)
    torch.testing.assert_close(gradient.reshape(-1), expected)
    only_empty = VoxelConstraints.from_voxels(N, [[1, 1, 1]], np.zeros((0, 3), int))
    assert float(touch_loss(voxels.detach(), only_empty, "balanced")) == pytest.approx(
        float(flat_v[only_empty.empty[0]] ** 2)
    )
    with pytest.raises(ValueError, match="unknown touch loss"):
        touch_loss(voxels, constraints, "mean")  # type: ignore[arg-type]


def test_threshold_loss_stops_pulling_at_the_surface() -> None:
    """Empty voxels pull only while v > 0.5, occupied ones only while v < 0.5, each kind
    averaged: gradient 2 (v - 0.5) / n_empty and -2 (0.5 - v) / n_occupied, else 0."""
    generator = torch.Generator().manual_seed(4)
    voxels = torch.rand(N, N, N, generator=generator, dtype=torch.float64, requires_grad=True)
    constraints = _constraints()
    loss = touch_loss(voxels, constraints, "threshold")
    (gradient,) = torch.autograd.grad(loss, voxels)
    flat_v = voxels.detach().reshape(-1)
    empty, occupied = constraints.empty, constraints.occupied
    over = (flat_v[empty] - 0.5).clamp(min=0)
    under = (0.5 - flat_v[occupied]).clamp(min=0)
    assert float(loss.detach()) == pytest.approx(float((over**2).mean() + (under**2).mean()))
    expected = torch.zeros(N**3, dtype=torch.float64)
    expected[empty] = 2 * over / len(empty)
    expected[occupied] = -2 * under / len(occupied)
    torch.testing.assert_close(gradient.reshape(-1), expected)
    assert (over == 0).any() and (over > 0).any()  # both sides of the threshold are exercised
    satisfied = torch.zeros(N, N, N, dtype=torch.float64).reshape(-1)
    satisfied[occupied] = 0.6
    satisfied[empty] = 0.4
    assert float(touch_loss(satisfied.reshape(N, N, N), constraints, "threshold")) == 0.0


def test_loss_rejects_a_volume_of_another_size() -> None:
    with pytest.raises(ValueError):
        touch_loss(torch.zeros(4, 4, 4), _constraints())


def test_refinement_lowers_the_loss_and_touches_only_the_latent() -> None:
    decoder = TinyDecoder().eval()
    parameters = [p.detach().clone() for p in decoder.parameters()]
    latent = torch.randn(1, 200, generator=torch.Generator().manual_seed(1))
    original = latent.clone()
    result = refine_latent(decoder, latent, _constraints(), learning_rate=1e-2, iterations=10)
    assert len(result.losses) == 11
    assert result.losses[-1] < result.losses[0]
    assert not result.latent.requires_grad and not result.voxels.requires_grad
    assert result.voxels.shape == (N, N, N)
    torch.testing.assert_close(latent, original)  # the caller's latent is not modified
    assert not torch.equal(result.latent, latent)
    for before, after in zip(parameters, decoder.parameters(), strict=True):
        torch.testing.assert_close(before, after)
        assert after.grad is None
    torch.testing.assert_close(result.voxels, decoder(result.latent).detach())


def test_adam_moves_each_latent_coordinate_by_about_the_learning_rate() -> None:
    """Why Adam at the paper's lr 0.001: the first step is ~lr per coordinate, whatever the loss
    scale (a sum over however many voxels the touches constrain)."""
    decoder = TinyDecoder().eval()
    latent = torch.randn(1, 200, generator=torch.Generator().manual_seed(2))
    result = refine_latent(decoder, latent, _constraints(), learning_rate=1e-3, iterations=1)
    step = (result.latent - latent).abs()
    moved = step > 0
    torch.testing.assert_close(step[moved], torch.full_like(step[moved], 1e-3), rtol=1e-3, atol=0)


def test_the_anchor_keeps_the_latent_near_the_vision_latent() -> None:
    """The anchor term's gradient is 2 w (z - z0) (checked through SGD), and a strong anchor
    holds the latent closer to it than the touches alone do."""
    decoder = TinyDecoder().eval()
    anchor = torch.randn(1, 200, generator=torch.Generator().manual_seed(5))
    latent = anchor + 0.1
    constraints = _constraints()
    free = refine_latent(decoder, latent, constraints, 1e-2, iterations=20, loss="balanced")
    held = refine_latent(
        decoder,
        latent,
        constraints,
        1e-2,
        iterations=20,
        loss="balanced",
        anchor_latent=anchor,
        anchor_weight=10.0,
    )
    assert (held.latent - anchor).norm() < (free.latent - anchor).norm()
    only_anchor = refine_latent(
        decoder,
        latent,
        VoxelConstraints.none(N),
        0.01,
        iterations=1,
        optimizer="sgd",
        loss="balanced",
        anchor_latent=anchor,
        anchor_weight=1.0,
    )
    torch.testing.assert_close(only_anchor.latent, latent - 0.01 * 2.0 * (latent - anchor))
    with pytest.raises(ValueError, match="anchor_latent"):
        refine_latent(decoder, latent, constraints, anchor_weight=1.0)


def test_sgd_follows_the_negative_gradient() -> None:
    decoder = TinyDecoder().eval()
    latent = torch.randn(1, 200, generator=torch.Generator().manual_seed(3)).requires_grad_(True)
    constraints = _constraints()
    (gradient,) = torch.autograd.grad(touch_loss(decoder(latent), constraints), latent)
    result = refine_latent(decoder, latent, constraints, 1e-3, iterations=1, optimizer="sgd")
    torch.testing.assert_close(result.latent, latent.detach() - 1e-3 * gradient)
    with pytest.raises(ValueError):
        refine_latent(decoder, latent, constraints, optimizer="lbfgs")  # type: ignore[arg-type]


def test_zero_iterations_and_batched_decoders() -> None:
    decoder = TinyDecoder().eval()
    latent = torch.zeros(1, 200)
    result = refine_latent(lambda z: decoder(z)[None], latent, _constraints(), iterations=0)
    assert len(result.losses) == 1
    torch.testing.assert_close(result.latent, latent)
    assert decode_volume(lambda z: decoder(z)[None], latent).shape == (N, N, N)
    with pytest.raises(ValueError):
        decode_volume(lambda z: torch.zeros(2, N, N, N), latent)


def test_direct_edit_writes_constraints_into_a_copy() -> None:
    voxels = np.full((N, N, N), 0.3, np.float32)
    constraints = _constraints()
    edited = direct_edit(voxels, constraints)
    assert np.all(voxels == 0.3)
    flat = edited.reshape(-1)
    assert np.all(flat[constraints.empty] == 0) and np.all(flat[constraints.occupied] == 1)
    untouched = np.ones(N**3, bool)
    untouched[np.concatenate([constraints.empty, constraints.occupied])] = False
    assert np.all(flat[untouched] == np.float32(0.3))
    with pytest.raises(ValueError):
        direct_edit(np.zeros((4, 4, 4)), constraints)


SPHERE_GRID = VoxelGrid(resolution=32, extent_m=0.16)  # 5 mm voxels
SPHERE_CENTRE_WORLD = np.array([0.0, 0.0, 0.06])


def _sphere_decoder(radius_at_zero_m: float) -> Callable[[torch.Tensor], torch.Tensor]:
    """A toy prior on ``SPHERE_GRID``: a sphere at ``SPHERE_CENTRE_WORLD`` whose radius is
    ``radius_at_zero_m + 0.05 * latent[0, 0]``, its surface blurred over 2 mm."""
    centres = torch.from_numpy(SPHERE_GRID.voxel_centres_world())
    centre = torch.from_numpy(SPHERE_CENTRE_WORLD)

    def decode(latent: torch.Tensor) -> torch.Tensor:
        radius_m = radius_at_zero_m + 0.05 * latent[0, 0]
        distance = torch.linalg.norm(centres - centre, dim=-1)
        return torch.sigmoid((radius_m - distance) / 0.002).float()

    return decode


def test_touches_shrink_a_too_fat_sphere_through_the_latent() -> None:
    """End to end: rays of a touch on a true sphere -> constraints -> refinement of a toy prior
    whose latent sets the radius; the prediction is too fat and must shrink toward the truth."""
    grid, centre_world = SPHERE_GRID, SPHERE_CENTRE_WORLD
    true_radius_m = 0.04
    sphere_decoder = _sphere_decoder(0.05)  # latent 0 -> 5 cm, 1 cm too fat

    touches = []
    for direction in ([1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]):
        direction = np.array(direction)
        pose = make_transform(frame_from_z_axis(direction), centre_world - 0.1 * direction)
        starts = pad_grid_world(pose, (0.019, 0.014), 0.001)
        # Analytic ray-sphere hits: every pad ray hits this sphere (pad smaller than it).
        offset = starts - centre_world
        along = -(offset @ direction)
        lateral_sq = np.einsum("ij,ij->i", offset, offset) - along**2
        contacts = starts + (along - np.sqrt(true_radius_m**2 - lateral_sq))[:, None] * direction
        touches.append(TouchResult.from_contact(contacts, direction, starts[0]))
    constraints = constraints_from_touches(touches, grid)
    latent = torch.zeros(1, 200)
    result = refine_latent(sphere_decoder, latent, constraints, learning_rate=0.02, iterations=10)
    radius_after = 0.05 + 0.05 * float(result.latent[0, 0])
    assert result.losses[-1] < result.losses[0]
    assert true_radius_m - 0.005 < radius_after < 0.05 - 0.005


def test_patience_stops_where_the_objective_stops_improving_and_keeps_the_best() -> None:
    """Steps far too long (lr 1 against an anchor 0.01 away) only ever overshoot: ``patience``
    updates later the refinement stops and returns the start, with its volume; None runs every
    step and returns the last latent."""
    decoder = TinyDecoder().eval()
    latent = torch.randn(1, 200, generator=torch.Generator().manual_seed(3))
    overshoot = {
        "constraints": VoxelConstraints.none(N),
        "learning_rate": 1.0,
        "iterations": 15,
        "anchor_latent": latent + 0.01,
        "anchor_weight": 1.0,
    }
    every = refine_latent(decoder, latent, **overshoot)
    assert len(every.losses) == 16 and min(every.losses[1:]) > every.losses[0]
    assert not torch.equal(every.latent, latent)
    held = refine_latent(decoder, latent, **overshoot, patience=3)
    assert held.losses == every.losses[:4]  # the start, then 3 updates that did not improve
    torch.testing.assert_close(held.latent, latent)
    torch.testing.assert_close(held.voxels, decoder(latent).detach())
    # While the objective keeps falling, patience changes nothing.
    free = refine_latent(decoder, latent, _constraints(), 1e-2, iterations=10)
    assert all(b < a for a, b in zip(free.losses, free.losses[1:], strict=False))
    patient = refine_latent(decoder, latent, _constraints(), 1e-2, iterations=10, patience=3)
    torch.testing.assert_close(patient.latent, free.latent)
    assert patient.losses == free.losses
    with pytest.raises(ValueError, match="patience"):
        refine_latent(decoder, latent, _constraints(), patience=0)


def test_a_stop_pulls_only_its_most_probable_voxel_and_none_once_one_is_inside() -> None:
    """A stop without an imprint: one of its voxels is occupied, which one is not known. The
    threshold loss pulls the group's most probable voxel up to 0.5, counted with the occupied
    voxels, and nothing once any of them is inside."""
    group = np.ravel_multi_index(([1, 2, 3], [1, 1, 1], [1, 1, 1]), (N, N, N))
    stopped = VoxelConstraints(N, np.zeros(0, np.int64), np.zeros(0, np.int64), (group,))
    voxels = torch.full((N, N, N), 0.1, dtype=torch.float64)
    voxels.reshape(-1)[group] = torch.tensor([0.2, 0.3, 0.1], dtype=torch.float64)
    voxels.requires_grad_(True)
    loss = touch_loss(voxels, stopped, "threshold")
    (gradient,) = torch.autograd.grad(loss, voxels)
    assert float(loss.detach()) == pytest.approx(0.2**2)  # 0.5 - 0.3: the most probable
    expected = torch.zeros(N**3, dtype=torch.float64)
    expected[group[1]] = -2 * 0.2
    torch.testing.assert_close(gradient.reshape(-1), expected)
    inside = voxels.detach().clone()
    inside.reshape(-1)[group[2]] = 0.7
    assert float(touch_loss(inside, stopped, "threshold")) == 0.0


def test_a_stop_grows_a_too_small_sphere_to_reach_the_tool() -> None:
    """End to end: a sphere predicted 1 cm too small; the fingers stopped by force 4 cm from its
    centre, on the tool's leading points, without an imprint. The stop's group makes the latent
    grow the sphere to reach them; the sweep alone (its free space) does not."""
    grid, centre_world = SPHERE_GRID, SPHERE_CENTRE_WORLD
    sphere_decoder = _sphere_decoder(0.03)  # latent 0 -> 3 cm, 1 cm too small

    direction = np.array([-1.0, 0.0, 0.0])
    start = make_transform(frame_from_z_axis(direction), centre_world + np.array([0.1, 0.0, 0.0]))
    stop = make_transform(frame_from_z_axis(direction), centre_world + np.array([0.045, 0.0, 0.0]))
    starts = pad_grid_world(start, (0.019, 0.014), 0.002)
    ends = pad_grid_world(stop, (0.019, 0.014), 0.002)
    radii = {}
    stop_points = ends + 0.005 * direction
    for name, stop in (("stop", (stop_points, [direction] * len(ends))), ("sweep", ())):
        touch = TouchResult.from_miss(starts, ends, *stop)
        constraints = constraints_from_touches([touch], grid)
        assert len(constraints.any_occupied) == (name == "stop")
        result = refine_latent(
            sphere_decoder, torch.zeros(1, 200), constraints, 0.02, 20, loss="threshold"
        )
        radii[name] = 0.03 + 0.05 * float(result.latent[0, 0])
    assert radii["sweep"] == pytest.approx(0.03, abs=0.001)
    assert radii["stop"] > 0.04
