"""Platt scaling of the shape net: fit, IoU offset, folding into the decoder."""

from __future__ import annotations

import pytest
import torch

from models.prior.networks import LATENT_DIM, ShapeNet, get_preset
from models.prior.platt import PlattScaling


def test_platt_fit_recovers_a_known_scaling() -> None:
    generator = torch.Generator().manual_seed(0)
    logits = 3.0 * torch.randn(4, 20_000, generator=generator)
    truth = (torch.rand(4, 20_000, generator=generator) < torch.sigmoid(0.5 * logits + 1.0)).float()
    platt = PlattScaling.fit(logits, truth)
    assert platt.scale == pytest.approx(0.5, abs=0.05)
    assert platt.offset == pytest.approx(1.0, abs=0.1)


def test_iou_offset_moves_the_threshold_onto_the_occupied_voxels() -> None:
    logits = torch.linspace(-4.0, 0.0, 100).repeat(2, 1)  # occupied voxels all below logit 0
    truth = (logits > -1.0).float()
    tuned = PlattScaling().with_iou_offset(logits, truth)
    assert tuned.scale == 1.0
    assert -0.1 < -1.0 + tuned.offset < 0.2  # the 0.5 threshold lands at the boundary (logit -1)


def test_folding_rescales_the_decoder_output() -> None:
    torch.manual_seed(0)
    net = ShapeNet(get_preset("cpu")).eval()
    latent = torch.randn(1, LATENT_DIM)
    platt = PlattScaling(1.7, 2.2)
    with torch.no_grad():
        before = net.decode_logits(latent)
        platt.fold_into(net)
        after = net.decode_logits(latent)
    assert torch.allclose(after, platt.apply(before), atol=1e-4)
    assert torch.allclose(after, 1.7 * before + 2.2, atol=1e-4)
