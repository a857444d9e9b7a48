"""The paper's 1D, 2D and 3D convolutional encoders and decoders (architecture tables of Section III).

:class:`ConvEncoder` is E_phi without the parameter residual and :class:`ConvDecoder` is G_psi; the
residual embedding is added by :class:`ParametricEncoder` (z = E_phi(x) + s) and by the latent model
before decoding (G_psi(z + s)), so the embedding is one shared module counted in the encoder.
"""

from __future__ import annotations

import contextlib
import math
import warnings
from collections.abc import Iterator

import numpy as np
import torch
from torch import nn

from .embedding import ParameterEmbedding
from .presets import BackboneSpec, BenchmarkShape

_CONV = {1: nn.Conv1d, 2: nn.Conv2d, 3: nn.Conv3d}
_DECONV = {1: nn.ConvTranspose1d, 2: nn.ConvTranspose2d, 3: nn.ConvTranspose3d}
_CONV_FN = {1: nn.functional.conv1d, 2: nn.functional.conv2d, 3: nn.functional.conv3d}
_UPSAMPLE_MODE = {1: "linear", 2: "bilinear", 3: "trilinear"}
_STRIDE = 2


@contextlib.contextmanager
def quiet_forward_ad() -> Iterator[None]:
    """torch's forward-mode AD loads its own decompositions through torch.jit.script, which torch itself
    deprecates (torch/_decomp/decompositions_for_jvp.py): nothing to change on our side, so say nothing."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r".*torch\.jit\.script.* is deprecated", category=DeprecationWarning)
        yield


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


def _fc_jacobian(layers: nn.Sequential, x: torch.Tensor) -> torch.Tensor:
    """d layers(x) / dx per row, (N, out, in), for a stack of Linear layers and exact GELUs (the chain rule by
    hand, carried transposed so that each Linear is one matrix product over all rows: forward-mode autodiff
    through vmap costs several times more here)."""
    with torch.no_grad():
        jac_t = torch.eye(x.shape[1], dtype=x.dtype, device=x.device)  # (in, features), shared until the first GELU
        h = x
        for layer in layers:
            if isinstance(layer, nn.Linear):
                jac_t = jac_t @ layer.weight.T
                h = layer(h)
            elif isinstance(layer, nn.GELU) and layer.approximate == "none":
                # GELU'(h) = Phi(h) + h phi(h)
                slope = 0.5 * (1 + torch.erf(h / math.sqrt(2))) + h * torch.exp(-0.5 * h * h) / math.sqrt(2 * math.pi)
                jac_t = jac_t * slope[:, None, :]
                h = layer(h)
            else:
                raise TypeError(f"no Jacobian rule for {type(layer).__name__} in the decoder's dense layers")
    jac_t = jac_t.expand(x.shape[0], -1, -1) if jac_t.ndim == 2 else jac_t
    return jac_t.mT


def _channels_last(module: nn.Module, h: torch.Tensor) -> bool:
    """Whether ``module`` convolves the 1D or 2D maps ``h`` in channels-last layout: in training, on the CPU."""
    return module.training and h.device.type == "cpu" and h.ndim in (3, 4)


def _convolution(h: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, stride: int, padding: int,
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
        return _CONV_FN[h.ndim - 2](h, weight, bias, stride=stride, padding=padding)
    if h.ndim == 3:
        out = nn.functional.conv2d(h.unsqueeze(2).contiguous(memory_format=torch.channels_last), weight.unsqueeze(2),
                                   bias, stride=(1, stride), padding=(0, padding))
        return out.squeeze(2).contiguous()
    return nn.functional.conv2d(h.contiguous(memory_format=torch.channels_last), weight, bias, stride=stride,
                                padding=padding)


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
        """(B, C_in, *grid) normalized input -> (B, r); in training on the CPU in channels-last layout."""
        if not _channels_last(self, x):
            return self.fc(self.conv(x).flatten(1))
        h = x
        for layer in self.conv:
            if isinstance(layer, nn.GELU):
                h = layer(h)
            else:
                h = _convolution(h, layer.weight, layer.bias, layer.stride[0], layer.padding[0], channels_last=True)
        return self.fc(h.flatten(1))


def _stride_one_transposed(layer: nn.Module, h: torch.Tensor, channels_last: bool = False) -> torch.Tensor:
    """A stride-1 transposed convolution computed as the equivalent plain convolution (flipped, transposed
    kernel, padding k - 1 - p): the same numbers to float32 round-off, 2-10x faster on CPU, where torch's
    oneDNN path for ConvTranspose is slow (benchmarks/perf.py). ``channels_last``: see :func:`_convolution`."""
    k, p = layer.kernel_size[0], layer.padding[0]
    spatial = tuple(range(2, layer.weight.ndim))
    weight = layer.weight.flip(spatial).transpose(0, 1)
    return _convolution(h, weight, layer.bias, 1, k - 1 - p, channels_last)


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
        self._receptive_radius: int | None = None

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        """(B, r) -> (B, C_out, *grid) normalized output."""
        return self.convolve(self.fc(z).view(z.shape[0], *self.bottleneck))

    def convolve(self, h: torch.Tensor) -> torch.Tensor:
        """The convolutional part: bottleneck features (B, C, *b) -> (B, C_out, *grid) for the whole grid, or
        (B, C_out, *(b * 2**stages)) for a window of ``b`` bottleneck cells (every stage is translation-equivariant,
        so a window's output equals the full output wherever its receptive field stays inside the window).

        The rows go through in blocks of about 2^17 output cells and a stride-1 transposed convolution runs as the
        equivalent plain one (:func:`_stride_one_transposed`), in training as out of it: the same numbers as
        torch's ConvTranspose on the whole batch to float32 round-off, 4-6x faster on CPU for large batches
        (benchmarks/perf.py). In training on the CPU the maps are in channels-last layout (:func:`_convolution`).
        :meth:`reference_convolve` is torch's ConvTranspose, kept for the tests.
        """
        cells = math.prod(h.shape[2:]) * 2 ** (len(self.deconv) * self.ndim)
        rows = max(1, (1 << 17) // cells)
        if h.shape[0] <= rows:
            return self._convolve(h, fast=True)
        return torch.cat([self._convolve(block, fast=True) for block in h.split(rows)])

    def reference_convolve(self, h: torch.Tensor) -> torch.Tensor:
        """:meth:`convolve` with torch's ConvTranspose layers on the whole batch: the reference it is tested
        against."""
        return self._convolve(h, fast=False)

    def _convolve(self, h: torch.Tensor, fast: bool) -> torch.Tensor:
        channels_last = fast and _channels_last(self, h)
        for i, layer in enumerate(self.deconv):
            if self.mode == "upsample":
                h = nn.functional.interpolate(h, scale_factor=2, mode=_UPSAMPLE_MODE[self.ndim])
                h = _stride_one_transposed(layer, h, channels_last) if fast else layer(h)
            else:
                h = layer(h)
            if i < len(self.deconv) - 1:
                h = self.act(h)
        return h.contiguous() if channels_last else h

    @property
    def receptive_radius(self) -> int:
        """The most bottleneck cells, on either side of ``cell // 2**stages``, that an output cell depends on.

        Exact, from the index arithmetic of each stage walked back from every output cell of each axis (a
        stride-1 transposed convolution reads cells ``j + p - k + 1 .. j + p``, a linear x2 upsampling
        ``floor(src)`` and the next one, a stride-2 transposed convolution ``ceil((j + p - k + 1) / 2) ..
        floor((j + p) / 2)``; zero padding and clamping at the grid's edges cut them), and cached.
        """
        if self._receptive_radius is None:
            k, p = self.deconv[0].kernel_size[0], self.deconv[0].padding[0]
            factor = 2 ** len(self.deconv)
            radius = 0
            for n in self.bottleneck[1:]:
                size = n * factor
                cells = np.arange(size)
                lo, hi = cells.copy(), cells.copy()
                for _ in self.deconv:
                    if self.mode == "upsample":
                        lo, hi = np.clip(lo + p - k + 1, 0, size - 1), np.clip(hi + p, 0, size - 1)
                        size //= 2
                        lo = np.floor(np.maximum((lo + 0.5) / 2 - 0.5, 0)).astype(int)
                        hi = np.minimum(np.floor(np.maximum((hi + 0.5) / 2 - 0.5, 0)).astype(int) + 1, size - 1)
                    else:
                        size //= 2
                        lo = np.clip(np.ceil((lo + p - k + 1) / 2).astype(int), 0, size - 1)
                        hi = np.clip(np.floor((hi + p) / 2).astype(int), 0, size - 1)
                center = cells // factor
                radius = max(radius, int((center - lo).max()), int((hi - center).max()))
            self._receptive_radius = radius
        return self._receptive_radius

    def window(self) -> tuple[int, ...] | None:
        """Bottleneck window per axis that holds any one output cell's receptive field; None when it is more
        than half the bottleneck (then decoding one window per sensor costs more than differentiating the whole
        decoder once per sensor: 7 x 7 of the 8 x 8 cells of the 2D grids)."""
        size = 2 * self.receptive_radius + 1
        window = tuple(min(size, n) for n in self.bottleneck[1:])
        return window if 2 * math.prod(window) <= math.prod(self.bottleneck[1:]) else None

    def sensor_jacobian(self, x: torch.Tensor, cells: torch.Tensor, channel: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Output ``channel`` at ``cells`` and its Jacobian with respect to the input, decoding only the window
        of bottleneck cells each output cell depends on (see :meth:`window`, which must not be None).

        ``x`` (N, r) decoder inputs, ``cells`` (N, m) flat output-grid indices. Returns values (N, m) and
        Jacobians (N, m, r), equal to autodiff through the whole decoder to float round-off. One backward pass
        over N * m small windows replaces m passes over the whole grid: with 16 sensors on the 1024-cell
        Burgers grid the window is 5 of 128 bottleneck cells.
        """
        window = self.window()
        if window is None:
            raise ValueError("the receptive field covers the whole bottleneck: differentiate the full decoder")
        n, m = cells.shape
        channels, *bottleneck = self.bottleneck
        factor = 2 ** len(self.deconv)
        grid = tuple(b * factor for b in bottleneck)
        device = x.device
        coords = torch.unravel_index(cells.to(device), grid)  # per axis (N, m)
        starts = [(c // factor - self.receptive_radius).clamp(0, b - w) for c, b, w in zip(coords, bottleneck, window)]
        # Flat bottleneck indices of every window (channel-major, then the window cells in C order): (N, m, K).
        offsets = torch.meshgrid(*[torch.arange(w, device=device) for w in window], indexing="ij")
        strides = [math.prod(bottleneck[i + 1:]) for i in range(len(bottleneck))]
        position = sum((s[..., None] + o.reshape(-1)) * st for s, o, st in zip(starts, offsets, strides))
        index = (torch.arange(channels, device=device)[:, None] * math.prod(bottleneck)
                 + position[..., None, :]).reshape(n, m, -1)
        hidden_net, last = self.fc[:-1], self.fc[-1]
        with torch.no_grad():
            hidden = hidden_net(x)
            features = last(hidden)  # the whole bottleneck, (N, channels * prod(bottleneck)): cheap
        with torch.enable_grad():
            windows = features.gather(1, index.reshape(n, -1)).reshape(n * m, channels, *window).requires_grad_(True)
            out = self.convolve(windows).reshape(n * m, -1, math.prod(w * factor for w in window))
            local = sum((c - s * factor).reshape(-1) * math.prod(w * factor for w in window[i + 1:])
                        for i, (c, s) in enumerate(zip(coords, starts)))
            values = out[torch.arange(n * m, device=device), channel, local]
            (grad,) = torch.autograd.grad(values.sum(), windows)
        # d values / d hidden: the gradient's weighted sum of the last layer's rows, without gathering them.
        v = nn.functional.embedding_bag(index.reshape(n * m, -1), last.weight,
                                        per_sample_weights=grad.reshape(n * m, -1), mode="sum")
        jac = v.reshape(n, m, -1) @ _fc_jacobian(hidden_net, x) if len(hidden_net) else v.reshape(n, m, -1)
        return values.detach().reshape(n, m), jac.detach()


class ParametricEncoder(nn.Module):
    """z = E_phi(x) + e_omega(mu): the encoder owns the embedding, shared with the decoder and latent map."""

    def __init__(self, backbone: ConvEncoder, embedding: ParameterEmbedding) -> None:
        super().__init__()
        self.backbone = backbone
        self.embedding = embedding

    def forward(self, x: torch.Tensor, mu: torch.Tensor) -> torch.Tensor:
        return self.backbone(x) + self.embedding(mu)
