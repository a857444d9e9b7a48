"""The exact push of a latent covariance through a convolutional decoder: ``diag(G F F^T G^T)`` per output cell.

``G = d decoder(x) / dx`` at ``x`` and ``F`` a factor of the covariance (``F F^T = P``), so the result is
``sum_j (G f_j)^2`` over the columns of ``F``: the tangent field of each column, squared and summed. The
decoder is linearized by hand with the numbers forward-mode autodiff would multiply (the two agree to float
round-off): the dense layers by the chain rule (:func:`~dks_gym.models.backbones.fc_jacobian`, every column
at once), then each convolutional stage applied to the tangent fields without its bias, times the GELU slope
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
* elements go through in chunks that keep a stage's tangent fields within a few MB (cache).

Decoders whose per-cell blocks would exceed :data:`KERNEL_NUMBERS` (the paper-size 2D and 3D ones, where
the convolutions' own cost dominates anyway) are not handled (:func:`supports_decoder_variance`).
"""

from __future__ import annotations

import itertools
import math
import weakref
from dataclasses import dataclass

import torch
from torch import nn

from .backbones import ConvDecoder, fc_jacobian, gelu_slope

#: Numbers in the largest tangent field of one chunk (cells x channels x elements x columns): 4 MB in float32.
CHUNK_NUMBERS = 2**20
#: The most numbers the per-cell blocks of all stages may hold (64 MB in float32).
KERNEL_NUMBERS = 2**24
_UPSAMPLE_MODE = {1: "linear", 2: "bilinear", 3: "trilinear"}
_CACHE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


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


def decoder_variance(decoder: ConvDecoder, x: torch.Tensor, factor: torch.Tensor) -> torch.Tensor:
    """``diag(G F F^T G^T)`` of ``decoder`` at its inputs ``x`` (B, r): (B, C_out, *grid), normalized units.

    ``factor`` (B, r, d): the columns ``f_j`` of a factor of each element's covariance; ``G`` the decoder's
    Jacobian at ``x``, never formed. Exact: no sampling, no finite differences.
    """
    if not supports_decoder_variance(decoder):
        raise TypeError("decoder_variance linearizes a ConvDecoder with exact GELU activations and per-cell "
                        f"blocks of at most {KERNEL_NUMBERS} numbers only")
    if x.ndim != 2 or factor.ndim != 3 or factor.shape[:2] != x.shape:
        raise ValueError(f"x must be (B, r) and factor (B, r, d), got {tuple(x.shape)} and {tuple(factor.shape)}")
    with torch.no_grad():
        lin = _linearization(decoder)
        hidden_net = decoder.fc[:-1]
        hidden = hidden_net(x)
        # d hidden / dx times the factor, (B, h, d): the tangents at the last dense layer's input
        columns = fc_jacobian(hidden_net, x) @ factor if len(hidden_net) else factor
        largest = max(_stage_numbers(decoder, i) for i in range(len(decoder.deconv)))
        step = max(1, CHUNK_NUMBERS // (largest * factor.shape[2]))
        parts = [_chunk_variance(decoder, lin, hidden[s:s + step], columns[s:s + step])
                 for s in range(0, x.shape[0], step)]
        return torch.cat(parts)


def _chunk_variance(decoder: ConvDecoder, lin: _Linearization, hidden: torch.Tensor,
                    columns: torch.Tensor) -> torch.Tensor:
    """:func:`decoder_variance` of the elements whose last hidden layer is ``hidden`` (b, h), with the
    tangents ``columns`` (b, h, d) there."""
    batch, h, d = columns.shape
    ndim = decoder.ndim
    flat = lin.weight.reshape(-1, h)
    pre = (flat @ hidden.T).view(*lin.weight.shape[:-1], batch) + lin.bias  # the first stage's pre-activation
    tangent = (flat @ columns.permute(1, 0, 2).reshape(h, batch * d)).view(*lin.weight.shape[:-1], batch, d)
    for i, stage in enumerate(lin.stages):
        slope = gelu_slope(pre)
        if i < len(lin.stages) - 1:  # the next stage's slope needs its pre-activation
            upcoming = _apply(stage, decoder.act(pre)) + stage.bias[:, None]
        tangent = _apply(stage, tangent, slope).unflatten(-1, (batch, d))
        pre = upcoming if i < len(lin.stages) - 1 else None
    var = tangent.pow(2).sum(-1)  # (*grid, C_out, b)
    return var.permute(ndim + 1, ndim, *range(ndim))


def _apply(stage: _Stage, t: torch.Tensor, slope: torch.Tensor | None = None) -> torch.Tensor:
    """``stage`` (no bias) on the fields ``t`` (*cells, C_in, N), or on ``t`` (*cells, C_in, b, d) times
    ``slope`` (*cells, C_in, b): (*2 cells, C_out, N), the rows innermost throughout.

    On the flattened padded grid a cell's window is a fixed flat shift from it, so per offset of the leading
    axes the windows over the last axis (``w`` cells x ``C_in``, contiguous) are one strided view; the rows
    of the padded columns of the leading axes compute values that are dropped.
    """
    cells, lo, ndim = stage.cells, stage.lo, len(stage.cells)
    w = stage.lo + stage.hi + 1
    c_in = t.shape[ndim]
    n = t[(0,) * (ndim + 1)].numel()
    size = [c + w - 1 for c in cells]
    plane = [math.prod(size[a + 1:]) for a in range(ndim)]  # flat strides of the padded grid, in cells
    total = math.prod(size)
    flat = t.new_empty(total + (w - 1) * sum(plane[1:]), c_in, n)  # the last rows' windows read past the grid
    grid = flat[:total].view(*size, c_in, n)
    for a in range(ndim):
        grid[(slice(None),) * a + (slice(0, lo),)] = 0
        grid[(slice(None),) * a + (slice(lo + cells[a], None),)] = 0
    flat[total:] = 0
    inner = grid[tuple(slice(lo, lo + c) for c in cells)]
    if slope is None:
        inner.copy_(t)
    else:
        torch.mul(t, slope[..., None], out=inner.unflatten(-1, t.shape[-2:]))
    rows = cells[0] * plane[0]
    out = None
    for j, lead in enumerate(itertools.product(range(w), repeat=ndim - 1)):
        shift = sum(o * plane[a] for a, o in enumerate(lead))
        windows = flat.as_strided((rows, w * c_in, n), (c_in * n, n, 1), shift * c_in * n)
        part = torch.bmm(stage.kernels[j], windows)
        out = part if out is None else out.add_(part)
    c_out = out.shape[1] // 2**ndim
    out = out.view(cells[0], *size[1:], *(2,) * ndim, c_out, n)[(slice(None), *(slice(0, c) for c in cells[1:]))]
    interleaved = [axis for a in range(ndim) for axis in (a, ndim + a)]  # cell q_a, then its phase a_a
    return out.permute(*interleaved, 2 * ndim, 2 * ndim + 1).reshape(*(2 * c for c in cells), c_out, n)


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
        x = nn.functional.interpolate(x, scale_factor=2, mode=_UPSAMPLE_MODE[decoder.ndim])
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
