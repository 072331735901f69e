"""The paper's two networks: the 2.5D sketch estimator and the 3D shape estimator (MarrNet-style).

Both have a ResNet-18 encoder written here (torchvision does not import on this machine). Width
and resolution come from a :class:`NetworkPreset`:

* ``paper``: 256x256 RGB -> ResNet-18 (widths 64..512) -> 384 maps of 16x16 -> three branches of
  four 5x5 stride-2 transposed conv + BN + ReLU sets and a 1x1 conv (depth, normals, silhouette at
  256x256); shape net: masked depth + normals -> modified ResNet-18 (adaptive average pooling,
  last linear to 200) -> 200-d latent -> five ConvTranspose3d + BN + ReLU sets
  (512@4^3 ... 32@64^3), one ConvTranspose3d and a sigmoid -> 128^3 voxels.
* ``cpu``: the same topology at 128x128 input and 64^3 voxels with narrower layers (one 3D set
  fewer, since 64^3 needs one upsampling fewer), sized to train on two CPU cores.
* ``cpu_wide``: ``cpu`` with a voxel decoder twice as wide (256@4^3 ... 32@32^3; the sketch net is
  the same, so ``cpu`` sketch weights load into it): the capacity experiment on the shape net's
  ~0.64 validation-IoU plateau (docs/prior.md).

Sketch conventions (all images are crops from :mod:`models.prior.virtual_camera`,
H = W = image_size): depth is "nearness" ``1 + (z_ref - z) / extent_m`` inside the silhouette and
0 outside (z the camera z-depth, z_ref the z-depth of the voxel grid's centre, extent_m the grid
edge), normals are unit camera-frame (OpenCV) normals, 0 outside, and the silhouette is a logit
map.
Voxel outputs are indexed [i, j, k] in the :class:`models.geometry.VoxelGrid` frame.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

LATENT_DIM = 200
"""Size of the shape latent code (the paper's 200-d vector that touch refinement optimises)."""


@dataclass(frozen=True)
class NetworkPreset:
    """Sizes of both networks. Widths are channel counts; resolutions are pixels / voxels."""

    name: str
    image_size: int
    """Square input crop, pixels (the sketches come out at the same size)."""
    voxel_resolution: int
    """Voxels per edge of the output cube."""
    encoder_width: int
    """Channels of the first ResNet-18 stage (64 in ResNet-18); stages double it."""
    sketch_widths: tuple[int, int, int, int, int]
    """Bridge channels (384 in the paper), then the four transposed-conv sets of each branch."""
    shape_widths: tuple[int, ...]
    """Channels of the 3D decoder sets, one per set from 4^3 up to voxel_resolution / 2."""

    def __post_init__(self) -> None:
        if self.image_size % 32 or self.image_size < 64:
            raise ValueError("image_size must be a multiple of 32, at least 64")
        sets = round(math.log2(self.voxel_resolution / 4))
        if 4 * 2**sets != self.voxel_resolution or sets < 1:
            raise ValueError("voxel_resolution must be 4 * 2^n with n >= 1")
        if len(self.shape_widths) != sets:
            raise ValueError(f"{self.voxel_resolution}^3 voxels need {sets} shape_widths")


PRESETS: dict[str, NetworkPreset] = {
    "paper": NetworkPreset(
        name="paper",
        image_size=256,
        voxel_resolution=128,
        encoder_width=64,
        sketch_widths=(384, 384, 384, 192, 96),
        shape_widths=(512, 256, 128, 64, 32),
    ),
    "cpu": NetworkPreset(
        name="cpu",
        image_size=128,
        voxel_resolution=64,
        encoder_width=32,
        sketch_widths=(96, 64, 48, 24, 12),
        shape_widths=(128, 64, 32, 16),
    ),
    "cpu_wide": NetworkPreset(
        name="cpu_wide",
        image_size=128,
        voxel_resolution=64,
        encoder_width=32,
        sketch_widths=(96, 64, 48, 24, 12),
        shape_widths=(256, 128, 64, 32),
    ),
}


def get_preset(name: str) -> NetworkPreset:
    """The preset called ``name``; a clear error lists the known ones."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(
            f"unknown network preset {name!r}; expected one of {list(PRESETS)}"
        ) from None


# --- ResNet-18 ------------------------------------------------------------------------------------


class BasicBlock(nn.Module):
    """ResNet basic block: two 3x3 conv + BN, identity (or 1x1 projection) shortcut."""

    def __init__(self, in_channels: int, out_channels: int, stride: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_channels, out_channels, 3, stride, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(out_channels)
        self.conv2 = nn.Conv2d(out_channels, out_channels, 3, 1, 1, bias=False)
        self.bn2 = nn.BatchNorm2d(out_channels)
        self.shortcut: nn.Module = nn.Identity()
        if stride != 1 or in_channels != out_channels:
            self.shortcut = nn.Sequential(
                nn.Conv2d(in_channels, out_channels, 1, stride, bias=False),
                nn.BatchNorm2d(out_channels),
            )

    def forward(self, x: Tensor) -> Tensor:
        out = torch.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return torch.relu(out + self.shortcut(x))


class ResNet18Encoder(nn.Module):
    """ResNet-18 feature extractor: (B, C, H, W) -> (B, 8 * width, H / 32, W / 32)."""

    def __init__(self, in_channels: int, width: int = 64) -> None:
        super().__init__()
        self.stem = nn.Sequential(
            nn.Conv2d(in_channels, width, 7, 2, 3, bias=False),
            nn.BatchNorm2d(width),
            nn.ReLU(inplace=True),
            nn.MaxPool2d(3, 2, 1),
        )
        stages = []
        channels = width
        for index in range(4):
            out = width * 2**index
            stride = 1 if index == 0 else 2
            stages.append(nn.Sequential(BasicBlock(channels, out, stride), BasicBlock(out, out, 1)))
            channels = out
        self.stages = nn.Sequential(*stages)
        self.out_channels = channels

    def forward(self, x: Tensor) -> Tensor:
        return self.stages(self.stem(x))


def _up2d(in_channels: int, out_channels: int) -> nn.Sequential:
    """5x5 stride-2 transposed conv + BN + ReLU: doubles H and W exactly."""
    return nn.Sequential(
        nn.ConvTranspose2d(in_channels, out_channels, 5, 2, 2, output_padding=1, bias=False),
        nn.BatchNorm2d(out_channels),
        nn.ReLU(inplace=True),
    )


# --- 2.5D sketch estimator ------------------------------------------------------------------------


def normalise_rgb(rgb: Tensor) -> Tensor:
    """uint8-range (0..255) or 0..1 float RGB (B, 3, H, W) -> zero-centred network input."""
    if rgb.dtype == torch.uint8:
        rgb = rgb.float() / 255.0
    return (rgb - 0.5) / 0.25


class SketchNet(nn.Module):
    """RGB crop -> 2.5D sketches: depth (nearness), camera-frame normals, silhouette logits."""

    def __init__(self, preset: NetworkPreset) -> None:
        super().__init__()
        self.preset = preset
        bridge, *branch = preset.sketch_widths
        self.encoder = ResNet18Encoder(3, preset.encoder_width)
        self.bridge = _up2d(self.encoder.out_channels, bridge)

        def branch_head(out_channels: int) -> nn.Sequential:
            layers, channels = [], bridge
            for width in branch:
                layers.append(_up2d(channels, width))
                channels = width
            layers.append(nn.Conv2d(channels, out_channels, 1))
            return nn.Sequential(*layers)

        self.depth_head = branch_head(1)
        self.normals_head = branch_head(3)
        self.silhouette_head = branch_head(1)

    def forward(self, rgb: Tensor) -> dict[str, Tensor]:
        """``rgb`` (B, 3, S, S) as from :func:`normalise_rgb` -> dict of (B, C, S, S) maps:
        ``depth`` (C=1), ``normals`` (C=3), ``silhouette_logits`` (C=1)."""
        features = self.bridge(self.encoder(rgb))
        return {
            "depth": self.depth_head(features),
            "normals": self.normals_head(features),
            "silhouette_logits": self.silhouette_head(features),
        }


# --- 3D shape estimator ---------------------------------------------------------------------------


def shape_input(depth: Tensor, normals: Tensor, silhouette: Tensor) -> Tensor:
    """The shape net's input: depth (B,1,S,S) and normals (B,3,S,S) masked by a 0/1 silhouette."""
    return torch.cat([depth, normals], dim=1) * silhouette


class VoxelDecoder(nn.Module):
    """200-d latent -> voxel logits (B, N, N, N): k4 s1 transposed conv to 4^3, k4 s2 sets after."""

    def __init__(self, preset: NetworkPreset) -> None:
        super().__init__()
        widths = preset.shape_widths
        layers: list[nn.Module] = [
            nn.ConvTranspose3d(LATENT_DIM, widths[0], 4, 1, 0, bias=False),
            nn.BatchNorm3d(widths[0]),
            nn.ReLU(inplace=True),
        ]
        for in_channels, out_channels in itertools.pairwise(widths):
            layers += [
                nn.ConvTranspose3d(in_channels, out_channels, 4, 2, 1, bias=False),
                nn.BatchNorm3d(out_channels),
                nn.ReLU(inplace=True),
            ]
        layers.append(nn.ConvTranspose3d(widths[-1], 1, 4, 2, 1))
        self.layers = nn.Sequential(*layers)

    def forward(self, latent: Tensor) -> Tensor:
        return self.layers(latent[:, :, None, None, None])[:, 0]


def _transposed_conv_k4s2(volume: Tensor, weight: Tensor) -> Tensor:
    """``F.conv_transpose3d(volume, weight, stride=2, padding=1)`` for a 4^3 kernel, as one matrix
    product and an overlap-add of its 64 taps. On one CPU thread, with one channel out (the
    decoder's last layer, 32^3 -> 64^3), this is ~3x faster than torch's; with more channels out
    the overlap-add costs more than torch's own."""
    batch, channels_in, n = volume.shape[0], volume.shape[1], volume.shape[-1]
    channels_out = weight.shape[1]
    taps = weight.reshape(channels_in, channels_out * 64).t() @ volume.reshape(
        batch, channels_in, n**3
    )
    taps = taps.reshape(batch, channels_out, 4, 4, 4, n, n, n)
    out = volume.new_zeros(batch, channels_out, 2 * n + 2, 2 * n + 2, 2 * n + 2)
    for a, b, c in itertools.product(range(4), repeat=3):
        out[:, :, a : a + 2 * n : 2, b : b + 2 * n : 2, c : c + 2 * n : 2] += taps[:, :, a, b, c]
    return out[:, :, 1:-1, 1:-1, 1:-1]


class _TransposedConvK4S2(torch.autograd.Function):
    """:func:`_transposed_conv_k4s2`, differentiable in its input only: the backward pass is the
    strided convolution the transposed one is the adjoint of."""

    @staticmethod
    def forward(ctx: torch.autograd.function.FunctionCtx, volume: Tensor, weight: Tensor) -> Tensor:
        ctx.save_for_backward(weight)
        return _transposed_conv_k4s2(volume, weight)

    @staticmethod
    def backward(ctx: torch.autograd.function.FunctionCtx, grad: Tensor) -> tuple[Tensor, None]:
        (weight,) = ctx.saved_tensors  # type: ignore[attr-defined]
        return nn.functional.conv3d(grad, weight, stride=2, padding=1), None


class FrozenVoxelDecoder(nn.Module):
    """A trained :class:`VoxelDecoder` in eval mode, for inference and latent refinement: the
    same logits (to float rounding), differentiable in the latent only, faster on a CPU.

    Batch norm is folded into the transposed convolutions before it, the first one (from a
    1^3 latent) is a matrix product and the last one (one channel out) runs as
    :func:`_transposed_conv_k4s2`. Why: every touch's global step decodes the latent and its
    gradient 16 times, and torch's last transposed convolution took half of each decode
    (docs/touch.md, "Cost").
    """

    def __init__(self, decoder: VoxelDecoder) -> None:
        super().__init__()
        layers = [layer for layer in decoder.layers if not isinstance(layer, nn.ReLU)]
        weights, biases = [], []
        for index, layer in enumerate(layers):
            if not isinstance(layer, nn.ConvTranspose3d):
                continue
            weight = layer.weight.detach().clone()
            bias = (
                layer.bias.detach().clone()
                if layer.bias is not None
                else weight.new_zeros(weight.shape[1])
            )
            if index + 1 < len(layers) and isinstance(layers[index + 1], nn.BatchNorm3d):
                norm = layers[index + 1]
                assert norm.running_mean is not None and norm.running_var is not None
                scale = norm.weight.detach() / torch.sqrt(norm.running_var + norm.eps)
                weight = weight * scale[None, :, None, None, None]
                bias = (bias - norm.running_mean) * scale + norm.bias.detach()
            weights.append(weight)
            biases.append(bias)
        first = weights[0]
        self.first_weight: Tensor
        self.register_buffer("first_weight", first.reshape(first.shape[0], -1).contiguous())
        self.first_shape = (first.shape[1], *first.shape[2:])
        for index, (weight, bias) in enumerate(zip(weights, biases, strict=True)):
            if index > 0:
                self.register_buffer(f"weight_{index}", weight.contiguous())
            self.register_buffer(f"bias_{index}", bias[None, :, None, None, None].contiguous())
        self.layer_count = len(weights)

    def forward(self, latent: Tensor) -> Tensor:
        """Latent (B, 200) -> voxel logits (B, N, N, N) indexed [i, j, k]."""
        volume = (latent @ self.first_weight).reshape(len(latent), *self.first_shape)
        volume = volume + self.bias_0
        for index in range(1, self.layer_count):
            volume = torch.relu(volume)
            weight = getattr(self, f"weight_{index}")
            if weight.shape[1] == 1:  # the last layer: torch's is slowest with one channel out
                volume = _TransposedConvK4S2.apply(volume, weight)
            else:
                volume = nn.functional.conv_transpose3d(volume, weight, stride=2, padding=1)
            volume = volume + getattr(self, f"bias_{index}")
        return volume[:, 0]


class ShapeNet(nn.Module):
    """Masked depth + normals -> 200-d latent -> voxel occupancy of the registered grid."""

    def __init__(self, preset: NetworkPreset) -> None:
        super().__init__()
        self.preset = preset
        self.encoder = ResNet18Encoder(4, preset.encoder_width)
        self.pool = nn.AdaptiveAvgPool2d(1)
        self.to_latent = nn.Linear(self.encoder.out_channels, LATENT_DIM)
        self.decoder = VoxelDecoder(preset)

    def encode(self, sketch_input: Tensor) -> Tensor:
        """(B, 4, S, S) from :func:`shape_input` -> latent (B, 200)."""
        return self.to_latent(self.pool(self.encoder(sketch_input)).flatten(1))

    def decode_logits(self, latent: Tensor) -> Tensor:
        """Latent (B, 200) -> voxel logits (B, N, N, N) indexed [i, j, k]."""
        return self.decoder(latent)

    def decode(self, latent: Tensor) -> Tensor:
        """Latent (B, 200) -> occupancy probabilities (B, N, N, N); differentiable in the latent."""
        return torch.sigmoid(self.decoder(latent))

    def forward(self, sketch_input: Tensor) -> Tensor:
        """(B, 4, S, S) -> voxel logits (B, N, N, N)."""
        return self.decode_logits(self.encode(sketch_input))


def parameter_count(module: nn.Module) -> int:
    """Number of parameters."""
    return sum(p.numel() for p in module.parameters())
