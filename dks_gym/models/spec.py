"""Which trained model to use, named rather than built: :class:`ModelSpec`, the one place a lookup's options live.

A wrapper takes a model object, a kind name ("koopman": the shipped or cached lite model with r = 32, T = 1
on the CPU) or a ``ModelSpec`` for any other lookup; the spec is turned into a model by
:func:`~dks_gym.models.load_model` with the env's dataset, exactly as ``load_model`` would be called by hand.
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass

import torch

from ..dataset import Dataset
from .latent_model import LatentModel
from .presets import MODEL_KINDS, MODEL_PRESETS
from .lookup import load_model


@dataclass(frozen=True)
class ModelSpec:
    """A trained model by name: ``kind`` (one of :data:`~dks_gym.models.MODEL_KINDS`), ``r`` (latent
    dimension), ``preset`` ("lite" or "paper"), ``T`` (multi-step training horizon), ``device`` (where it
    is loaded; the filter runs there too) and ``train_if_missing`` (train a missing checkpoint and tune its
    Q scale, instead of raising :class:`~dks_gym.models.CheckpointMissing`). These are the keywords of
    :func:`~dks_gym.models.load_model`; the dataset is the environment's.
    """

    kind: str
    r: int = 32
    preset: str = "lite"
    T: int = 1
    device: str | torch.device = "cpu"
    train_if_missing: bool = False

    def __post_init__(self) -> None:
        if self.kind not in MODEL_KINDS:
            raise ValueError(f"unknown model {self.kind!r}; choose one of {', '.join(MODEL_KINDS)} "
                             "or pass a model object")
        if self.preset not in MODEL_PRESETS:
            raise ValueError(f"unknown model preset {self.preset!r}; choose one of {', '.join(MODEL_PRESETS)}")
        for name in ("r", "T"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")

    def load(self, benchmark: str, dataset: Dataset | None = None) -> LatentModel:
        """The model this spec names for ``benchmark``, trained on ``dataset`` (see :func:`load_model`)."""
        return load_model(benchmark, self.kind, r=self.r, preset=self.preset, T=self.T, dataset=dataset,
                          device=self.device, train_if_missing=self.train_if_missing)
