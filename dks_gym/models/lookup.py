"""The lookup of trained models: the user's checkpoint, else the shipped model, else training on request.

:func:`load_model` is the single entry point that returns a trained model; :func:`locate_model` is its lookup
without loading or training (``dks-gym reproduce`` checks with it what is missing before it runs), and
:func:`is_stale` says when a cached checkpoint was trained with another schedule than its preset's current
one, so that it counts as missing.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from ..dataset import Dataset
from .checkpoint import (
    CheckpointMissing,
    check_metadata,
    check_model_args,
    checkpoint_path,
    model_from_checkpoint,
    read_metadata,
    train_command,
)
from .latent_model import LatentModel
from .presets import benchmark_shape
from .schedule import training_schedule
from .shipped import find_shipped
from .training import resolve_device, train_model

logger = logging.getLogger(__name__)


def is_stale(meta: dict[str, Any], benchmark: Any, model: str, preset: str) -> bool:
    """Whether a finished checkpoint (its ``meta``) was trained with another schedule than ``preset``'s current
    one (an older dks-gym, custom steps): :func:`load_model` retrains such a cached checkpoint."""
    return (bool(meta.get("complete")) and model != "pdmd"
            and meta.get("preset_schedule") != training_schedule(benchmark, preset).record())


@dataclass(frozen=True)
class ModelLookup:
    """Where :func:`load_model` finds a trained model without training, and what to say when it does not."""

    found: Path | None  # the file to load: the user's checkpoint or the shipped one; None when neither serves
    checkpoint: Path  # the user's checkpoint path (where training writes)
    reason: str  # why nothing was found (empty when found)
    command: str  # the `dks-gym train` command that makes it
    stale: bool  # the user's checkpoint exists but was trained with another schedule


def locate_model(benchmark: Any, model: str, r: int = 32, preset: str = "lite", T: int = 1, *,
                 dataset: Dataset | None = None, data_preset: str = "paper",
                 path: Path | str | None = None) -> ModelLookup:
    """The lookup of :func:`load_model`, without loading or training: the user's own complete checkpoint
    (``path``, or the data home's), else the shipped model when ``dataset`` matches its training data.
    Raises ValueError for a checkpoint of another benchmark, r, preset, T or dataset."""
    shape = benchmark_shape(benchmark, dataset)
    name = shape.name
    check_model_args(model, preset, r, T)
    if dataset is not None and dataset.benchmark.name != name:
        raise ValueError(f"dataset {dataset.path} is for {dataset.benchmark.name}, not {name}")
    data_preset = (dataset.preset or "custom") if dataset is not None else data_preset
    cached = path is None  # the data home's checkpoint must follow the preset; an explicit path is taken as is
    path = Path(path) if path is not None else checkpoint_path(shape, model, preset, r, T, data_preset=data_preset)
    command = train_command(name, model, preset, r, T, data_preset, None if dataset is None else dataset.path)
    stale = False
    if path.exists():
        meta = read_metadata(path)
        check_metadata(meta, path, benchmark=shape, model=model, r=r, preset=preset, T=T, dataset=dataset)
        stale = cached and is_stale(meta, shape, model, preset)
        if meta.get("complete") and not stale:
            return ModelLookup(path, path, "", command, False)
        if stale:  # trained by an older dks-gym, or with other settings than the preset's
            reason = (f"{path} was trained with another schedule than the current {preset} preset's "
                      f"({meta.get('steps_done')} steps; schedule {meta.get('schedule')})")
            command += " --restart"
        else:
            reason = f"training in {path} stopped at step {meta.get('steps_done')} of {meta.get('steps')}"
    else:
        reason = f"no trained {name} {model} model (preset {preset}, r={r}, T={T}) at {path}"
    shipped = find_shipped(name, model, preset, r, T) if cached else None
    if shipped is not None:
        differences = [] if dataset is None else shipped.differences(dataset)
        if not differences:
            return ModelLookup(shipped.path, path, "", command, stale)
        reason += (f"; the {name} {model} model that ships with dks-gym was trained on other data than "
                   f"{dataset.path}: {'; '.join(differences)}")
    return ModelLookup(None, path, reason, command, stale)


def load_model(
    benchmark: Any,
    model: str,
    r: int = 32,
    preset: str = "lite",
    T: int = 1,
    *,
    dataset: Dataset | None = None,
    data_preset: str = "paper",
    train_if_missing: bool = False,
    device: str | torch.device = "cpu",
    progress: bool = True,
    path: Path | str | None = None,
) -> LatentModel:
    """The trained ``model`` of ``benchmark``, in eval mode on ``device``.

    Looked up in this order: the user's own checkpoint (``path``, or the data home's
    ``models/`` for (benchmark, model, preset, r, T) and the dataset preset of ``dataset`` or
    ``data_preset``); then the model that ships with dks-gym (:mod:`dks_gym.models.shipped`), used only
    when ``dataset`` matches the data it was trained on; then, with ``train_if_missing=True``, training
    (or resuming) it with the preset's schedule and a progress bar. Otherwise :class:`CheckpointMissing`
    (a FileNotFoundError) says what was looked for, what differs from a shipped model, and names the
    ``dks-gym train`` command. A cached checkpoint trained with another schedule than the preset's (an
    older dks-gym, custom steps) is passed over; one given by ``path`` is loaded as it is. A checkpoint
    for another benchmark, r, preset or T, or trained on another dataset than ``dataset``, raises
    ValueError. Nothing is written unless ``train_if_missing`` trains.
    """
    shape = benchmark_shape(benchmark, dataset)
    name = shape.name
    lookup = locate_model(shape, model, r, preset, T, dataset=dataset, data_preset=data_preset, path=path)
    if lookup.found is not None:
        return model_from_checkpoint(lookup.found, resolve_device(device))
    data_preset = (dataset.preset or "custom") if dataset is not None else data_preset
    path, reason, command, stale = lookup.checkpoint, lookup.reason, lookup.command, lookup.stale
    if not train_if_missing:
        raise CheckpointMissing(
            f"{reason}. Train it with `{command}`{'' if stale else ' (it resumes an unfinished run)'}, or call "
            "load_model(..., train_if_missing=True)."
        )
    what = ("retraining it with the current schedule" if stale else
            "resuming its unfinished training" if path.exists() else "training it on first use")
    logger.info("%s %s model (%s, r=%d, T=%d): %s, as `%s` would; it is kept at %s for later runs",
                name, model, preset, r, T, what, command, path)
    result = train_model(shape, model, r, preset, T, dataset=dataset, data_preset=data_preset, device=device,
                         path=path, progress=progress, resume=not stale)
    return result.model


__all__ = ["ModelLookup", "is_stale", "load_model", "locate_model"]
