"""How the backbones' convolutions run: the layer tables per number of axes, the channels-last layout of
training on the CPU, and a stride-1 transposed convolution as the equivalent plain one."""

from __future__ import annotations

import torch
from torch import nn

CONV = {1: nn.Conv1d, 2: nn.Conv2d, 3: nn.Conv3d}
DECONV = {1: nn.ConvTranspose1d, 2: nn.ConvTranspose2d, 3: nn.ConvTranspose3d}
CONV_FN = {1: nn.functional.conv1d, 2: nn.functional.conv2d, 3: nn.functional.conv3d}
DECONV_FN = {1: nn.functional.conv_transpose1d, 2: nn.functional.conv_transpose2d, 3: nn.functional.conv_transpose3d}
UPSAMPLE_MODE = {1: "linear", 2: "bilinear", 3: "trilinear"}


def channels_last(module: nn.Module, h: torch.Tensor) -> bool:
    """Whether ``module`` convolves the 1D or 2D maps ``h`` in channels-last layout: in training, on the CPU."""
    return module.training and h.device.type == "cpu" and h.ndim in (3, 4)


def convolution(h: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, stride: int, padding: int,
                 channels_last: bool) -> torch.Tensor:
    """A plain convolution of 1D, 2D or 3D maps (B, C, *grid).

    ``channels_last`` (training, on the CPU): 1D and 2D maps go through oneDNN in channels-last layout, a 1D map
    as a map of height 1. The same numbers to float32 round-off; oneDNN's backward is faster on that layout for
    these few channels (1.2-1.4x on a whole lite training step, timed interleaved on one thread), and for 1D
    maps it avoids a backward that took up to tens of ms per layer on the loaded test machine. 2D outputs keep
    the layout (the next convolution takes them without a copy); 1D outputs are made contiguous again (the GELU
    and linear upsampling between are slower on the strided height-1 layout). Out of training the layout is
    left alone: inference is unchanged.
    """
    if not channels_last or h.ndim not in (3, 4):
        return CONV_FN[h.ndim - 2](h, weight, bias, stride=stride, padding=padding)
    if h.ndim == 3:
        out = nn.functional.conv2d(h.unsqueeze(2).contiguous(memory_format=torch.channels_last), weight.unsqueeze(2),
                                   bias, stride=(1, stride), padding=(0, padding))
        return out.squeeze(2).contiguous()
    return nn.functional.conv2d(h.contiguous(memory_format=torch.channels_last), weight, bias, stride=stride,
                                padding=padding)


def stride_one_transposed(layer: nn.Module, h: torch.Tensor, bias: bool = True,
                           channels_last: bool = False) -> torch.Tensor:
    """A stride-1 transposed convolution computed as the equivalent plain convolution (flipped, transposed
    kernel, padding k - 1 - p): the same numbers to float32 round-off, 2-10x faster on CPU, where torch's
    oneDNN path for ConvTranspose is slow (benchmarks/perf.py). ``bias=False`` leaves the bias out;
    ``channels_last``: see :func:`convolution`."""
    k, p = layer.kernel_size[0], layer.padding[0]
    spatial = tuple(range(2, layer.weight.ndim))
    weight = layer.weight.flip(spatial).transpose(0, 1)
    return convolution(h, weight, layer.bias if bias else None, 1, k - 1 - p, channels_last)
