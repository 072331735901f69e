"""Post-hoc calibration of the shape net's voxel probabilities (Platt scaling).

Trained briefly with the paper's plain BCE, the shape net ranks voxels well but under-states
occupancy: voxels are mostly empty, so early in training the occupied ones sit near the decoder's
output bias (probability about 0.35) and nothing reaches 0.5. Platt scaling fits
``p = sigmoid(a * logit + b)`` by BCE on sketches *predicted* by the sketch net (the deployed
pipeline); ``b`` is then shifted (within +-3) to the value whose 0.5 threshold maximises the mean
voxel IoU on the same views (the decision threshold the metrics use). Both are folded into the
decoder's last transposed convolution, so the network keeps its architecture and
``decode(latent)`` returns the calibrated probabilities that the touch policy's confidence
``|v - 0.5|`` reads.
"""

from __future__ import annotations

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


def fit_platt(logits: torch.Tensor, truth: torch.Tensor, steps: int = 100) -> tuple[float, float]:
    """Scale a and offset b minimising BCE of sigmoid(a * logit + b) against 0/1 ``truth``."""
    flat_logits, flat_truth = logits.flatten(), truth.flatten()
    params = torch.tensor([1.0, 0.0], requires_grad=True)
    optimizer = torch.optim.LBFGS([params], lr=0.5, max_iter=steps, line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        optimizer.zero_grad()
        loss = F.binary_cross_entropy_with_logits(params[0] * flat_logits + params[1], flat_truth)
        loss.backward()
        return loss

    optimizer.step(closure)
    scale, offset = params.detach().tolist()
    return scale, offset


@torch.no_grad()
def iou_offset(
    logits: torch.Tensor, truth: torch.Tensor, scale: float, offset: float, span: float = 3.0
) -> float:
    """The offset (near ``offset``, within +-``span``) whose 0.5 threshold maximises the mean
    voxel IoU of ``sigmoid(scale * logit + offset)``: the decision threshold, folded into b."""
    scaled = (scale * logits).flatten(1)
    occupied = truth.flatten(1) > 0.5

    def mean_iou(candidate: float) -> float:
        predicted = scaled + candidate >= 0
        intersection = (predicted & occupied).sum(1).float()
        union = (predicted | occupied).sum(1).float().clamp(min=1)
        return float((intersection / union).mean())

    candidates = [offset + span * (k / 30.0 - 1.0) for k in range(61)]
    return max(candidates, key=mean_iou)


@torch.no_grad()
def fold_platt(shape_net: ShapeNet, scale: float, offset: float) -> None:
    """Make the decoder output ``scale * logit + offset`` by rescaling its last layer in place."""
    last = shape_net.decoder.layers[-1]
    if not isinstance(last, nn.ConvTranspose3d) or last.bias is None:
        raise TypeError("the decoder must end in a ConvTranspose3d with a bias")
    last.weight.mul_(scale)
    last.bias.mul_(scale).add_(offset)
