"""Build a latent model by kind: the one table that says which class and latent map each kind is.

``build_model(benchmark, model, r=32, preset="paper" | "lite")`` returns a
:class:`~dks_gym.models.latent_model.LatentModel` with the uniform interface; :data:`MODEL_BUILDERS` maps
each of :data:`~dks_gym.models.presets.MODEL_KINDS` to what builds it.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import torch
from torch import nn

from ..dataset import Dataset
from .koopman import KoopmanOperator
from .latent_model import ArrayLike, KoopmanModel, LatentModel, NeuralLatentModel
from .mlp import MLPTransition
from .pdmd import BENCHMARK_SETTINGS as PDMD_BENCHMARK_SETTINGS
from .pdmd import PDMD
from .presets import (
    KOOPMAN_HIDDEN_LAYERS,
    MLP_HIDDEN_LAYERS,
    MLP_HIDDEN_WIDTH,
    MODEL_KINDS,
    MODEL_PRESETS,
    XLSTM_CONV_KERNEL,
    XLSTM_EMBEDDING_DIM,
    XLSTM_NUM_HEADS,
    XLSTM_QKV_BLOCKSIZE,
    benchmark_shape,
)
from .xlstm import XLSTMTransition

#: Per neural kind: the model class and the latent map factory ``(r, dt) -> module`` (the paper's tables).
NEURAL_MAPS: dict[str, tuple[type[NeuralLatentModel], Callable[[int, float], nn.Module]]] = {
    "koopman": (KoopmanModel, lambda r, dt: KoopmanOperator(r, dt, KOOPMAN_HIDDEN_LAYERS)),
    "mlp": (NeuralLatentModel, lambda r, dt: MLPTransition(r, MLP_HIDDEN_WIDTH, MLP_HIDDEN_LAYERS)),
    "xlstm": (NeuralLatentModel, lambda r, dt: XLSTMTransition(
        r, XLSTM_EMBEDDING_DIM, XLSTM_NUM_HEADS, XLSTM_CONV_KERNEL, XLSTM_QKV_BLOCKSIZE)),
}
assert set(NEURAL_MAPS) | {PDMD.kind} == set(MODEL_KINDS), "every model kind needs a builder"


def build_model(
    benchmark: Any,
    model: str,
    r: int = 32,
    preset: str = "paper",
    *,
    dataset: Dataset | None = None,
    dt: float | None = None,
    stats_mean: ArrayLike | None = None,
    stats_std: ArrayLike | None = None,
    cell_type: ArrayLike | None = None,
    seed: int | None = 0,
) -> LatentModel:
    """Build a latent model of ``benchmark`` (name, Benchmark or its shape; a custom benchmark's name with its
    ``dataset``): one of :data:`MODEL_KINDS`.

    ``preset`` is "paper" (the paper's architectures, exact parameter counts at r = 32) or "lite"
    (narrower, CPU-trainable). Pass ``dataset=ds`` to take the latent step, the train-split channel
    statistics and the cell type from a :class:`dks_gym.dataset.Dataset`; otherwise the benchmark's
    paper dt and an identity normalization are used (fine for counting parameters and for tests).
    Weights are initialized from ``seed`` without touching the global RNG. A pDMD model is returned
    unfitted: call ``.fit(...)`` or ``.fit_dataset(ds)``. The model is in eval mode, as a loaded one is
    (the training loop switches to training mode and back).
    """
    shape = benchmark_shape(benchmark, dataset)
    if model not in MODEL_KINDS:
        raise ValueError(f"unknown model {model!r}; choose one of {', '.join(MODEL_KINDS)}")
    if preset not in MODEL_PRESETS:
        raise ValueError(f"unknown model preset {preset!r}; choose one of {', '.join(MODEL_PRESETS)}")
    if dataset is not None:
        ds_name = getattr(dataset.benchmark, "name", dataset.benchmark)
        if str(ds_name).lower() != shape.name:
            raise ValueError(f"dataset is for benchmark {ds_name!r}, not {shape.name!r}")
        dt = dataset.dt if dt is None else dt
        stats_mean = dataset.stats_mean if stats_mean is None else stats_mean
        stats_std = dataset.stats_std if stats_std is None else stats_std
        cell_type = dataset.cell_type if cell_type is None else cell_type
    if model == PDMD.kind:
        settings = PDMD_BENCHMARK_SETTINGS.get(shape.name, {})  # regularization a benchmark's data need
        return PDMD(shape, r, dt=dt, stats_mean=stats_mean, stats_std=stats_std, **settings).eval()
    cls, latent_map = NEURAL_MAPS[model]
    devices: Sequence[Any] = []
    with torch.random.fork_rng(devices=devices):
        if seed is not None:
            torch.manual_seed(seed)
        return cls(shape, model, latent_map, r, preset, dt=dt, stats_mean=stats_mean, stats_std=stats_std,
                   cell_type=cell_type).eval()
