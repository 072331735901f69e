"""Platt scaling of the shape net's voxel probabilities, folded into its last layer.

Trained briefly with the paper's plain BCE, the shape net ranks voxels well but under-states
occupancy: voxels are mostly empty, so early in training the occupied ones sit near the decoder's
output bias and nothing reaches 0.5. :class:`PlattScaling` fits ``p = sigmoid(a * logit + b)`` by
BCE on sketches *predicted* by the sketch net (the deployed pipeline); ``b`` is then shifted
(within +-3) to the value whose 0.5 threshold maximises the mean voxel IoU on the same views (the
decision threshold the metrics use). Both are folded into the decoder's last transposed
convolution, so the network keeps its architecture and ``decode(latent)`` returns the scaled
probabilities that the touch policy's confidence ``|v - 0.5|`` reads. See docs/prior.md.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F
from torch import nn

from models.prior.dataset import SketchVoxelDataset
from models.prior.networks import ShapeNet, SketchNet, normalise_rgb
from models.prior.training import predicted_shape_input


@torch.no_grad()
def predicted_logits(
    sketch_net: SketchNet,
    shape_net: ShapeNet,
    dataset: SketchVoxelDataset,
    indices: list[int],
    *,
    batch_size: int = 16,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Voxel logits from predicted sketches and the true voxels, both (len(indices), N, N, N)."""
    sketch_net.eval()
    shape_net.eval()
    logits, truth = [], []
    for start in range(0, len(indices), batch_size):
        items = [dataset[i] for i in indices[start : start + batch_size]]
        rgb = torch.stack([item["rgb"] for item in items])
        prediction = sketch_net(normalise_rgb(rgb))
        logits.append(shape_net(predicted_shape_input(prediction)))
        truth.append(torch.stack([item["voxels"] for item in items]))
    return torch.cat(logits), torch.cat(truth)


@dataclass(frozen=True)
class PlattScaling:
    """``p = sigmoid(scale * logit + offset)``: the shape net's logits rescaled."""

    scale: float = 1.0
    offset: float = 0.0

    @classmethod
    def fit(cls, logits: torch.Tensor, truth: torch.Tensor, steps: int = 100) -> PlattScaling:
        """The scale and offset minimising BCE of the scaled logits against 0/1 ``truth``."""
        flat_logits, flat_truth = logits.flatten(), truth.flatten()
        params = torch.tensor([1.0, 0.0], requires_grad=True)
        optimizer = torch.optim.LBFGS(
            [params], lr=0.5, max_iter=steps, line_search_fn="strong_wolfe"
        )

        def closure() -> torch.Tensor:
            optimizer.zero_grad()
            loss = F.binary_cross_entropy_with_logits(
                params[0] * flat_logits + params[1], flat_truth
            )
            loss.backward()
            return loss

        optimizer.step(closure)
        scale, offset = params.detach().tolist()
        return cls(scale, offset)

    def apply(self, logits: torch.Tensor) -> torch.Tensor:
        """The scaled logits."""
        return self.scale * logits + self.offset

    @torch.no_grad()
    def with_iou_offset(
        self, logits: torch.Tensor, truth: torch.Tensor, span: float = 3.0
    ) -> PlattScaling:
        """The same scale with the offset (within +-``span`` of this one) whose 0.5 threshold
        maximises the mean voxel IoU of the scaled probabilities: the decision threshold."""
        scaled = (self.scale * logits).flatten(1)
        occupied = truth.flatten(1) > 0.5

        def mean_iou(candidate: float) -> float:
            predicted = scaled + candidate >= 0
            intersection = (predicted & occupied).sum(1).float()
            union = (predicted | occupied).sum(1).float().clamp(min=1)
            return float((intersection / union).mean())

        candidates = [self.offset + span * (k / 30.0 - 1.0) for k in range(61)]
        return replace(self, offset=max(candidates, key=mean_iou))

    @torch.no_grad()
    def fold_into(self, shape_net: ShapeNet) -> None:
        """Make the decoder output the scaled logits by rescaling its last layer in place."""
        last = shape_net.decoder.layers[-1]
        if not isinstance(last, nn.ConvTranspose3d) or last.bias is None:
            raise TypeError("the decoder must end in a ConvTranspose3d with a bias")
        last.weight.mul_(self.scale)
        last.bias.mul_(self.scale).add_(self.offset)
