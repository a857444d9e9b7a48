"""The paper's 1D, 2D and 3D convolutional encoders and decoders (architecture tables of Section III).

:class:`ConvEncoder` is E_phi without the parameter residual and :class:`ConvDecoder` is G_psi; the
residual embedding is added by :class:`ParametricEncoder` (z = E_phi(x) + s) and by the latent model
before decoding (G_psi(z + s)), so the embedding is one shared module counted in the encoder.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from .embedding import ParameterEmbedding
from .presets import BackboneSpec, BenchmarkShape

_CONV = {1: nn.Conv1d, 2: nn.Conv2d, 3: nn.Conv3d}
_DECONV = {1: nn.ConvTranspose1d, 2: nn.ConvTranspose2d, 3: nn.ConvTranspose3d}
_UPSAMPLE_MODE = {1: "linear", 2: "bilinear", 3: "trilinear"}
_STRIDE = 2


def _fc_stack(widths: list[int]) -> nn.Sequential:
    """Linear layers through ``widths`` with GELU between them (none after the last)."""
    layers: list[nn.Module] = []
    for i, (n_in, n_out) in enumerate(zip(widths[:-1], widths[1:])):
        if i > 0:
            layers.append(nn.GELU())
        layers.append(nn.Linear(n_in, n_out))
    return nn.Sequential(*layers)


def _bottleneck_grid(shape: BenchmarkShape, spec: BackboneSpec) -> tuple[int, ...]:
    factor = _STRIDE ** len(spec.conv_channels)
    for n in shape.grid:
        if n % factor:
            raise ValueError(
                f"grid {shape.grid} is not divisible by {factor}, which {len(spec.conv_channels)} stride-2 "
                "convolutions need"
            )
    return tuple(n // factor for n in shape.grid)


class ConvEncoder(nn.Module):
    """E_phi: strided convolutions, flatten, fully connected layers to r (no parameter residual)."""

    def __init__(self, shape: BenchmarkShape, spec: BackboneSpec, r: int) -> None:
        super().__init__()
        conv = _CONV[shape.ndim]
        channels = [shape.in_channels, *spec.conv_channels]
        layers: list[nn.Module] = []
        for i, (c_in, c_out) in enumerate(zip(channels[:-1], channels[1:])):
            layers.append(conv(c_in, c_out, spec.kernel_size, stride=_STRIDE, padding=spec.padding))
            if i < len(spec.conv_channels) - 1 or spec.act_after_last_conv:
                layers.append(nn.GELU())
        self.conv = nn.Sequential(*layers)
        n_flat = spec.conv_channels[-1] * math.prod(_bottleneck_grid(shape, spec))
        self.fc = _fc_stack([n_flat, *spec.fc_widths, r])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C_in, *grid) normalized input -> (B, r)."""
        return self.fc(self.conv(x).flatten(1))


class ConvDecoder(nn.Module):
    """G_psi: fully connected layers from r, reshape, then upsampling/transposed convolutions to the grid."""

    def __init__(self, shape: BenchmarkShape, spec: BackboneSpec, r: int) -> None:
        super().__init__()
        self.ndim = shape.ndim
        self.mode = spec.decoder_mode
        self.bottleneck = (spec.conv_channels[-1], *_bottleneck_grid(shape, spec))
        self.fc = _fc_stack([r, *reversed(spec.fc_widths), math.prod(self.bottleneck)])
        deconv = _DECONV[shape.ndim]
        channels = [*reversed(spec.conv_channels), shape.out_channels]
        self.deconv = nn.ModuleList()
        for c_in, c_out in zip(channels[:-1], channels[1:]):
            if self.mode == "upsample":  # size-preserving: the interpolation does the x2
                layer = deconv(c_in, c_out, spec.kernel_size, stride=1, padding=spec.padding)
            else:
                layer = deconv(
                    c_in, c_out, spec.kernel_size, stride=_STRIDE, padding=spec.padding, output_padding=1
                )
            self.deconv.append(layer)
        self.act = nn.GELU()

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        """(B, r) -> (B, C_out, *grid) normalized output."""
        h = self.fc(z).view(z.shape[0], *self.bottleneck)
        for i, layer in enumerate(self.deconv):
            if self.mode == "upsample":
                h = nn.functional.interpolate(h, scale_factor=2, mode=_UPSAMPLE_MODE[self.ndim])
            h = layer(h)
            if i < len(self.deconv) - 1:
                h = self.act(h)
        return h


class ParametricEncoder(nn.Module):
    """z = E_phi(x) + e_omega(mu): the encoder owns the embedding, shared with the decoder and latent map."""

    def __init__(self, backbone: ConvEncoder, embedding: ParameterEmbedding) -> None:
        super().__init__()
        self.backbone = backbone
        self.embedding = embedding

    def forward(self, x: torch.Tensor, mu: torch.Tensor) -> torch.Tensor:
        return self.backbone(x) + self.embedding(mu)
