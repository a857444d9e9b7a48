"""The exact push of a latent covariance through a convolutional decoder: ``diag(G F F^T G^T)`` per output cell.

``G = d decoder(x) / dx`` at ``x`` and ``F`` a factor of the covariance (``F F^T = P``), so the result is
``sum_j (G f_j)^2`` over the columns of ``F``: the tangent field of each column, squared and summed. The
decoder is linearized by hand with the numbers forward-mode autodiff would multiply (the two agree to float
round-off): the dense layers by the chain rule (every column of every element in one matrix product per
layer), then each convolutional stage applied to the tangent fields without its bias, times the GELU slope
at the primal pre-activation between stages. What makes it cheap on a CPU, where ``d`` Jacobian-vector
products through torch's convolutions cost about 4 decodes each (``benchmarks/uncertainty_cost.py``):

* the last dense layer and the first stage (linear: upsampling and convolution, or a transposed
  convolution) are one precomputed matrix, so the tangent fields enter at the first activation through one
  matrix product over every element and column;
* every later stage is a set of per-cell blocks, read off the stage itself once per weight set
  (:func:`_probe`): input cell ``q`` and its window ``q - lo .. q + hi`` give the ``2^ndim`` output cells
  ``2 q + a``. With the fields laid out rows innermost, ``(*cells, C, N)``, the windows along the last axis
  are a strided view of the zero-padded field and a stage is one batched matrix product per window offset
  of the other axes: no upsampled field is ever stored, and torch's convolutions, 5-70x slower on the lite
  decoders' 1-8 channels, are not called;
* elements go through in chunks that keep a stage's tangent fields within a few MB (cache), written into
  fields kept from call to call (:func:`_workspace`: fresh pages fault on their first touch);
* a caller that decodes ``x`` anyway passes the GELU inputs its decode recorded (``preactivations``), and
  the slopes are read off them instead of a primal pass here.

Decoders whose per-cell blocks would exceed :data:`KERNEL_NUMBERS` (the paper-size 2D and 3D ones, where
the convolutions' own cost dominates anyway) are not handled (:func:`supports_decoder_variance`).
"""

from __future__ import annotations

import itertools
import math
import threading
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import nn

from .backbones import ConvDecoder
from .convolution import UPSAMPLE_MODE
from .dense_derivatives import gelu_slope, gelu_slopes

#: Numbers in the largest tangent field of one chunk (cells x channels x elements x columns): 4 MB in float32.
CHUNK_NUMBERS = 2**20
#: The most numbers the per-cell blocks of all stages may hold (64 MB in float32).
KERNEL_NUMBERS = 2**24
_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_LOCAL = threading.local()  # per thread: the chunks' fields of each decoder (:func:`_workspace`)


@dataclass(frozen=True)
class _Stage:
    """A convolutional stage (no bias) as per-cell blocks: ``kernels`` (w^(ndim-1), rows, 2^ndim C_out,
    w C_in) over the rows of the padded input grid (``lo`` + ``cells`` + ``hi`` per axis, flattened, from
    the first axis's cells), one block per offset of the window's leading axes."""

    cells: tuple[int, ...]
    lo: int
    hi: int
    kernels: torch.Tensor
    bias: torch.Tensor


@dataclass(frozen=True)
class _Linearization:
    """The decoder's stages as :func:`decoder_variance` applies them, for one weight set (``key``)."""

    key: tuple
    weight: torch.Tensor  # (*cells_1, C_1, h): the last dense layer through the first stage
    bias: torch.Tensor  # (*cells_1, C_1, 1)
    stages: tuple[_Stage, ...]


def supports_decoder_variance(decoder: nn.Module) -> bool:
    """True when :func:`decoder_variance` can linearize ``decoder``: a :class:`ConvDecoder` of Linear layers,
    exact GELUs (the slope rule used) and plain (ungrouped, undilated) transposed convolutions, whose per-cell
    blocks hold at most :data:`KERNEL_NUMBERS` numbers."""
    if not isinstance(decoder, ConvDecoder) or not isinstance(decoder.act, nn.GELU):
        return False
    exact = all(isinstance(m, nn.Linear) or (isinstance(m, nn.GELU) and m.approximate == "none")
                for m in (*decoder.fc, decoder.act))
    plain = all(m.groups == 1 and set(m.dilation) == {1} and len(set(m.kernel_size)) == 1 for m in decoder.deconv)
    return exact and plain and sum(_kernel_numbers(decoder, i) for i in range(1, len(decoder.deconv))) <= KERNEL_NUMBERS


def decoder_variance(decoder: ConvDecoder, x: torch.Tensor, factor: torch.Tensor,
                     preactivations: Sequence[torch.Tensor] | None = None) -> torch.Tensor:
    """``diag(G F F^T G^T)`` of ``decoder`` at its inputs ``x`` (B, r): (B, C_out, *grid), normalized units.

    ``factor`` (B, r, d): the columns ``f_j`` of a factor of each element's covariance; ``G`` the decoder's
    Jacobian at ``x``, never formed. Exact: no sampling, no finite differences. ``preactivations``: what
    ``decoder(x, preactivations=[])`` recorded, when the caller decodes ``x`` anyway: the GELU slopes are
    then read off them instead of a primal pass of its own (the same numbers to float round-off).
    """
    if not supports_decoder_variance(decoder):
        raise TypeError("decoder_variance linearizes a ConvDecoder with exact GELU activations and per-cell "
                        f"blocks of at most {KERNEL_NUMBERS} numbers only")
    if x.ndim != 2 or factor.ndim != 3 or factor.shape[:2] != x.shape:
        raise ValueError(f"x must be (B, r) and factor (B, r, d), got {tuple(x.shape)} and {tuple(factor.shape)}")
    with torch.no_grad():
        lin = _linearization(decoder)
        space = _workspace(decoder, lin, factor.shape[2])
        hidden, columns = _dense_tangents(decoder.fc[:-1], x, factor, space)
        slopes = _slopes(decoder, lin, hidden) if preactivations is None else _recorded_slopes(lin, preactivations,
                                                                                              x.shape[0])
        largest = max(_stage_numbers(decoder, i) for i in range(len(decoder.deconv)))
        step = max(1, CHUNK_NUMBERS // (largest * factor.shape[2]))
        parts = [_chunk_variance(lin, [slope[..., s:s + step] for slope in slopes], columns[:, s:s + step], space)
                 for s in range(0, x.shape[0], step)]
        variance = torch.cat(parts)
        # A grid padded to a multiple of 2**stages (custom benchmarks): the decoder crops its output; so here.
        return variance if decoder.crop is None else variance[decoder.crop].contiguous()


def _workspace(decoder: ConvDecoder, lin: _Linearization, d: int) -> dict:
    """The padded fields the chunks of :func:`decoder_variance` write, kept from call to call for this
    thread, this weight set and ``d`` columns. Fresh memory costs a page fault per 4 kB: allocated anew at
    every call, these fields cost a fifth of the std of a vector env step (Burgers, N = 256). Per thread,
    so that two threads decoding with one model do not share them."""
    spaces = getattr(_LOCAL, "spaces", None)
    if spaces is None:
        spaces = _LOCAL.spaces = weakref.WeakKeyDictionary()
    key = (lin.key, d)
    held = spaces.get(decoder)
    if held is None or held[0] != key:  # new weights or columns: the old fields go
        held = spaces[decoder] = (key, {})
    return held[1]


def _dense_tangents(layers: nn.Sequential, x: torch.Tensor, factor: torch.Tensor,
                    space: dict) -> tuple[torch.Tensor, torch.Tensor]:
    """The dense layers before the last at ``x`` (B, r) and their Jacobian times ``factor`` (B, r, d): the
    hidden layer (B, h) and the tangents there, ``(h, B, d)`` (features outermost, so that every Linear is
    one matrix product over all elements and columns, and a chunk of elements is a strided matrix), written
    into fields of ``space`` (:func:`_workspace`)."""
    batch, r, d = factor.shape
    slopes, h = gelu_slopes(layers, x)
    tangent = factor.permute(1, 0, 2)
    for i, layer in enumerate(layers):
        if isinstance(layer, nn.Linear):
            key = ("dense", i, batch)
            if key not in space:
                space[key] = tangent.new_empty(layer.out_features, batch, d)
            tangent = torch.mm(layer.weight, tangent.reshape(r, batch * d),
                               out=space[key].view(-1, batch * d)).view(-1, batch, d)
            r = tangent.shape[0]
        else:  # an exact GELU (supports_decoder_variance); in place: the product above is this call's
            tangent = tangent.mul_(slopes.pop(0).T[..., None])
    return h, tangent


def _slopes(decoder: ConvDecoder, lin: _Linearization, hidden: torch.Tensor) -> list[torch.Tensor]:
    """The primal pass over every element at once: the GELU slope at the pre-activation feeding each stage
    after the first, ``(*cells, C, B)`` each, from the last hidden layer ``hidden`` (B, h)."""
    pre = (lin.weight.reshape(-1, hidden.shape[1]) @ hidden.T).view(*lin.weight.shape[:-1], -1) + lin.bias
    slopes = []
    for i, stage in enumerate(lin.stages):
        slopes.append(gelu_slope(pre))
        if i < len(lin.stages) - 1:
            pre = _products(stage, _padded_copy(stage, decoder.act(pre))) + stage.bias[:, None]
    return slopes


def _recorded_slopes(lin: _Linearization, preactivations: Sequence[torch.Tensor], batch: int) -> list[torch.Tensor]:
    """:func:`_slopes` from the decoder's own pre-activations (B, C, *cells), one per stage after the first."""
    ndim = len(lin.weight.shape) - 2
    expected = [(batch, lin.weight.shape[-2], *lin.weight.shape[:-2])]
    expected += [(batch, stage.bias.shape[0], *(2 * c for c in stage.cells)) for stage in lin.stages[:-1]]
    expected = expected[: len(lin.stages)]  # a one-stage decoder has no GELU between stages
    got = [tuple(p.shape) for p in preactivations]
    if got != expected:
        raise ValueError(f"preactivations must be what decoder(x, preactivations=[]) records for this x, shapes "
                         f"{expected}; got {got}")
    rows_inner = (*range(2, ndim + 2), 1, 0)  # (B, C, *cells) -> (*cells, C, B), as _slopes lays them out
    return [gelu_slope(p).permute(*rows_inner) for p in preactivations]  # views: a transposing copy costs more


def _chunk_variance(lin: _Linearization, slopes: list[torch.Tensor], columns: torch.Tensor,
                    space: dict) -> torch.Tensor:
    """:func:`decoder_variance` of the elements whose tangents at the last dense layer's input are ``columns``
    (h, b, d) and whose stages' slopes are ``slopes``. Each stage's input is written straight into the
    zero-padded field its products read (the slope multiplied in place), a field of ``space`` reused from
    chunk to chunk (only interiors are written, so the zero borders stay)."""
    h, batch, d = columns.shape
    ndim = len(lin.weight.shape) - 2
    weight = lin.weight.reshape(-1, h)
    columns = columns.reshape(h, batch * d)

    def workspace(key: tuple, make: Callable[[], tuple]) -> tuple:
        if key not in space:
            space[key] = make()
        return space[key]

    if not lin.stages:
        tangent = (weight @ columns).view(*lin.weight.shape[:-1], batch * d)
    else:
        field, inner = workspace((0, batch), lambda: _padded(lin.stages[0], lin.weight.shape[-2], batch * d, columns))
        if inner.is_contiguous():  # 1D: the interior is one block
            torch.mm(weight, columns, out=inner.view(weight.shape[0], -1))
        else:
            inner.copy_((weight @ columns).view(inner.shape))
    for i, (stage, slope) in enumerate(zip(lin.stages, slopes)):
        inner.unflatten(-1, (batch, d)).mul_(slope[..., None])
        if i == len(lin.stages) - 1:
            cells = tuple(2 * c for c in stage.cells)
            tangent = workspace(("out", batch), lambda: (columns.new_empty(*cells, stage.bias.shape[0], batch * d),))[0]
            _products(stage, field, out=tangent)
        else:
            following = workspace((i + 1, batch), lambda: _padded(lin.stages[i + 1], stage.bias.shape[0], batch * d,
                                                                  columns))
            _products(stage, field, out=following[1])
            field, inner = following
    var = torch.linalg.vector_norm(tangent.unflatten(-1, (batch, d)), dim=-1).square_()  # (*grid, C_out, b)
    return var.permute(ndim + 1, ndim, *range(ndim))


def _padded(stage: _Stage, channels: int, n: int, like: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A zero-padded field for ``stage``'s input, flat ``(cells + tail, channels, n)`` with zero borders (and a
    zero tail the last rows' windows read), and its interior ``(*cells, channels, n)`` (left to be written)."""
    cells, lo, w = stage.cells, stage.lo, stage.lo + stage.hi + 1
    size = [c + w - 1 for c in cells]
    total = math.prod(size)
    flat = like.new_empty(total + (w - 1) * sum(math.prod(size[a + 1:]) for a in range(1, len(cells))), channels, n)
    grid = flat[:total].view(*size, channels, n)
    for a in range(len(cells)):
        grid[(slice(None),) * a + (slice(0, lo),)] = 0
        grid[(slice(None),) * a + (slice(lo + cells[a], None),)] = 0
    flat[total:] = 0
    return flat, grid[tuple(slice(lo, lo + c) for c in cells)]


def _padded_copy(stage: _Stage, t: torch.Tensor) -> torch.Tensor:
    """``t`` (*cells, C, n) in a zero-padded field for ``stage`` (see :func:`_padded`)."""
    flat, inner = _padded(stage, t.shape[-2], t.shape[-1], t)
    inner.copy_(t)
    return flat


def _products(stage: _Stage, flat: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor | None:
    """``stage`` (no bias) on the zero-padded field ``flat`` (see :func:`_padded`): (*2 cells, C_out, n), or
    written into ``out`` (that shape; e.g. the next stage's padded interior) and None.

    On the flattened padded grid a cell's window is a fixed flat shift from it, so per offset of the leading
    axes the windows over the last axis (``w`` cells x ``C_in``, contiguous) are one strided view and the
    offset's part one batched product; the rows of the padded columns of the leading axes compute values
    that are dropped. In 1D the products are the output cells in order (cell ``2q + a`` is row ``q``, phase
    ``a``), so they go straight into ``out``.
    """
    cells, ndim, w = stage.cells, len(stage.cells), stage.lo + stage.hi + 1
    c_in, n = flat.shape[1:]
    size = [c + w - 1 for c in cells]
    plane = [math.prod(size[a + 1:]) for a in range(ndim)]  # flat strides of the padded grid, in cells
    rows = cells[0] * plane[0]
    direct = out is not None and ndim == 1 and out.is_contiguous()
    products = None
    for j, lead in enumerate(itertools.product(range(w), repeat=ndim - 1)):
        shift = sum(o * plane[a] for a, o in enumerate(lead))
        windows = flat.as_strided((rows, w * c_in, n), (c_in * n, n, 1), shift * c_in * n)
        if products is None:
            products = torch.bmm(stage.kernels[j], windows, out=out.view(rows, -1, n) if direct else None)
        else:
            products.baddbmm_(stage.kernels[j], windows)
    if direct:
        return None
    c_out = products.shape[1] // 2**ndim
    products = products.view(cells[0], *size[1:], *(2,) * ndim, c_out, n)
    products = products[(slice(None), *(slice(0, c) for c in cells[1:]))]
    interleaved = [axis for a in range(ndim) for axis in (a, ndim + a)]  # cell q_a, then its phase a_a
    result = products.permute(*interleaved, 2 * ndim, 2 * ndim + 1).reshape(*(2 * c for c in cells), c_out, n)
    if out is None:
        return result
    out.copy_(result)
    return None


def _linearization(decoder: ConvDecoder) -> _Linearization:
    """The decoder's :class:`_Linearization`, cached per decoder until a weight changes."""
    params = [decoder.fc[-1].weight, decoder.fc[-1].bias, *decoder.deconv.parameters()]
    key = tuple((p.data_ptr(), p._version, p.dtype, p.device) for p in params)
    cached = _CACHE.get(decoder)
    if cached is not None and cached.key == key:
        return cached
    last, first = decoder.fc[-1], decoder.deconv[0]
    channels, *cells = decoder.bottleneck
    ndim = len(cells)
    rows_inner = (*range(2, ndim + 2), 1, 0)  # (N, C, *cells) -> (*cells, C, N)
    with torch.no_grad():
        basis = last.weight.T.reshape(-1, channels, *cells)  # column j of the last layer as a bottleneck field
        weight = _stage_linear(decoder, 0, basis).permute(*rows_inner).contiguous()
        offset = _stage_linear(decoder, 0, last.bias.reshape(1, channels, *cells))
        bias = (offset + first.bias.view(-1, *[1] * ndim)).permute(*rows_inner).contiguous()
        stages = tuple(_probe(decoder, i) for i in range(1, len(decoder.deconv)))
    lin = _Linearization(key, weight, bias, stages)
    _CACHE[decoder] = lin
    return lin


def _stage_linear(decoder: ConvDecoder, i: int, x: torch.Tensor) -> torch.Tensor:
    """Stage ``i`` of the decoder without its bias, with torch's own operators: (N, C_in, *cells) ->
    (N, C_out, *2 cells), as :meth:`ConvDecoder.convolve` computes it in training mode."""
    layer = decoder.deconv[i]
    transposed = getattr(nn.functional, f"conv_transpose{decoder.ndim}d")
    if decoder.mode == "upsample":
        x = nn.functional.interpolate(x, scale_factor=2, mode=UPSAMPLE_MODE[decoder.ndim])
        return transposed(x, layer.weight, None, 1, layer.padding)
    return transposed(x, layer.weight, None, layer.stride, layer.padding, layer.output_padding)


def _band(decoder: ConvDecoder, i: int) -> tuple[int, int]:
    """``(lo, hi)``: output cell ``2 q + a`` of stage ``i`` reads the input cells ``q - lo .. q + hi`` (per axis).

    Upsampling: upsampled cell ``j`` reads input cells ``(j - 1) // 2 .. (j + 1) // 2``, and the stride-1
    transposed convolution's output cell ``m`` upsampled cells ``m - (k - 1 - p) .. m + p``; a stride-2
    transposed convolution's output cell ``m`` reads ``ceil((m + p - k + 1) / 2) .. floor((m + p) / 2)``.
    """
    layer = decoder.deconv[i]
    k, p = layer.kernel_size[0], layer.padding[0]
    if decoder.mode == "upsample":
        first = [(a - (k - 1 - p) - 1) // 2 for a in (0, 1)]
        last = [(a + p + 1) // 2 for a in (0, 1)]
    else:
        first = [-((k - 1 - a - p) // 2) for a in (0, 1)]
        last = [(a + p) // 2 for a in (0, 1)]
    return max(0, -min(first)), max(0, max(last))


def _probe(decoder: ConvDecoder, i: int) -> _Stage:
    """Stage ``i`` read off as per-cell blocks: the stage applied to ``w^ndim C_in`` probe fields, each with
    ones in one channel at the cells of one residue class mod ``w`` per axis. A block's window holds one
    cell of each class, so the probe's output at ``2 q + a`` is the block's column for that cell and channel
    (zero where that cell lies outside the grid): exact, edges included."""
    layer = decoder.deconv[i]
    ndim, c_in, c_out = decoder.ndim, layer.in_channels, layer.out_channels
    cells = tuple(n * 2**i for n in decoder.bottleneck[1:])
    lo, hi = _band(decoder, i)
    w = lo + hi + 1
    weight = layer.weight
    color = sum((torch.arange(n, device=weight.device) % w).view(*[-1 if b == a else 1 for b in range(ndim)])
                * w ** (ndim - 1 - a) for a, n in enumerate(cells))
    pattern = (color == torch.arange(w**ndim, device=weight.device).view(-1, *[1] * ndim)).to(weight.dtype)
    eye = torch.eye(c_in, dtype=weight.dtype, device=weight.device).view(1, c_in, c_in, *[1] * ndim)
    probes = (pattern[:, None, None] * eye).reshape(w**ndim * c_in, c_in, *cells)
    out = _stage_linear(decoder, i, probes).view(*(w,) * ndim, c_in, c_out, *(2 * n for n in cells))
    dims = 3 * ndim + 2  # the blocks' axes: q (ndim), a (ndim), C_out, e (ndim), C_in

    def along(values: torch.Tensor, dim: int) -> torch.Tensor:
        return values.view(*[-1 if d == dim else 1 for d in range(dims)])

    q = [along(torch.arange(n, device=weight.device), a) for a, n in enumerate(cells)]
    phase = [along(torch.arange(2, device=weight.device), ndim + a) for a in range(ndim)]
    offset = [along(torch.arange(w, device=weight.device), 2 * ndim + 1 + a) for a in range(ndim)]
    blocks = out[(*[(q[a] - lo + offset[a]) % w for a in range(ndim)],
                  along(torch.arange(c_in, device=weight.device), 3 * ndim + 1),
                  along(torch.arange(c_out, device=weight.device), 2 * ndim),
                  *[2 * q[a] + phase[a] for a in range(ndim)])]
    blocks = blocks.reshape(*cells, 2**ndim * c_out, w ** (ndim - 1), w * c_in).movedim(-2, 0)
    kernels = blocks.new_zeros(w ** (ndim - 1), cells[0], *(n + w - 1 for n in cells[1:]), *blocks.shape[-2:])
    kernels[(slice(None), slice(None), *(slice(0, n) for n in cells[1:]))] = blocks
    return _Stage(cells, lo, hi, kernels.flatten(1, ndim), layer.bias.detach())


def _stage_numbers(decoder: ConvDecoder, i: int) -> int:
    """Numbers per column in the output of stage ``i`` (cells x channels)."""
    return math.prod(decoder.bottleneck[1:]) * 2 ** ((i + 1) * decoder.ndim) * decoder.deconv[i].out_channels


def _kernel_numbers(decoder: ConvDecoder, i: int) -> int:
    """Numbers in the per-cell blocks of stage ``i`` (:func:`_probe`)."""
    layer = decoder.deconv[i]
    lo, hi = _band(decoder, i)
    w = lo + hi + 1
    cells = [n * 2**i for n in decoder.bottleneck[1:]]
    rows = cells[0] * math.prod(n + w - 1 for n in cells[1:])
    return rows * w**decoder.ndim * 2**decoder.ndim * layer.in_channels * layer.out_channels


__all__ = ["CHUNK_NUMBERS", "KERNEL_NUMBERS", "decoder_variance", "supports_decoder_variance"]
