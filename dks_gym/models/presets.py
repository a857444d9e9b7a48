"""Architecture presets: the paper's encoder/decoder tables (``paper``) and narrow CPU versions (``lite``), and
the rule that sizes the same structure for any other grid (:func:`sized_backbone`).

The ``paper`` specs transcribe the architecture tables of the paper (Burgers, cylinder, sphere; the
dambreak uses the cylinder structure with six input and five output channels). Built as specified they
reproduce the parameter counts of the paper's table ``tab:ld32_param_counts`` exactly at r = 32
(:data:`PAPER_PARAM_COUNTS`). The ``lite`` specs keep every layer type, kernel, stride and the number of
layers, and divide the convolution widths by 4 (1D) or 16 (2D, 3D) and the fully connected widths by 4
(1D, 2D) or 8 (3D), so that the models train on two CPU cores in minutes (about 0.5-1 s per Adam step at
batch 32 in 2D, 2 s at batch 4 on the sphere, measured on a loaded 2-core machine).

The benchmark constants the models need (grid, channels, latent step, parameter range) come from the
benchmark registry (SPEC section 1) or a benchmark object (a custom one, from its schema file) through
:func:`benchmark_shape`, so models can be built (and counted) without data.

A benchmark without a table of the paper (a custom one, :class:`~dks_gym.benchmarks.CustomBenchmark`) gets
its encoder and decoder from :func:`sized_backbone`, a stated rule; the four keep their tables exactly.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from ..benchmarks import BENCHMARKS, Benchmark
from ..names import MODEL_KINDS  # noqa: F401 - re-exported: the one list of model kinds, for models/

MODEL_PRESETS = ("paper", "lite")


@dataclass(frozen=True)
class BenchmarkShape:
    """What a latent model needs to know about a benchmark (SPEC section 1)."""

    name: str
    grid: tuple[int, ...]
    n_fields: int  # physical channels stored in the dataset
    has_cell_type: bool  # the encoder appends the cell type as an extra input channel
    reconstructs_cell_type: bool  # the decoder outputs the cell type as an extra channel (sphere)
    dt: float  # latent step of K(mu; dt), equal to the frame spacing
    param_range: tuple[float, float]
    channels: tuple[str, ...] = ()  # names of the physical channels

    @property
    def ndim(self) -> int:
        return len(self.grid)

    @property
    def in_channels(self) -> int:
        return self.n_fields + int(self.has_cell_type)

    @property
    def out_channels(self) -> int:
        return self.n_fields + int(self.reconstructs_cell_type)

    def record(self) -> dict[str, Any]:
        """The shape as JSON-ready checkpoint metadata: a checkpoint rebuilds its model from it, without the
        benchmark's registry entry or its data (a custom benchmark has neither)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_record(cls, record: dict[str, Any]) -> "BenchmarkShape":
        """The shape :meth:`record` wrote (JSON turns its tuples into lists; they are turned back)."""
        values = {f.name: record[f.name] for f in dataclasses.fields(cls) if f.name in record}
        for name in ("grid", "param_range", "channels"):
            if name in values:
                values[name] = tuple(values[name])
        return cls(**values)


# Per the paper's architecture tables only the sphere decoder also outputs the cell type (5 channels).
_RECONSTRUCTS_CELL_TYPE = frozenset({"sphere"})


def _shape_of(benchmark: Benchmark) -> BenchmarkShape:
    return BenchmarkShape(
        name=benchmark.name,
        grid=tuple(benchmark.grid),
        n_fields=len(benchmark.channels),
        has_cell_type=bool(benchmark.cell_type_codes),
        reconstructs_cell_type=benchmark.name in _RECONSTRUCTS_CELL_TYPE,
        dt=float(benchmark.dt),
        param_range=(float(benchmark.param_range[0]), float(benchmark.param_range[1])),
        channels=tuple(benchmark.channels),
    )


BENCHMARK_SHAPES: dict[str, BenchmarkShape] = {name: _shape_of(b) for name, b in BENCHMARKS.items()}


@dataclass(frozen=True)
class BackboneSpec:
    """Convolutional encoder/decoder of one benchmark.

    Encoder: ``len(conv_channels)`` strided convolutions, flatten, fully connected layers through
    ``fc_widths`` to r. Decoder: the mirror image, fully connected r -> reversed(fc_widths) -> flat
    feature map, then either ``upsample`` (interpolate x2 followed by a size-preserving ConvTranspose,
    Burgers and cylinder tables) or ``transpose`` (strided ConvTranspose with output_padding, sphere table).
    """

    conv_channels: tuple[int, ...]
    fc_widths: tuple[int, ...]
    kernel_size: int
    padding: int
    # GELU after every encoder convolution (sphere) or after all but the last one (Burgers, cylinder).
    act_after_last_conv: bool
    decoder_mode: str  # "upsample" or "transpose"

    def __post_init__(self) -> None:
        if self.decoder_mode not in ("upsample", "transpose"):
            raise ValueError(f"decoder_mode must be 'upsample' or 'transpose', got {self.decoder_mode!r}")


# Burgers table: Conv1D 1->8->16->32 (k3 s2 p1), FC (32x128)->512->256->r; decoder FC r->256->512->(32x128),
# 3x (linear upsample x2, ConvTranspose1D k3 s1 p1) 32->16->8->1.
# Cylinder table: Conv2D 4->128->256->512 (k5 s2 p2), FC (512x8x8)->512->256->r; decoder mirror with
# bilinear upsampling and ConvTranspose2D k5 s1 p2, 512->256->128->3.
# Sphere table: Conv3D 5->64->128->256->512 (k3 s2 p1, GELU after all), FC (512x4x4x4)->1024->r; decoder
# FC r->1024->(512x4x4x4), ConvTranspose3D 512->256->128->64->5 (k3 s2 p1 output_padding 1).
_PAPER_1D = BackboneSpec((8, 16, 32), (512, 256), 3, 1, False, "upsample")
_PAPER_2D = BackboneSpec((128, 256, 512), (512, 256), 5, 2, False, "upsample")
_PAPER_3D = BackboneSpec((64, 128, 256, 512), (1024,), 3, 1, True, "transpose")

_LITE_1D = BackboneSpec((2, 4, 8), (128, 64), 3, 1, False, "upsample")
_LITE_2D = BackboneSpec((8, 16, 32), (128, 64), 5, 2, False, "upsample")
_LITE_3D = BackboneSpec((4, 8, 16, 32), (128,), 3, 1, True, "transpose")

BACKBONES: dict[str, dict[str, BackboneSpec]] = {
    "paper": {"burgers": _PAPER_1D, "cylinder": _PAPER_2D, "dambreak": _PAPER_2D, "sphere": _PAPER_3D},
    "lite": {"burgers": _LITE_1D, "cylinder": _LITE_2D, "dambreak": _LITE_2D, "sphere": _LITE_3D},
}

# Latent maps (identical in both presets: they are small already).
EMBEDDING_HIDDEN_LAYERS = 4  # e(mu): Linear(1, r), then four Linear(r, r) with GELU (Eq. 6)
KOOPMAN_HIDDEN_LAYERS = 4  # Q_theta, d_theta: 4 hidden layers of width r (Table koopman_mlp_hparams)
MLP_HIDDEN_LAYERS = 4  # Table mlp_latent_hparams
MLP_HIDDEN_WIDTH = 105
XLSTM_EMBEDDING_DIM = 32  # Table xlstm_latent_hparams and Appendix A.3
XLSTM_NUM_HEADS = 4
XLSTM_CONV_KERNEL = 4
XLSTM_QKV_BLOCKSIZE = 4

# Table tab:ld32_param_counts at r = 32: (encoder incl. e(mu), decoder).
PAPER_PARAM_COUNTS: dict[str, tuple[int, int]] = {
    "burgers": (2_243_504, 2_243_249),
    "cylinder": (21_031_264, 21_056_003),
    "dambreak": (21_037_664, 21_062_405),
    "sphere": (38_247_008, 38_274_949),
}
PAPER_LATENT_PARAM_COUNTS: dict[str, int] = {"mlp": 43_607, "koopman": 43_296}
# The paper's xLSTM count (43,104; sphere 45,696) is not reachable with xlstm 2.x at the stated config.
PAPER_XLSTM_PARAM_COUNT_UNREACHABLE = 43_104


#: The sizing rule's bottleneck: at most this many cells in all (the paper's: 128 in 1D, 8 x 8 in 2D, 4^3 in 3D).
MAX_BOTTLENECK_CELLS = 128
#: The fewest stride-2 stages the rule uses (the paper's tables have three or four).
MIN_STAGES = 3
#: Per preset: the first convolution width per input channel, the narrowest and the widest first convolution.
_WIDTH_PER_CHANNEL = {"lite": 2, "paper": 8}
#: lite: at least the lite 2D table's 8. Burgers' lite 2-4-8 suits its smooth field; on the KS example (L = 22,
#: 64 points) 2-4-8 left the Koopman and MLP models' reconstructions at 12 % and 19 % of the field's variance,
#: 8-16-32 at 0.5 % and 2.7 % (docs/results/kuramoto-sivashinsky).
_MIN_WIDTH = {"lite": 8, "paper": 8}
_MAX_WIDTH = {"lite": 64, "paper": 512}
#: Per preset and number of axes: the table whose kernel, padding, activations, decoder and dense widths the rule
#: keeps.
_TABLE_OF_NDIM = {"paper": {1: _PAPER_1D, 2: _PAPER_2D, 3: _PAPER_3D}, "lite": {1: _LITE_1D, 2: _LITE_2D, 3: _LITE_3D}}


def stride_stages(grid: tuple[int, ...]) -> int:
    """The rule's number of stride-2 stages: the fewest, at least :data:`MIN_STAGES`, after which the bottleneck
    (``ceil(n / 2**stages)`` cells per axis) has at most :data:`MAX_BOTTLENECK_CELLS` cells. On the paper's grids
    it gives the paper's counts: 3 on 1024 (128 cells), 3 on 64 x 64 (8 x 8), 4 on 64^3 (4^3)."""
    stages = MIN_STAGES
    while math.prod(-(-n // 2**stages) for n in grid) > MAX_BOTTLENECK_CELLS:
        stages += 1
    return stages


def sized_backbone(shape: BenchmarkShape, preset: str = "lite") -> BackboneSpec:
    """The encoder/decoder of a benchmark without a table of the paper, sized from its grid and channels.

    The rule keeps the paper's structure (strided convolutions, a dense bottleneck, a decoder that mirrors them):

    * stages: :func:`stride_stages` of the grid (3 for most grids; more until the bottleneck has at most 128
      cells);
    * convolution widths: stage s has w 2^s channels, w = 2 (lite) or 8 (paper) per encoder input channel
      (fields plus the cell type) but at least 8, and at most 64 (lite) or 512 (paper). On Burgers' one channel
      this is the paper 1D table (8-16-32), and 8-16-32 in lite too (wider than Burgers' lite table, 2-4-8,
      which suits its smooth field but not a chaotic one: :data:`_MIN_WIDTH`); on the cylinder's four inputs
      the lite 2D table (8-16-32);
    * everything else from the table of the same dimension and preset: kernel 3 (1D, 3D) or 5 (2D), the
      decoder's upsampling (1D, 2D) or strided transposed convolutions (3D), dense widths 512-256 (lite
      128-64) in 1D and 2D, 1024 (lite 128) in 3D.

    A grid that is not a multiple of 2^stages along an axis is padded at that axis's upper end to the next
    multiple (zeros, in normalized units: the channel's mean) before the encoder, and the decoder's output
    is cropped back to the grid (:mod:`dks_gym.models.backbones`).
    """
    if preset not in MODEL_PRESETS:
        raise ValueError(f"unknown model preset {preset!r}; choose one of {', '.join(MODEL_PRESETS)}")
    base = max(_WIDTH_PER_CHANNEL[preset] * shape.in_channels, _MIN_WIDTH[preset])
    widths = tuple(min(base * 2**s, _MAX_WIDTH[preset]) for s in range(stride_stages(shape.grid)))
    return dataclasses.replace(_TABLE_OF_NDIM[preset][shape.ndim], conv_channels=widths)


def benchmark_shape(benchmark: object, dataset: Any = None) -> BenchmarkShape:
    """Return the :class:`BenchmarkShape` of a benchmark given by name, by a ``Benchmark`` object (a custom one
    too) or as a shape (returned as it is). With a ``dataset`` (a :class:`~dks_gym.dataset.Dataset`), the name
    of its benchmark resolves through it: a custom benchmark by name."""
    if dataset is not None and isinstance(benchmark, str) and benchmark.lower() == dataset.benchmark.name:
        benchmark = dataset.benchmark
    if isinstance(benchmark, BenchmarkShape):
        return benchmark
    if isinstance(benchmark, Benchmark):
        return _shape_of(benchmark)
    name = getattr(benchmark, "name", benchmark)
    key = str(name).lower()
    if key not in BENCHMARK_SHAPES:
        raise ValueError(f"unknown benchmark {name!r}; choose one of {', '.join(BENCHMARK_SHAPES)}, or pass the "
                         "benchmark object of a custom one (dks_gym.dataset.load_benchmark(path))")
    return BENCHMARK_SHAPES[key]


def backbone_spec(benchmark: object, preset: str = "paper") -> BackboneSpec:
    """Return the encoder/decoder spec of ``benchmark`` in ``preset`` ("paper" or "lite"): the paper's table
    (:data:`BACKBONES`) for the four benchmarks, :func:`sized_backbone` for any other."""
    if preset not in MODEL_PRESETS:
        raise ValueError(f"unknown model preset {preset!r}; choose one of {', '.join(MODEL_PRESETS)}")
    shape = benchmark_shape(benchmark)
    table = BACKBONES[preset].get(shape.name)
    return table if table is not None else sized_backbone(shape, preset)
