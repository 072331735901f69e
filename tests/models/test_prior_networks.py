"""Tensor shapes through both networks for both presets, and the differentiable decoder."""

from __future__ import annotations

import pytest
import torch

from models.prior.networks import (
    LATENT_DIM,
    PRESETS,
    FrozenVoxelDecoder,
    NetworkPreset,
    ResNet18Encoder,
    ShapeNet,
    SketchNet,
    get_preset,
    normalise_rgb,
    shape_input,
)


@pytest.mark.parametrize("name", ["cpu", "cpu_wide", "paper"])
def test_sketch_and_shape_net_shapes(name: str) -> None:
    torch.manual_seed(0)
    preset = get_preset(name)
    size, n = preset.image_size, preset.voxel_resolution
    sketch, shape = SketchNet(preset).eval(), ShapeNet(preset).eval()
    rgb = torch.randint(0, 256, (1, 3, size, size), dtype=torch.uint8)
    with torch.no_grad():
        features = sketch.encoder(normalise_rgb(rgb))
        assert features.shape == (1, 8 * preset.encoder_width, size // 32, size // 32)
        bridge = sketch.bridge(features)
        assert bridge.shape == (1, preset.sketch_widths[0], size // 16, size // 16)
        out = sketch(normalise_rgb(rgb))
        assert out["depth"].shape == (1, 1, size, size)
        assert out["normals"].shape == (1, 3, size, size)
        assert out["silhouette_logits"].shape == (1, 1, size, size)
        inputs = shape_input(out["depth"], out["normals"], (out["silhouette_logits"] > 0).float())
        assert inputs.shape == (1, 4, size, size)
        latent = shape.encode(inputs)
        assert latent.shape == (1, LATENT_DIM)
        voxels = shape.decode(latent)
    assert voxels.shape == (1, n, n, n)
    assert float(voxels.min()) >= 0.0 and float(voxels.max()) <= 1.0


def test_paper_preset_matches_the_paper() -> None:
    paper = PRESETS["paper"]
    assert (paper.image_size, paper.voxel_resolution) == (256, 128)
    assert paper.sketch_widths[0] == 384  # 384 maps of 16x16 from a 256x256 image
    assert len(paper.shape_widths) == 5  # five ConvTranspose3d + BN + ReLU sets
    assert ResNet18Encoder(3, 64).out_channels == 512


def test_decode_is_differentiable_in_the_latent() -> None:
    torch.manual_seed(0)
    shape = ShapeNet(get_preset("cpu")).eval()
    latent = torch.randn(1, LATENT_DIM, requires_grad=True)
    shape.decode(latent)[0, 10:20, 10:20, 0:10].sum().backward()
    assert latent.grad is not None and float(latent.grad.abs().sum()) > 0


@pytest.mark.parametrize("name", ["cpu", "cpu_wide"])
def test_the_frozen_decoder_gives_the_decoders_logits_and_latent_gradient(name: str) -> None:
    torch.manual_seed(0)
    shape = ShapeNet(get_preset(name))
    for layer in shape.decoder.modules():  # batch norm with statistics of its own, not 0 / 1
        if isinstance(layer, torch.nn.BatchNorm3d):
            layer.running_mean.uniform_(-0.5, 0.5)
            layer.running_var.uniform_(0.5, 2.0)
            layer.weight.data.uniform_(0.5, 1.5)
            layer.bias.data.uniform_(-0.2, 0.2)
    shape.eval()
    frozen = FrozenVoxelDecoder(shape.decoder)
    latent = torch.randn(2, LATENT_DIM)
    with torch.no_grad():
        expected = shape.decoder(latent)
    assert torch.allclose(frozen(latent), expected, atol=1e-4 * float(expected.abs().max()))
    weights = torch.rand_like(expected[:1])
    gradients = []
    for decoder in (shape.decoder, frozen):
        variable = latent[:1].clone().requires_grad_(True)
        (torch.sigmoid(decoder(variable)) * weights).sum().backward()
        gradients.append(variable.grad)
    assert torch.allclose(gradients[1], gradients[0], rtol=1e-4, atol=1e-6)
    assert not any(buffer.requires_grad for buffer in frozen.buffers())


def test_bad_presets_are_rejected() -> None:
    with pytest.raises(ValueError, match="unknown network preset"):
        get_preset("huge")
    with pytest.raises(ValueError, match="shape_widths"):
        NetworkPreset("x", 128, 64, 32, (8, 8, 8, 8, 8), (8, 8))
