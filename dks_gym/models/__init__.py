"""Latent models of the paper (Sections II.B-II.D, Appendix A): Koopman, MLP, xLSTM and pDMD.

``build_model(benchmark, model, r=32, preset="paper" | "lite")`` returns a :class:`LatentModel` with the
uniform interface ``encode``/``decode`` (physical units), ``forecast``/``forecast_jacobian`` and
``observe``, batched over a leading dimension.
"""

from __future__ import annotations

from .backbones import ConvDecoder, ConvEncoder, ParametricEncoder
from .embedding import ParameterEmbedding
from .koopman import KoopmanOperator, dissipative_generator
from .latent_model import LatentModel, NeuralLatentModel, build_model, count_parameters
from .mlp import MLPTransition
from .pdmd import PDMD, streamed_pod
from .presets import (
    BENCHMARK_SHAPES,
    MODEL_KINDS,
    MODEL_PRESETS,
    PAPER_LATENT_PARAM_COUNTS,
    PAPER_PARAM_COUNTS,
    BackboneSpec,
    BenchmarkShape,
    backbone_spec,
    benchmark_shape,
)
from .xlstm import XLSTMTransition, xlstm_block_stack

__all__ = [
    "BENCHMARK_SHAPES",
    "MODEL_KINDS",
    "MODEL_PRESETS",
    "PAPER_LATENT_PARAM_COUNTS",
    "PAPER_PARAM_COUNTS",
    "PDMD",
    "BackboneSpec",
    "BenchmarkShape",
    "ConvDecoder",
    "ConvEncoder",
    "KoopmanOperator",
    "LatentModel",
    "MLPTransition",
    "NeuralLatentModel",
    "ParameterEmbedding",
    "ParametricEncoder",
    "XLSTMTransition",
    "backbone_spec",
    "benchmark_shape",
    "build_model",
    "count_parameters",
    "dissipative_generator",
    "streamed_pod",
    "xlstm_block_stack",
]
