"""The trained models that ship inside the package, and the check that a dataset is the one they were trained on.

dks-gym ships the ``lite`` models (r = 32, T = 1) of the four kinds for Burgers, the cylinder and the
dambreak as package data (``dks_gym/models/weights/``), so that a user who has generated a benchmark's
``paper`` data filters it at once, without training. A shipped file is a checkpoint (the format of
:mod:`dks_gym.models.checkpoint`) stripped to what inference needs: the weights and normalization
(``model.*``), the calibration with its tuned Q scale (``calibration.*``) and metadata (the schedule the
model was trained with, its best validation loss, versions) plus the **data fingerprint** of the data it
was trained on (:func:`data_fingerprint`): benchmark, dataset preset, generator name and version, the
train split's shape, a SHA-256 of the train split's parameters and the per-channel mean and standard
deviation. No optimizer state, no loss history, no machine path (the training data's file name only).

A shipped model is used only for a dataset that matches its fingerprint (:func:`fingerprint_differences`):
the same benchmark, preset, generator version, train-split shape and parameters (exactly: they are drawn
from the preset's seed), and per-channel statistics within :data:`STATS_RTOL` of the channel's standard
deviation. That tolerance admits what the same generator writes on another machine (its floating-point
sums may differ in the last bits) and refuses anything that changes the flow: docs/models.md gives the
measurements behind it.

``dks-gym train BENCHMARK --model all --preset lite --export`` writes the shipped files from trained
checkpoints (:func:`export_model`); ``dks-gym models`` lists them and whether the local data match.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..dataset import Dataset
from ..atomic import atomic_path
from .checkpoint import checkpoint_name, read_checkpoint

#: The folder of the shipped files, inside the installed package.
WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
#: What ships: these benchmarks' lite models, r = 32, T = 1 (pDMD: r = 32), trained on their ``paper`` data.
SHIPPED_BENCHMARKS = ("burgers", "cylinder", "dambreak")
SHIPPED_PRESET, SHIPPED_R, SHIPPED_T, SHIPPED_DATA_PRESET = "lite", 32, 1, "paper"
#: Largest accepted difference of a channel's mean or standard deviation, relative to the shipped standard
#: deviation of that channel (measured differences: docs/models.md, "Shipped models").
STATS_RTOL = 1e-5
#: Largest shipped file (bytes); the package's weights stay small. A neural lite model takes about 1.3 MB.
#: pDMD's file is its POD basis and the training coefficients its parametric DMD is refitted from: on the
#: dambreak's five 64 x 64 channels the rank-32 basis alone is 2.6 MB, so pDMD has a limit of its own.
MAX_FILE_BYTES = 3 * 1024 * 1024
MAX_PDMD_FILE_BYTES = 6 * 1024 * 1024
#: Every shipped file together.
MAX_TOTAL_BYTES = 30 * 1024 * 1024
#: Metadata keys of a training checkpoint that an inference file drops (the time it was written).
_DROPPED = ("saved",)


def data_fingerprint(dataset: Dataset) -> dict[str, Any]:
    """What identifies the data a model was trained on, machine-independently (see the module docstring)."""
    params = np.ascontiguousarray(dataset.params("train"), dtype="<f8")
    generator = dict(getattr(dataset, "generator", None) or {})
    return {
        "benchmark": dataset.benchmark.name,
        "preset": dataset.preset,
        "generator": generator.get("name"),
        "generator_version": None if generator.get("version") is None else str(generator.get("version")),
        "train_shape": [int(n) for n in dataset.fields("train").shape],
        "train_params_sha256": hashlib.sha256(params.tobytes()).hexdigest(),
        "stats_mean": [float(v) for v in np.asarray(dataset.stats_mean, dtype=np.float64).reshape(-1)],
        "stats_std": [float(v) for v in np.asarray(dataset.stats_std, dtype=np.float64).reshape(-1)],
    }


def fingerprint_differences(shipped: dict[str, Any], local: dict[str, Any], rtol: float = STATS_RTOL) -> list[str]:
    """What differs between a shipped model's data fingerprint and a dataset's, in words (empty: they match)."""
    differences = []
    for key in ("benchmark", "preset", "generator", "generator_version", "train_shape"):
        if shipped.get(key) != local.get(key):
            differences.append(f"{key.replace('_', ' ')} {local.get(key)!r} "
                               f"(the shipped model's: {shipped.get(key)!r})")
    if shipped.get("train_params_sha256") != local.get("train_params_sha256"):
        differences.append("the train split's parameters")
    if differences:  # statistics of another split or generator say nothing more
        return differences
    std = np.asarray(shipped["stats_std"], dtype=np.float64)
    for name in ("stats_mean", "stats_std"):
        a, b = np.asarray(shipped[name], dtype=np.float64), np.asarray(local[name], dtype=np.float64)
        if a.shape != b.shape:
            differences.append(f"the number of channels ({b.size}, the shipped model's {a.size})")
            break
        worst = float(np.max(np.abs(a - b) / std))
        if worst > rtol:
            what = "means" if name == "stats_mean" else "standard deviations"
            differences.append(f"the per-channel {what} (by {worst:.2g} of a channel's std; tolerance {rtol:g})")
    return differences


@dataclass(frozen=True)
class ShippedModel:
    """One shipped file: its path, its metadata and the fingerprint of its training data."""

    path: Path
    metadata: dict[str, Any]

    @property
    def fingerprint(self) -> dict[str, Any]:
        return self.metadata["data"]

    def differences(self, dataset: Dataset) -> list[str]:
        """What differs between the data this model was trained on and ``dataset`` (empty: it may be used)."""
        return fingerprint_differences(self.fingerprint, data_fingerprint(dataset))


def shipped_name(benchmark: str, model: str) -> str:
    """File name of a shipped model (the training checkpoint's name)."""
    return checkpoint_name(benchmark, model, SHIPPED_PRESET, SHIPPED_R, SHIPPED_T, data_preset=SHIPPED_DATA_PRESET)


def find_shipped(benchmark: str, model: str, preset: str = SHIPPED_PRESET, r: int = SHIPPED_R, T: int = SHIPPED_T,
                 *, weights_dir: Path | None = None) -> ShippedModel | None:
    """The shipped model of this (benchmark, kind, preset, r, T), or None when none ships."""
    if model != "pdmd" and (preset, T) != (SHIPPED_PRESET, SHIPPED_T):
        return None
    if r != SHIPPED_R:
        return None
    path = (WEIGHTS_DIR if weights_dir is None else weights_dir) / shipped_name(benchmark, model)
    if not path.exists():
        return None
    from .checkpoint import read_metadata

    return ShippedModel(path, read_metadata(path))


def list_shipped(weights_dir: Path | None = None) -> list[ShippedModel]:
    """Every shipped model, sorted by file name."""
    from .checkpoint import read_metadata

    folder = WEIGHTS_DIR if weights_dir is None else weights_dir
    return [ShippedModel(p, read_metadata(p)) for p in sorted(folder.glob("*.safetensors"))]


def export_model(checkpoint: Path | str, dataset: Dataset, out_dir: Path | str | None = None) -> Path:
    """Write the inference-only file of a trained ``checkpoint`` into ``out_dir`` (default: the package's
    weights folder), with the fingerprint of ``dataset``, which must be the data it was trained on."""
    from safetensors.torch import save_file

    from .checkpoint import _CALIBRATION, _METADATA_KEY, _MODEL, check_metadata

    ckpt = read_checkpoint(checkpoint, optimizer=False, training=False)
    meta = ckpt.metadata
    check_metadata(meta, ckpt.path, dataset=dataset)  # the fingerprint must describe the data it was trained on
    if not meta.get("complete"):
        raise ValueError(f"{ckpt.path} is not finished training ({meta.get('steps_done')} of {meta.get('steps')} "
                         "steps): finish it with `dks-gym train` before exporting it")
    if "Q_scale" not in ckpt.calibration:
        raise ValueError(f"{ckpt.path} has no tuned process-noise scale: run `dks-gym calibrate "
                         f"{meta['benchmark']} --model {meta['model']}` before exporting it")
    shipped_meta = {k: v for k, v in meta.items() if k not in _DROPPED}
    shipped_meta["dataset"] = dict(meta.get("dataset", {}), path=Path(meta.get("dataset", {}).get("path", "")).name)
    shipped_meta["data"] = data_fingerprint(dataset)
    shipped_meta["exported_from"] = ckpt.path.name
    shipped_meta["q_scale"] = float(ckpt.calibration["Q_scale"])
    tensors = {_MODEL + k: v.contiguous() for k, v in ckpt.model_state.items()}
    tensors.update({_CALIBRATION + k: v.contiguous() for k, v in ckpt.calibration.items()})
    out = Path(WEIGHTS_DIR if out_dir is None else out_dir)
    out.mkdir(parents=True, exist_ok=True)
    target = out / ckpt.path.name
    with atomic_path(target) as tmp:
        save_file(tensors, str(tmp), metadata={_METADATA_KEY: json.dumps(shipped_meta, sort_keys=True)})
        os.chmod(tmp, 0o644)
    size, limit = target.stat().st_size, max_file_bytes(meta["model"])
    if size > limit:
        target.unlink()
        raise ValueError(f"{target.name} would be {size / 2**20:.1f} MiB, over the {limit / 2**20:.0f} MiB "
                         "a shipped model may take")
    return target


def max_file_bytes(model: str) -> int:
    """The size limit of one shipped file of this model kind."""
    return MAX_PDMD_FILE_BYTES if model == "pdmd" else MAX_FILE_BYTES


def is_shipped(path: Path | str | None) -> bool:
    """Whether ``path`` is a file of the package's weights folder (never written by tuning or training)."""
    return path is not None and Path(path).resolve().parent == WEIGHTS_DIR


__all__ = [
    "SHIPPED_BENCHMARKS",
    "STATS_RTOL",
    "WEIGHTS_DIR",
    "ShippedModel",
    "data_fingerprint",
    "export_model",
    "find_shipped",
    "fingerprint_differences",
    "is_shipped",
    "max_file_bytes",
    "list_shipped",
    "shipped_name",
]
