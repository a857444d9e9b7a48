"""The paper's 1D, 2D and 3D convolutional encoders and decoders (architecture tables of Section III).

:class:`ConvEncoder` is E_phi without the parameter residual and :class:`ConvDecoder` is G_psi; the
residual embedding is added by :class:`ParametricEncoder` (z = E_phi(x) + s) and by the latent model
before decoding (G_psi(z + s)), so the embedding is one shared module counted in the encoder.
"""

from __future__ import annotations

import contextlib
import math
import warnings
from collections import OrderedDict
from collections.abc import Iterator
from typing import Any

import numpy as np
import torch
from torch import nn

from .convolution import CONV, DECONV, DECONV_FN, UPSAMPLE_MODE, channels_last, convolution, stride_one_transposed
from .dense_derivatives import fc_jacobian, fc_vjp
from .embedding import ParameterEmbedding
from .presets import BackboneSpec, BenchmarkShape

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
    """Cells per axis after the stride-2 stages: ``ceil(n / 2**stages)`` (a grid that is not a multiple of
    2**stages is padded up to one, see :func:`_grid_padding`)."""
    factor = _STRIDE ** len(spec.conv_channels)
    return tuple(-(-n // factor) for n in shape.grid)


def _grid_padding(shape: BenchmarkShape, spec: BackboneSpec) -> tuple[int, ...]:
    """Cells added at the upper end of each axis to reach a multiple of 2**stages (zero on the paper's grids)."""
    factor = _STRIDE ** len(spec.conv_channels)
    return tuple(b * factor - n for b, n in zip(_bottleneck_grid(shape, spec), shape.grid))


class ConvEncoder(nn.Module):
    """E_phi: strided convolutions, flatten, fully connected layers to r (no parameter residual)."""

    def __init__(self, shape: BenchmarkShape, spec: BackboneSpec, r: int) -> None:
        super().__init__()
        conv = CONV[shape.ndim]
        channels = [shape.in_channels, *spec.conv_channels]
        layers: list[nn.Module] = []
        for i, (c_in, c_out) in enumerate(zip(channels[:-1], channels[1:])):
            layers.append(conv(c_in, c_out, spec.kernel_size, stride=_STRIDE, padding=spec.padding))
            if i < len(spec.conv_channels) - 1 or spec.act_after_last_conv:
                layers.append(nn.GELU())
        self.conv = nn.Sequential(*layers)
        n_flat = spec.conv_channels[-1] * math.prod(_bottleneck_grid(shape, spec))
        self.fc = _fc_stack([n_flat, *spec.fc_widths, r])
        # torch's pad lists the last axis first: (0, pad_last, 0, pad_before_last, ...); None on the paper's grids
        padding = _grid_padding(shape, spec)
        self.padding = tuple(p for n in reversed(padding) for p in (0, n)) if any(padding) else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, C_in, *grid) normalized input -> (B, r); a grid that is not a multiple of 2**stages is padded
        with zeros (the channel means) at the upper end of each axis. In training on the CPU in channels-last
        layout (:func:`~dks_gym.models.convolution.convolution`)."""
        if self.padding is not None:
            x = nn.functional.pad(x, self.padding)
        if not channels_last(self, x):
            return self.fc(self.conv(x).flatten(1))
        h = x
        for layer in self.conv:
            if isinstance(layer, nn.GELU):
                h = layer(h)
            else:
                h = convolution(h, layer.weight, layer.bias, layer.stride[0], layer.padding[0], True)
        return self.fc(h.flatten(1))


class ConvDecoder(nn.Module):
    """G_psi: fully connected layers from r, reshape, then upsampling/transposed convolutions to the grid."""

    def __init__(self, shape: BenchmarkShape, spec: BackboneSpec, r: int) -> None:
        super().__init__()
        self.ndim = shape.ndim
        self.mode = spec.decoder_mode
        self.grid = tuple(shape.grid)
        # The padded grid's output is cropped to the grid (None on the paper's grids: nothing to crop).
        self.crop = (..., *(slice(0, n) for n in shape.grid)) if any(_grid_padding(shape, spec)) else None
        self.bottleneck = (spec.conv_channels[-1], *_bottleneck_grid(shape, spec))
        self.fc = _fc_stack([r, *reversed(spec.fc_widths), math.prod(self.bottleneck)])
        deconv = DECONV[shape.ndim]
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
        self._cell_plans: dict[int, tuple[list[int], np.ndarray]] = {}
        self._layouts: OrderedDict[tuple, tuple[int, list[tuple]]] = OrderedDict()  # see _layout

    def _apply(self, fn: Any, *args: Any, **kwargs: Any) -> "ConvDecoder":
        self._layouts.clear()  # products of the weights in their old dtype or device
        return super()._apply(fn, *args, **kwargs)

    def forward(self, z: torch.Tensor, preactivations: list[torch.Tensor] | None = None) -> torch.Tensor:
        """(B, r) -> (B, C_out, *grid) normalized output (cropped from the padded grid where there is one).

        ``preactivations``: a list that receives, per convolutional stage followed by a GELU, that GELU's input
        (B, C, *cells) (what :func:`~dks_gym.models.decoder_variance.decoder_variance` linearizes at, so that
        the decode and its variance share one forward pass); the output is the same either way."""
        out = self.convolve(self.fc(z).view(z.shape[0], *self.bottleneck), preactivations)
        return out if self.crop is None else out[self.crop].contiguous()  # contiguous as uncropped: callers view it

    def convolve(self, h: torch.Tensor, preactivations: list[torch.Tensor] | None = None) -> torch.Tensor:
        """The convolutional part: bottleneck features (B, C, *b) -> (B, C_out, *grid) for the whole grid, or
        (B, C_out, *(b * 2**stages)) for a window of ``b`` bottleneck cells (every stage is translation-equivariant,
        so a window's output equals the full output wherever its receptive field stays inside the window).

        The rows go through in blocks of about 2^17 output cells and a stride-1 transposed convolution runs as the
        equivalent plain one (:func:`stride_one_transposed`), in training as out of it: the same numbers as
        torch's ConvTranspose on the whole batch to float32 round-off, 4-6x faster on CPU for large batches
        (benchmarks/perf.py). In training on the CPU the maps are in channels-last layout
        (:func:`~dks_gym.models.convolution.convolution`).
        :meth:`reference_convolve` is torch's ConvTranspose, kept for the tests. ``preactivations``: as in
        :meth:`forward`.
        """
        cells = math.prod(h.shape[2:]) * 2 ** (len(self.deconv) * self.ndim)
        rows = max(1, (1 << 17) // cells)
        if h.shape[0] <= rows:
            return self._convolve(h, fast=True, preactivations=preactivations)
        blocks = h.split(rows)
        parts = [None if preactivations is None else [] for _ in blocks]  # each block's, joined below
        out = torch.cat([self._convolve(block, fast=True, preactivations=part) for block, part in zip(blocks, parts)])
        if preactivations is not None:
            preactivations.extend(torch.cat(stage) for stage in zip(*parts))
        return out

    def reference_convolve(self, h: torch.Tensor) -> torch.Tensor:
        """:meth:`convolve` with torch's ConvTranspose layers on the whole batch: the reference it is tested
        against."""
        return self._convolve(h, fast=False)

    def _convolve(self, h: torch.Tensor, fast: bool, preactivations: list[torch.Tensor] | None = None) -> torch.Tensor:
        last = fast and channels_last(self, h)
        for i in range(len(self.deconv)):
            h = self._stage(i, h, fast, last, preactivations)
        return h.contiguous() if last else h

    def _stage(self, i: int, h: torch.Tensor, fast: bool, last: bool = False,
               preactivations: list[torch.Tensor] | None = None) -> torch.Tensor:
        """Stage ``i`` of the convolutional part: x2 in every axis (upsampling and a size-preserving transposed
        convolution, or a stride-2 one), then GELU unless it is the last (its input appended to
        ``preactivations`` when given)."""
        layer = self.deconv[i]
        if self.mode == "upsample":
            h = nn.functional.interpolate(h, scale_factor=2, mode=UPSAMPLE_MODE[self.ndim])
            h = stride_one_transposed(layer, h, channels_last=last) if fast else layer(h)
        else:
            h = layer(h)
        if i == len(self.deconv) - 1:
            return h
        if preactivations is not None:
            preactivations.append(h)
        return self.act(h)

    def _stage_matrix(self, i: int, widths: tuple[int, ...]) -> tuple[torch.Tensor, torch.Tensor] | None:
        """Stage ``i`` before its GELU on a window of ``widths`` cells as a matrix and a bias, ``(K_in, K_out)`` and
        ``(K_out,)`` over the window's flat C-order cells (channels first): upsampling and convolution are linear,
        so the matrix is the stage applied to the identity (cheap, and differentiable in the weights). None where
        it would pass 2^20 entries (the paper sphere's wide first stages)."""
        layer = self.deconv[i]
        n_in = layer.in_channels * math.prod(widths)
        n_out = layer.out_channels * math.prod(2 * w for w in widths)
        if n_in * n_out > 1 << 20:
            return None
        weight = self.deconv[i].weight
        basis = torch.eye(n_in, dtype=weight.dtype, device=weight.device).view(n_in, layer.in_channels, *widths)
        if self.mode == "upsample":
            basis = nn.functional.interpolate(basis, scale_factor=2, mode=UPSAMPLE_MODE[self.ndim])
            matrix = stride_one_transposed(layer, basis, bias=False)
        else:
            matrix = DECONV_FN[self.ndim](basis, layer.weight, None, stride=layer.stride, padding=layer.padding,
                                           output_padding=layer.output_padding)
        return matrix.reshape(n_in, n_out), layer.bias.repeat_interleave(n_out // layer.out_channels)

    def _window_stage(self, i: int, h: torch.Tensor) -> torch.Tensor:
        """Stage ``i`` on many small windows (N, C, *w), as one product with :meth:`_stage_matrix`: a convolution
        of windows a few cells wide runs many times slower on CPU than the product. A stage without a matrix
        stays a convolution."""
        stage = self._stage_matrix(i, tuple(h.shape[2:]))
        if stage is None:
            return self._stage(i, h, fast=True)
        matrix, bias = stage
        out = (self.deconv[i].out_channels, *(2 * w for w in h.shape[2:]))
        h = torch.addmm(bias, h.reshape(len(h), -1), matrix).view(len(h), *out)
        return self.act(h) if i < len(self.deconv) - 1 else h

    def _stage_inputs(self, lo: np.ndarray, hi: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
        """The input cells ``lo .. hi`` (one axis) that a stage's output cells ``lo .. hi`` read, for a stage
        whose output has ``size`` cells on that axis: a stride-1 transposed convolution reads cells
        ``j + p - k + 1 .. j + p``, a linear x2 upsampling ``floor(src)`` and the next one, a stride-2 transposed
        convolution ``ceil((j + p - k + 1) / 2) .. floor((j + p) / 2)``; zero padding and clamping at the grid's
        edges cut them."""
        k, p = self.deconv[0].kernel_size[0], self.deconv[0].padding[0]
        if self.mode == "upsample":
            lo, hi = np.clip(lo + p - k + 1, 0, size - 1), np.clip(hi + p, 0, size - 1)
            size //= 2
            lo = np.floor(np.maximum((lo + 0.5) / 2 - 0.5, 0)).astype(int)
            hi = np.minimum(np.floor(np.maximum((hi + 0.5) / 2 - 0.5, 0)).astype(int) + 1, size - 1)
            return lo, hi
        size //= 2
        return (np.clip(np.ceil((lo + p - k + 1) / 2).astype(int), 0, size - 1),
                np.clip(np.floor((hi + p) / 2).astype(int), 0, size - 1))

    def _read_ranges(self, n: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per stage, the cells ``lo .. hi`` of its input (one axis of ``n`` bottleneck cells) that each output
        cell of the grid depends on, walked back from the output: ``[(lo, hi) of stage 0 (the bottleneck), ...]``,
        arrays over the ``n * 2**stages`` output cells."""
        size = n * 2 ** len(self.deconv)
        lo, hi = np.arange(size), np.arange(size)
        ranges = []
        for i in reversed(range(len(self.deconv))):
            lo, hi = self._stage_inputs(lo, hi, n * 2 ** (i + 1))
            ranges.append((lo, hi))
        return ranges[::-1]

    @property
    def receptive_radius(self) -> int:
        """The most bottleneck cells, on either side of ``cell // 2**stages``, that an output cell depends on.

        Exact, from the index arithmetic of each stage walked back from every output cell of each axis (a
        stride-1 transposed convolution reads cells ``j + p - k + 1 .. j + p``, a linear x2 upsampling
        ``floor(src)`` and the next one, a stride-2 transposed convolution ``ceil((j + p - k + 1) / 2) ..
        floor((j + p) / 2)``; zero padding and clamping at the grid's edges cut them), and cached.
        """
        if self._receptive_radius is None:
            factor = 2 ** len(self.deconv)
            radius = 0
            for n in self.bottleneck[1:]:
                lo, hi = self._read_ranges(n)[0]
                center = np.arange(n * factor) // factor
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

    def _cell_windows(self, n: int) -> tuple[list[int], np.ndarray]:
        """How :meth:`at_cells` decodes one output cell along an axis of ``n`` bottleneck cells: per stage the width
        of its input window (one for all cells) and, per output cell, the window's start, ``(stages, n * 2**stages)``.

        Each window holds the cells its output cell reads at that stage (:meth:`_read_ranges`) and lies inside
        the grid and inside the previous stage's output window, so every cell read is exact: where a window's
        edge is not the grid's, the cells next to it that the window's own padding spoils are not read. Cached.
        """
        if n not in self._cell_plans:
            ranges = self._read_ranges(n)
            widths = [int((hi - lo).max()) + 1 for lo, hi in ranges]
            starts: list[np.ndarray] = []
            lower, upper = np.zeros_like(ranges[0][0]), np.full_like(ranges[0][0], n)  # the bottleneck
            for i, ((lo, hi), width) in enumerate(zip(ranges, widths)):
                if i:  # stage i - 1's output window, which is inside the grid
                    lower, upper = 2 * starts[-1], 2 * (starts[-1] + widths[i - 1])
                start = np.maximum(np.minimum(lo, upper - width), lower)
                if not bool(((start <= lo) & (hi < start + width) & (start + width <= upper)).all()):
                    raise ValueError(f"no window plan for this decoder's stages (kernel "
                                     f"{self.deconv[0].kernel_size[0]}, padding {self.deconv[0].padding[0]})")
                starts.append(start)
            self._cell_plans[n] = (widths, np.stack(starts))
        return self._cell_plans[n]

    @staticmethod
    def _windows(h: torch.Tensor, rows: torch.Tensor, starts: list[torch.Tensor],
                 widths: tuple[int, ...]) -> torch.Tensor:
        """Windows of ``h`` (N, C, *size): window j is cut from row ``rows[j]`` at ``starts[axis][j]`` with
        ``widths[axis]`` cells on each axis -> (len(rows), C, *widths), one indexing of ``h``'s unfolded view."""
        for axis, width in enumerate(widths):
            h = h.unfold(2 + axis, width, 1)
        return h[(rows, slice(None), *starts)]

    @staticmethod
    def _flat_windows(size: tuple[int, ...], channels: torch.Tensor, starts: list[torch.Tensor],
                      widths: tuple[int, ...]) -> torch.Tensor:
        """Flat C-order indices, into a block (C, *size), of windows at ``starts`` per axis (k,) with ``widths``
        cells per axis, ``channels`` kept: (k, len(channels) * prod(widths)), channel-major."""
        offsets = torch.meshgrid(*[torch.arange(w, device=channels.device) for w in widths], indexing="ij")
        position = sum((s[:, None] + o.reshape(-1)) * math.prod(size[axis + 1:])
                       for axis, (s, o) in enumerate(zip(starts, offsets)))  # (k, prod(widths))
        return (channels[:, None] * math.prod(size) + position[:, None, :]).reshape(len(starts[0]), -1)

    def at_cells(self, x: torch.Tensor, cells: torch.Tensor, channel: int) -> torch.Tensor:
        """Output ``channel`` at ``cells`` decoded from only the cells each one reads, equal to ``forward(x)`` there
        to float round-off: ``x`` (N, r) decoder inputs, ``cells`` (N, m) flat output-grid indices -> (N, m).

        Every stage runs on one window per output cell, as a product with its matrix on that window
        (:meth:`_stage_matrix`), cropped after it to what the next stage reads (:meth:`_cell_windows`): on the
        Burgers grid windows of 5, 4 and 3 cells in, against 128, 256 and 512 cells per stage of a whole decode.
        Where every row reads the same cells (one sensor layout), few enough that their windows hold fewer
        features than the bottleneck, the crops are folded into the matrices and the first stage into the last
        dense layer, once per layout (:meth:`_layout`).
        """
        n, m = cells.shape
        cells = cells.to(x.device)
        widths = self._window_widths()
        if m * self.deconv[0].out_channels * math.prod(widths[1]) <= math.prod(self.bottleneck) \
                and bool((cells == cells[:1]).all()):
            layout = self._layout(cells[0], channel)
            if layout is not None:
                return self._at_layout(x, layout)
        return self._at_cells(x, cells, channel)

    def _window_widths(self) -> list[tuple[int, ...]]:
        """Per stage the input window's cells per axis (:meth:`_cell_windows`), then the output cell's (1, ...)."""
        plans = [self._cell_windows(b) for b in self.bottleneck[1:]]
        return [tuple(w[i] for w, _ in plans) for i in range(len(self.deconv))] + [(1,) * len(plans)]

    def _window_starts(self, cells: torch.Tensor) -> list[list[torch.Tensor]]:
        """Per stage, per axis, the window starts of flat output ``cells`` (k,); last, the cells' coordinates."""
        # Flat indices of the output grid: a padded grid's output is its lower corner (the crop keeps [0, n) per
        # axis), so a cell's coordinates are the same on both, but the flat index unravels by the output grid.
        coords = torch.unravel_index(cells, self.grid)  # per axis (k,)
        plans = [torch.as_tensor(self._cell_windows(b)[1], device=cells.device) for b in self.bottleneck[1:]]
        return [[s[i][c] for s, c in zip(plans, coords)] for i in range(len(self.deconv))] + [list(coords)]

    def _layout(self, cells: torch.Tensor, channel: int) -> tuple[int, list[tuple]] | None:
        """:meth:`at_cells`' products for one layout of m ``cells``: ``(m, stages)``, per stage a matrix, a bias,
        each cell's crop among the G distinct ones (None where G = 1) and G. The first stage's matrix keeps, per
        cell, its window's columns (the crop) and is folded into the window's rows of the last dense layer,
        (H, m K_1); a later stage's is (K_in, G K_out) (G = 1 for cells evenly spaced on the grid, as the paper
        layouts are). None where a stage has no matrix. Cached per layout and weights (not while the weights
        are being differentiated, nor inside torch.func's transforms)."""
        key = None
        if not (torch.is_grad_enabled() and any(p.requires_grad for p in self.parameters())):
            try:
                key = (cells.cpu().numpy().tobytes(), channel, tuple(p._version for p in self.parameters()))
            except RuntimeError:  # inside torch.func's transforms (autodiff Jacobians) a tensor has no data to read
                key = None
        if key in self._layouts:
            self._layouts.move_to_end(key)
            return self._layouts[key]
        widths, starts = self._window_widths(), self._window_starts(cells)
        matrices = [self._stage_matrix(i, w) for i, w in enumerate(widths[:-1])]
        if any(stage is None for stage in matrices):
            return None
        device, last, stages = cells.device, self.fc[-1], []
        for i, (matrix, bias) in enumerate(matrices):
            kept = torch.arange(self.deconv[i].out_channels, device=device) if i + 1 < len(matrices) else \
                torch.tensor([channel], device=device)
            offsets = torch.stack([t - 2 * s for t, s in zip(starts[i + 1], starts[i])], 1)  # (m, axes)
            distinct, group = (offsets, None) if i == 0 else torch.unique(offsets, dim=0, return_inverse=True)
            crop = self._flat_windows(tuple(2 * w for w in widths[i]), kept, list(distinct.T), widths[i + 1])
            matrix, bias = matrix[:, crop], bias[crop]  # (K_in, G, K_out), (G, K_out)
            if i == 0:  # per cell: the window's rows of the last dense layer, times the cropped stage
                columns = self._flat_windows(self.bottleneck[1:], torch.arange(self.bottleneck[0], device=device),
                                             starts[0], widths[0])  # (m, K_0)
                bias = (last.bias[columns][:, None, :] @ matrix.movedim(1, 0))[:, 0] + bias
                matrix = (last.weight[columns].mT @ matrix.movedim(1, 0)).movedim(0, 1)  # (H, m, K_1)
            stages.append((matrix.reshape(len(matrix), -1), bias.reshape(-1),
                           None if i == 0 or len(distinct) == 1 else group, len(distinct)))
        layout = (len(cells), stages)
        if key is not None:
            self._layouts[key] = layout
            while len(self._layouts) > 8:
                self._layouts.popitem(last=False)
        return layout

    def _at_layout(self, x: torch.Tensor, layout: tuple[int, list[tuple]]) -> torch.Tensor:
        """:meth:`at_cells` for N rows that read one layout's m cells (:meth:`_layout`): the hidden dense layers,
        then one product per stage over all N m rows -> (N, m)."""
        m, stages = layout
        hidden_net = self.fc[:-1]
        h = hidden_net(x) if len(hidden_net) else x
        n = len(h)
        for i, (matrix, bias, group, n_crops) in enumerate(stages):
            h = torch.addmm(bias, h.reshape(-1, len(matrix)), matrix)  # (N, m K_1), then (N m, G K_out)
            if i and group is None:
                h = h.view(n * m, -1)
            elif i:  # each cell's own crop
                h = h.view(n, m, n_crops, -1)[:, torch.arange(m, device=h.device), group].reshape(n * m, -1)
            if i + 1 < len(stages):
                h = self.act(h)
        return h.view(n, m)

    def _at_cells(self, x: torch.Tensor, cells: torch.Tensor, channel: int) -> torch.Tensor:
        """:meth:`at_cells` for any cells: the dense layers whole, then the windows cut from their output and
        from every stage's (one indexing of an unfolded view each)."""
        n, m = cells.shape
        widths, starts = self._window_widths(), self._window_starts(cells.reshape(-1))
        features = self.fc(x).view(n, *self.bottleneck)
        h = self._windows(features, torch.arange(n, device=x.device).repeat_interleave(m), starts[0], widths[0])
        every = torch.arange(n * m, device=x.device)
        for i in range(len(self.deconv)):
            h = self._window_stage(i, h)
            if i + 1 == len(self.deconv):
                h = h[:, channel:channel + 1]
            h = self._windows(h, every, [t - 2 * s for t, s in zip(starts[i + 1], starts[i])], widths[i + 1])
        return h.reshape(n, m)

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
        device = x.device
        # Grid coordinates are the same on the padded grid (its padding is at the upper ends).
        coords = torch.unravel_index(cells.to(device), self.grid)  # per axis (N, m)
        starts = [(c // factor - self.receptive_radius).clamp(0, b - w) for c, b, w in zip(coords, bottleneck, window)]
        # Flat bottleneck indices of every window (channel-major, then the window cells in C order): (N, m, K).
        index = self._flat_windows(tuple(bottleneck), torch.arange(channels, device=device),
                                   [s.reshape(-1) for s in starts], window).reshape(n, m, -1)
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
        v = v.reshape(n, m, -1)
        # d values / d x through the dense layers: rows back through them where fewer than the columns
        jac = fc_vjp(hidden_net, x, v) if m <= x.shape[1] else v @ fc_jacobian(hidden_net, x)
        return values.detach().reshape(n, m), jac.detach()


class ParametricEncoder(nn.Module):
    """z = E_phi(x) + e_omega(mu): the encoder owns the embedding, shared with the decoder and latent map."""

    def __init__(self, backbone: ConvEncoder, embedding: ParameterEmbedding) -> None:
        super().__init__()
        self.backbone = backbone
        self.embedding = embedding

    def forward(self, x: torch.Tensor, mu: torch.Tensor) -> torch.Tensor:
        return self.backbone(x) + self.embedding(mu)
