"""Latent models of the paper (Sections II.B-II.D, Appendix A): Koopman, MLP, xLSTM and pDMD.

``build_model(benchmark, model, r=32, preset="paper" | "lite")`` returns a :class:`LatentModel` with the
uniform interface ``encode``/``decode`` (physical units), ``forecast``/``forecast_jacobian`` and
``observe``, batched over a leading dimension. :func:`train_model` trains one (Eqs. 10-11) into a
checkpoint with a :class:`TrainingSchedule` (:func:`training_schedule`: a preset's, or one with other steps,
batch size or learning rate) and :func:`load_model` loads a trained one (or trains it when asked); a
:class:`ModelSpec` names one for a wrapper. :class:`FilterableModel` is the Protocol of what the filters need
of any model.
"""

from __future__ import annotations

from .backbones import ConvDecoder, ConvEncoder, ParametricEncoder
from .checkpoint import (
    CheckpointMissing,
    checkpoint_path,
    dataset_identity,
    model_from_checkpoint,
    read_checkpoint,
    read_metadata,
    save_checkpoint,
)
from .embedding import ParameterEmbedding
from .koopman import KoopmanOperator, dissipative_generator
from .build import NEURAL_MAPS, build_model
from .latent_model import KoopmanModel, LatentModel, NeuralLatentModel, count_parameters
from .mlp import MLPTransition
from .pdmd import PDMD
from .pod import streamed_pod
from .protocol import FILTERABLE_MEMBERS, FilterableModel, missing_members, model_device, model_dtype
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
from .calibration import calibrate
from .diagnostics import one_step_error
from .lookup import load_model, locate_model
from .loss import training_loss
from .schedule import TRAINING_SCHEDULES, TrainingSchedule, training_schedule
from .spec import ModelSpec
from .training import TrainingResult, train_model
from .windows import WindowSampler
from .xlstm import XLSTMTransition, xlstm_block_stack

__all__ = [
    "BENCHMARK_SHAPES",
    "FILTERABLE_MEMBERS",
    "MODEL_KINDS",
    "MODEL_PRESETS",
    "NEURAL_MAPS",
    "PAPER_LATENT_PARAM_COUNTS",
    "PAPER_PARAM_COUNTS",
    "PDMD",
    "TRAINING_SCHEDULES",
    "BackboneSpec",
    "BenchmarkShape",
    "CheckpointMissing",
    "ConvDecoder",
    "ConvEncoder",
    "FilterableModel",
    "KoopmanModel",
    "KoopmanOperator",
    "LatentModel",
    "MLPTransition",
    "ModelSpec",
    "NeuralLatentModel",
    "ParameterEmbedding",
    "ParametricEncoder",
    "TrainingResult",
    "TrainingSchedule",
    "WindowSampler",
    "XLSTMTransition",
    "backbone_spec",
    "benchmark_shape",
    "build_model",
    "calibrate",
    "checkpoint_path",
    "count_parameters",
    "dataset_identity",
    "dissipative_generator",
    "load_model",
    "locate_model",
    "missing_members",
    "model_device",
    "model_dtype",
    "model_from_checkpoint",
    "one_step_error",
    "read_checkpoint",
    "read_metadata",
    "save_checkpoint",
    "streamed_pod",
    "train_model",
    "training_loss",
    "training_schedule",
    "xlstm_block_stack",
]
