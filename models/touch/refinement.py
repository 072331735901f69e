"""Touch refinement: the paper's differentiable touch loss back-propagated into the shape latent.

For constrained voxels the loss is ``v^2`` where a touch proved the voxel empty (in front of a
contact along the approach ray, or anywhere on a missed stroke) and ``(1 - v)^2`` at a contact
voxel, summed over the constrained voxels of all touches so far; its gradient is ``2 v`` and
``2 (v - 1)``. The latent is updated by Adam with the paper's learning rate 0.001 for 10
iterations per touch (both configurable: ``ModelsConfig.refine_learning_rate`` and
``refine_iterations_per_touch``). Why Adam: the paper gives only "a learning rate of 0.001",
which is Adam's customary default; plain SGD at that rate would move the latent by an amount
tied to the arbitrary scale of the summed loss and of the decoder's Jacobian, while Adam moves
each latent coordinate by about ``lr`` per step whatever the number of constrained voxels. SGD
stays available (``optimizer="sgd"``). See docs/touch.md.

Direct Edit, the paper's baseline without a prior, writes the constraints into the voxels.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from numpy.typing import ArrayLike, NDArray
from torch import Tensor

from models.touch.constraints import VoxelConstraints

Decode = Callable[[Tensor], Tensor]
"""latent (e.g. (1, 200), or (200,) for ``ShapePrior.decode``) -> occupancy probabilities in
(0, 1), shape (N, N, N) or (1, N, N, N), indexed [i, j, k] in the VoxelGrid frame, differentiable
in the latent. A decoder with batch norm must be in eval mode: a batch of one has no batch
statistics."""


def decode_volume(decode: Decode, latent: Tensor) -> Tensor:
    """``decode(latent)`` as an (N, N, N) tensor (a leading batch axis of one is dropped)."""
    voxels = decode(latent)
    if voxels.dim() == 4 and voxels.shape[0] == 1:
        voxels = voxels[0]
    if voxels.dim() != 3 or len(set(voxels.shape)) != 1:
        raise ValueError(f"decoder must return an (N, N, N) volume, got {tuple(voxels.shape)}")
    return voxels


TouchLossKind = Literal["sum", "balanced", "threshold"]


def touch_loss(
    voxels: Tensor, constraints: VoxelConstraints, kind: TouchLossKind = "sum"
) -> Tensor:
    """The paper's touch loss: v^2 over empty voxels and (1 - v)^2 over occupied ones (and
    over the most probable voxel of each ``any_occupied`` group, whose one occupied voxel is
    not known).

    ``"sum"``: summed over all constrained voxels, as the paper writes it. ``"balanced"``: the
    mean over the empty voxels plus the mean over the occupied ones. A touch proves ~10 voxels
    empty in front of every contact voxel, so in the sum the cheapest way down is to empty the
    shape: the latent shrinks or thins it instead of moving its surface to the contacts.
    ``"threshold"``: balanced, but a voxel stops pulling once it is on the right side of the
    surface (v <= 0.5 for empty, v >= 0.5 for occupied): max(0, v - 0.5)^2 and
    max(0, 0.5 - v)^2. The prior cannot raise a few contact voxels to 1 without growing the
    whole shape around them (the decoder couples neighbouring voxels), so pulling them past the
    surface only inflates the shape (docs/explore.md).
    """
    if voxels.shape != (constraints.resolution,) * 3:
        raise ValueError(
            f"volume {tuple(voxels.shape)} does not match constraints at {constraints.resolution}^3"
        )
    flat = voxels.reshape(-1)
    empty_v = flat[torch.from_numpy(constraints.empty).to(voxels.device)]
    occupied_v = flat[torch.from_numpy(constraints.occupied).to(voxels.device)]
    # A group of which one voxel is occupied pulls on its most probable voxel only.
    any_v = (
        torch.stack(
            [
                flat[torch.from_numpy(group).to(voxels.device)].max()
                for group in constraints.any_occupied
            ]
        )
        if constraints.any_occupied
        else flat.new_zeros(0)
    )
    if kind == "threshold":
        empty, occupied = torch.relu(empty_v - 0.5) ** 2, torch.relu(0.5 - occupied_v) ** 2
        any_occupied = torch.relu(0.5 - any_v) ** 2
    else:
        empty, occupied, any_occupied = empty_v**2, (1.0 - occupied_v) ** 2, (1.0 - any_v) ** 2
    if kind == "sum":
        return empty.sum() + occupied.sum() + any_occupied.sum()
    if kind in ("balanced", "threshold"):
        # The groups count with the occupied voxels: each is one more voxel proven occupied.
        occupied = torch.cat([occupied, any_occupied])
        return sum(
            (terms.mean() for terms in (empty, occupied) if terms.numel()), flat.new_zeros(())
        )
    raise ValueError(f"unknown touch loss {kind!r}; expected 'sum', 'balanced' or 'threshold'")


@dataclass(frozen=True)
class RefinementResult:
    """Refined latent (shape as given), its decoded volume (N, N, N) and the loss before each
    update plus after the last one (iterations + 1 values; fewer where ``patience`` stopped
    early, and then the latent is the best one evaluated)."""

    latent: Tensor
    voxels: Tensor
    losses: list[float]


def refine_latent(
    decode: Decode,
    latent: Tensor,
    constraints: VoxelConstraints,
    learning_rate: float = 1e-3,
    iterations: int = 10,
    optimizer: Literal["adam", "sgd"] = "adam",
    loss: TouchLossKind = "sum",
    anchor_latent: Tensor | None = None,
    anchor_weight: float = 0.0,
    patience: int | None = None,
) -> RefinementResult:
    """Update the latent so the decoded shape agrees with the touches (the paper's refinement).

    Pass the constraints of all touches so far and the latent from the previous refinement (or
    the vision estimate). The decoder's parameters are left untouched: only the latent's
    gradient is computed. Returns detached tensors.

    ``patience``: stop once this many updates in a row have not lowered the objective below
    the best evaluated so far, and return that best latent (and its volume, already decoded).
    A refinement started where the touches are explained already (a warm start from the last
    touch's fit) then costs a few decodes instead of ``iterations``. None: every iteration,
    the last latent.
    """
    if iterations < 0 or learning_rate <= 0 or anchor_weight < 0:
        raise ValueError("iterations and anchor_weight must be >= 0 and learning_rate positive")
    if patience is not None and patience < 1:
        raise ValueError("patience must be >= 1 (or None)")
    if anchor_weight > 0 and anchor_latent is None:
        raise ValueError("anchor_weight needs an anchor_latent")
    anchor = None if anchor_latent is None else anchor_latent.detach().reshape(latent.shape)

    def objective(voxels: Tensor, variable: Tensor) -> Tensor:
        value = touch_loss(voxels, constraints, loss)
        if anchor is not None and anchor_weight > 0:
            value = value + anchor_weight * ((variable - anchor) ** 2).sum()
        return value

    variable = latent.detach().clone().requires_grad_(True)
    if optimizer == "adam":
        step: torch.optim.Optimizer = torch.optim.Adam([variable], lr=learning_rate)
    elif optimizer == "sgd":
        step = torch.optim.SGD([variable], lr=learning_rate)
    else:
        raise ValueError(f"unknown optimizer {optimizer!r}; expected 'adam' or 'sgd'")
    losses: list[float] = []
    best: tuple[float, Tensor, Tensor] | None = None  # objective, latent, volume
    stale = 0
    with torch.enable_grad():
        for _ in range(iterations):
            voxels = decode_volume(decode, variable)
            value = objective(voxels, variable)
            losses.append(float(value.detach()))
            if patience is not None:
                if best is None or losses[-1] < best[0]:
                    best, stale = (losses[-1], variable.detach().clone(), voxels.detach()), 0
                else:
                    stale += 1
                    if stale >= patience:
                        return RefinementResult(best[1], best[2], losses)
            (variable.grad,) = torch.autograd.grad(value, variable)
            step.step()
    with torch.no_grad():
        voxels = decode_volume(decode, variable)
        losses.append(float(objective(voxels, variable)))
    if best is not None and best[0] <= losses[-1]:
        return RefinementResult(best[1], best[2], losses)
    return RefinementResult(variable.detach(), voxels.detach(), losses)


def direct_edit(voxels: ArrayLike, constraints: VoxelConstraints) -> NDArray[np.float32]:
    """The Direct Edit baseline: a copy with empty voxels set to 0 and occupied voxels to 1.

    Apply it to the vision estimate with the constraints of all touches so far.
    """
    edited = np.array(voxels, dtype=np.float32, copy=True)
    if edited.shape != (constraints.resolution,) * 3:
        raise ValueError(
            f"volume {edited.shape} does not match constraints at {constraints.resolution}^3"
        )
    flat = edited.reshape(-1)
    flat[constraints.empty] = 0.0
    flat[constraints.occupied] = 1.0
    return edited
