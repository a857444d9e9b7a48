"""Checkpoint files of trained latent models: safetensors with JSON metadata, written atomically.

One file per (benchmark, model, model preset, r, T) under ``data_home()/models/``, named
``{benchmark}-{model}-{preset}-r{r}-T{T}.safetensors`` (pDMD has no preset or horizon:
``{benchmark}-pdmd-r{r}.safetensors``). A model trained on a dataset preset other than ``paper`` gets
the suffix ``-data-{preset}`` so that a demo model trained on the ``small`` data never shadows the
paper one.

The file holds only tensors and text, never a pickle:

- ``model.<name>``: the model's ``state_dict`` (weights, normalization statistics, cell type; for pDMD
  the POD basis, singular values, training coefficients and parameters);
- ``optimizer.<index>.<name>``: the Adam state (``step``, ``exp_avg``, ``exp_avg_sq`` per parameter),
  so training resumes exactly;
- ``training.generator``: the state of the batch-sampling ``torch.Generator``;
- ``training.losses``: (steps done, 4) history of the total loss and its three terms;
- header metadata ``{"dks_gym": JSON}``: benchmark, model kind, preset, r, T, dt, steps done and
  planned, batch size, learning rate, seed, the dataset's identity and what is needed to rebuild the
  model (see :func:`build_metadata`).

The dataset identity is its path, preset and ``created`` attribute (informational) and a SHA-256
fingerprint of the train parameters, the train statistics, the frame times and the train-split shape.
Only the fingerprint decides whether a dataset matches: a regenerated but identical dataset is accepted,
a different one is refused.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..benchmarks import PRESETS
from ..dataset import Dataset
from ..atomic import atomic_path
from ..home import data_home, ensure_writable
from ..locks import file_lock
from .build import build_model
from .latent_model import LatentModel
from .presets import MODEL_KINDS, MODEL_PRESETS, BenchmarkShape, benchmark_shape

FORMAT = "dks-gym-checkpoint"
FORMAT_VERSION = 1
_METADATA_KEY = "dks_gym"
_MODEL, _OPTIMIZER, _TRAINING, _CALIBRATION = "model.", "optimizer.", "training.", "calibration."


class CheckpointMissing(FileNotFoundError):
    """No finished checkpoint where one was expected; the message names the command that trains it."""


def models_dir() -> Path:
    """Directory of the trained models: ``data_home()/models`` (not created)."""
    return data_home() / "models"


def checkpoint_name(benchmark: str, model: str, preset: str = "lite", r: int = 32, T: int = 1,
                    *, data_preset: str | None = "paper") -> str:
    """File name of a checkpoint (see the module docstring)."""
    stem = f"{benchmark}-pdmd-r{r}" if model == "pdmd" else f"{benchmark}-{model}-{preset}-r{r}-T{T}"
    if data_preset not in (None, "paper"):
        stem += f"-data-{data_preset}"
    return stem + ".safetensors"


def checkpoint_path(benchmark: Any, model: str, preset: str = "lite", r: int = 32, T: int = 1,
                    *, data_preset: str | None = "paper") -> Path:
    """Default location of a checkpoint under ``data_home()/models``."""
    name = benchmark_shape(benchmark).name
    check_model_args(model, preset, r, T)
    return models_dir() / checkpoint_name(name, model, preset, r, T, data_preset=data_preset)


def loss_curve_path(checkpoint: Path | str) -> Path:
    """The loss-curve figure written beside a checkpoint: ``NAME.loss.png`` for ``NAME.safetensors``."""
    checkpoint = Path(checkpoint)
    return checkpoint.with_name(checkpoint.stem + ".loss.png")


def check_model_args(model: str, preset: str, r: int, T: int) -> None:
    """Raise a clear ValueError for an unknown model or preset, or a non-positive r or T."""
    if model not in MODEL_KINDS:
        raise ValueError(f"unknown model {model!r}; choose one of {', '.join(MODEL_KINDS)}")
    if preset not in MODEL_PRESETS:
        raise ValueError(f"unknown model preset {preset!r}; choose one of {', '.join(MODEL_PRESETS)}")
    if isinstance(r, bool) or int(r) != r or r < 1:
        raise ValueError(f"latent dimension r must be a positive integer, got {r!r}")
    if isinstance(T, bool) or int(T) != T or T < 1:
        raise ValueError(f"training horizon T must be a positive integer, got {T!r}")


def train_command(benchmark: str, model: str, preset: str, r: int, T: int, data_preset: str | None,
                  data_path: Path | str | None = None) -> str:
    """The ``dks-gym train`` command line that produces this checkpoint: on the data home's preset file, or on
    the file ``data_path`` where the data are no preset of the data home (a custom benchmark's, say)."""
    if data_preset not in (None, *PRESETS) and data_path is not None:
        cmd = f"dks-gym train --data {data_path} --model {model}"
    else:
        cmd = f"dks-gym train {benchmark} --model {model}"
    if model != "pdmd":
        cmd += f" --preset {preset}"
    cmd += f" --r {r}"
    if model != "pdmd":
        cmd += f" --T {T}"
    if data_preset in PRESETS and data_preset != "paper":
        cmd += f" --data-preset {data_preset}"
    return cmd


# Dataset identity ------------------------------------------------------------------------------------
def dataset_identity(dataset: Dataset) -> dict[str, Any]:
    """Path, preset, ``created`` attribute and content fingerprint of a :class:`dks_gym.dataset.Dataset`."""
    h = hashlib.sha256()
    h.update(dataset.benchmark.name.encode())
    h.update(np.asarray(dataset.fields("train").shape, dtype="<i8").tobytes())
    for values in (dataset.params("train"), dataset.stats_mean, dataset.stats_std, dataset.time):
        h.update(np.ascontiguousarray(values, dtype="<f8").tobytes())
    return {
        "path": str(dataset.path),
        "preset": dataset.preset,
        "created": _created(dataset),
        "fingerprint": h.hexdigest(),
    }


def _created(dataset: Dataset) -> str | None:
    created = getattr(dataset, "created", None)
    return None if created is None else str(created)


# Metadata --------------------------------------------------------------------------------------------
def build_metadata(model: LatentModel, *, preset: str, T: int, dataset: Dataset, **training: Any) -> dict[str, Any]:
    """Metadata of a checkpoint of ``model`` trained on ``dataset``; ``training`` adds steps, batch, lr, seed."""
    from ..version import __version__

    meta: dict[str, Any] = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "benchmark": model.benchmark,
        "model": model.kind,
        "preset": None if model.fitted_in_closed_form else preset,
        "r": model.r,
        "T": None if model.fitted_in_closed_form else int(T),
        "dt": model.dt,
        "shape": model.shape.record(),  # what rebuilds the model without the benchmark (a custom one's file)
        "dataset": dataset_identity(dataset),
        "dks_gym_version": __version__,
        "torch_version": torch.__version__,
    }
    meta.update(model.checkpoint_metadata())
    meta.update(training)
    return meta


def check_metadata(
    metadata: dict[str, Any],
    path: Path | str,
    *,
    benchmark: Any = None,
    model: str | None = None,
    r: int | None = None,
    preset: str | None = None,
    T: int | None = None,
    dataset: Dataset | None = None,
) -> None:
    """Refuse (ValueError) a checkpoint whose benchmark, model, r, preset, T or dataset differ from the request."""
    if metadata.get("format") != FORMAT:
        raise ValueError(f"{path} is not a dks-gym checkpoint (no '{FORMAT}' metadata)")
    if int(metadata.get("format_version", -1)) != FORMAT_VERSION:
        raise ValueError(
            f"{path} has checkpoint format version {metadata.get('format_version')}; this dks-gym reads "
            f"{FORMAT_VERSION}. Retrain it (dks-gym train ... --restart)."
        )
    wanted = {
        "benchmark": None if benchmark is None else benchmark_shape(benchmark).name,
        "model": model,
        "r": r,
    }
    if metadata.get("model") != "pdmd":  # pDMD has no architecture preset and no training horizon
        wanted.update(preset=preset, T=T)
    for key, value in wanted.items():
        if value is not None and metadata.get(key) != value:
            raise ValueError(
                f"checkpoint {path} is for {key} = {metadata.get(key)!r}, not {value!r} "
                f"({_describe(metadata)}); load the checkpoint that matches, or train one with "
                f"`dks-gym train`"
            )
    if dataset is not None:
        ident = dataset_identity(dataset)
        stored = metadata.get("dataset", {})
        if stored.get("fingerprint") != ident["fingerprint"]:
            command = train_command(metadata["benchmark"], metadata["model"], metadata.get("preset") or "lite",
                                    metadata["r"], metadata.get("T") or 1, ident["preset"] or "custom", ident["path"])
            raise ValueError(
                f"checkpoint {path} was trained on another dataset ({stored.get('path')}, preset "
                f"{stored.get('preset')}, created {stored.get('created')}) than {ident['path']} (preset "
                f"{ident['preset']}, created {ident['created']}): their train parameters or statistics differ. "
                f"Retrain on this dataset with `{command} --restart`."
            )


def _describe(metadata: dict[str, Any]) -> str:
    parts = [f"{metadata.get('benchmark')} {metadata.get('model')}"]
    if metadata.get("model") != "pdmd":
        parts.append(f"preset {metadata.get('preset')}")
    parts.append(f"r={metadata.get('r')}")
    if metadata.get("model") != "pdmd":
        parts.append(f"T={metadata.get('T')}")
    return ", ".join(parts)


# Writing ---------------------------------------------------------------------------------------------
def save_checkpoint(
    path: Path | str,
    model: LatentModel,
    metadata: dict[str, Any],
    *,
    optimizer_state: dict[str, Any] | None = None,
    training_tensors: dict[str, torch.Tensor] | None = None,
    model_state: dict[str, torch.Tensor] | None = None,
) -> Path:
    """Write model weights, optional Adam state and training tensors with ``metadata``, atomically.

    ``model_state`` replaces ``model.state_dict()`` as the weights stored (the best-on-validation ones); the
    model's ``calibration`` tensors (process noise, reconstruction variance) are stored with them."""
    from safetensors.torch import save_file

    path = Path(path)
    ensure_writable(path.parent)
    tensors = {_MODEL + k: _plain(v) for k, v in (model_state or model.state_dict()).items()}
    if optimizer_state is not None:
        tensors.update({_OPTIMIZER + k: _plain(v) for k, v in flatten_optimizer_state(optimizer_state).items()})
    for k, v in (training_tensors or {}).items():
        tensors[_TRAINING + k] = _plain(v)
    for k, v in model.calibration.items():
        tensors[_CALIBRATION + k] = _plain(v)
    meta = dict(metadata, saved=datetime.now(timezone.utc).isoformat(timespec="seconds"))
    with atomic_path(path) as tmp:  # an interrupted write never leaves a file that looks valid
        save_file(tensors, str(tmp), metadata={_METADATA_KEY: json.dumps(meta, sort_keys=True)})
        os.chmod(tmp, 0o644)  # safetensors creates 0600 files; checkpoints are as shareable as the datasets
    return path


def update_calibration(path: Path | str, calibration: dict[str, torch.Tensor]) -> Path:
    """Replace the calibration tensors of the checkpoint at ``path`` (weights, Adam state, training tensors and
    metadata kept), atomically and under the checkpoint's write lock."""
    from safetensors import safe_open
    from safetensors.torch import save_file

    path = Path(path)
    with file_lock(path, "write"):
        raw = {}
        with safe_open(str(path), framework="pt", device="cpu") as f:
            metadata = f.metadata()
            for key in f.keys():  # noqa: SIM118 (safe_open is not a mapping)
                if not key.startswith(_CALIBRATION):
                    raw[key] = f.get_tensor(key)
        raw.update({_CALIBRATION + k: _plain(v) for k, v in calibration.items()})
        with atomic_path(path) as tmp:
            save_file(raw, str(tmp), metadata=metadata)
            os.chmod(tmp, 0o644)
    return path


def _plain(t: torch.Tensor) -> torch.Tensor:
    return t.detach().to("cpu").contiguous().clone()  # clone: safetensors refuses shared storage


def flatten_optimizer_state(state_dict: dict[str, Any]) -> dict[str, torch.Tensor]:
    """``optimizer.state_dict()["state"]`` as flat ``"<param index>.<name>"`` tensors (no hyperparameters)."""
    flat = {}
    for index, entries in state_dict["state"].items():
        for name, value in entries.items():
            if not isinstance(value, torch.Tensor):
                raise TypeError(f"optimizer state {index}.{name} is not a tensor ({type(value).__name__})")
            flat[f"{index}.{name}"] = value
    return flat


def unflatten_optimizer_state(flat: dict[str, torch.Tensor]) -> dict[int, dict[str, torch.Tensor]]:
    """Inverse of :func:`flatten_optimizer_state`."""
    state: dict[int, dict[str, torch.Tensor]] = {}
    for key, value in flat.items():
        index, name = key.split(".", 1)
        state.setdefault(int(index), {})[name] = value
    return state


# Reading ---------------------------------------------------------------------------------------------
@dataclass
class Checkpoint:
    """The content of a checkpoint file."""

    path: Path
    metadata: dict[str, Any]
    model_state: dict[str, torch.Tensor]
    optimizer_state: dict[int, dict[str, torch.Tensor]] = field(default_factory=dict)
    training: dict[str, torch.Tensor] = field(default_factory=dict)
    calibration: dict[str, torch.Tensor] = field(default_factory=dict)


def read_metadata(path: Path | str) -> dict[str, Any]:
    """The JSON metadata of a checkpoint, without reading its tensors."""
    from safetensors import SafetensorError, safe_open

    path = Path(path)
    if not path.exists():
        raise CheckpointMissing(f"no checkpoint at {path}")
    try:
        with safe_open(str(path), framework="pt") as f:
            raw = (f.metadata() or {}).get(_METADATA_KEY)
    except (SafetensorError, OSError) as exc:
        raise ValueError(f"{path} is not a readable safetensors checkpoint ({exc}); delete it and retrain") from exc
    if raw is None:
        raise ValueError(f"{path} is not a dks-gym checkpoint (no '{_METADATA_KEY}' metadata)")
    return json.loads(raw)


def calibration_names(path: Path | str) -> set[str]:
    """The names of the calibration tensors in the checkpoint at ``path`` (``Q``, ``Q_scale`` ...), without
    reading any tensor."""
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as f:
        return {k[len(_CALIBRATION):] for k in f.keys() if k.startswith(_CALIBRATION)}  # noqa: SIM118


def read_checkpoint(path: Path | str, *, optimizer: bool = True, training: bool = True) -> Checkpoint:
    """Read a checkpoint: the model tensors, and the Adam state and training tensors unless switched off."""
    from safetensors import safe_open

    path = Path(path)
    metadata = read_metadata(path)
    model_state: dict[str, torch.Tensor] = {}
    optimizer_flat: dict[str, torch.Tensor] = {}
    training_tensors: dict[str, torch.Tensor] = {}
    calibration: dict[str, torch.Tensor] = {}
    with safe_open(str(path), framework="pt", device="cpu") as f:
        for key in f.keys():  # noqa: SIM118 (safe_open is not a mapping)
            if key.startswith(_MODEL):
                model_state[key[len(_MODEL):]] = f.get_tensor(key)
            elif optimizer and key.startswith(_OPTIMIZER):
                optimizer_flat[key[len(_OPTIMIZER):]] = f.get_tensor(key)
            elif training and key.startswith(_TRAINING):
                training_tensors[key[len(_TRAINING):]] = f.get_tensor(key)
            elif key.startswith(_CALIBRATION):
                calibration[key[len(_CALIBRATION):]] = f.get_tensor(key)
    return Checkpoint(path, metadata, model_state, unflatten_optimizer_state(optimizer_flat), training_tensors,
                      calibration)


def model_from_checkpoint(checkpoint: Checkpoint | Path | str, device: str | torch.device = "cpu") -> LatentModel:
    """Rebuild the model described by a checkpoint and load its weights (in eval mode, on ``device``)."""
    if not isinstance(checkpoint, Checkpoint):
        checkpoint = read_checkpoint(checkpoint, optimizer=False, training=False)
    meta, state = checkpoint.metadata, checkpoint.model_state
    check_metadata(meta, checkpoint.path)
    kwargs: dict[str, Any] = {
        "dt": meta["dt"],
        "stats_mean": state["stats_mean"].numpy(),
        "stats_std": state["stats_std"].numpy(),
    }
    # The stored shape where there is one (every checkpoint since custom benchmarks; the shipped files predate it).
    benchmark = BenchmarkShape.from_record(meta["shape"]) if "shape" in meta else meta["benchmark"]
    if meta["model"] == "pdmd":
        model = build_model(benchmark, "pdmd", r=meta["r"], **kwargs)
        model.pinv_rtol = meta.get("pdmd", {}).get("pinv_rtol")
        model.fit_info = meta.get("pdmd", {}).get("fit_info", {})
    else:
        if "cell_type" in state:
            kwargs["cell_type"] = state["cell_type"].numpy()
        model = build_model(benchmark, meta["model"], r=meta["r"], preset=meta["preset"], seed=None, **kwargs)
    model.load_state_dict(state)
    model.calibration = dict(checkpoint.calibration)
    model.checkpoint_path = Path(checkpoint.path)  # where a later calibration step (the Q scale) is kept
    return model.to(device).eval()
