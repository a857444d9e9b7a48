"""The scale of the calibrated process noise: tuned once per model, at the end of training or on request.

The calibrated ``Q`` (:func:`dks_gym.models.calibration.calibrate`) is the covariance of a model's latent one-step
residuals. A filter that assumes it is too sure of itself when the model's errors are correlated in time
(a systematic drift, not white noise): its latent covariance grows slower than its error, and the decoded
``estimate_std`` is too small. On the Burgers lite models (docs/filters.md) the mean NEES per cell over the
held-out trajectories was 1.05 for the Koopman model, 6.3 for the MLP and 4.7 for the xLSTM.

:func:`tune_process_noise` runs the EKF with ``s * Q`` on the trajectories the model was calibrated on
(held out from its training; pDMD's are its training ones), at the env's default sensing (16 sensors of the
paper's layout, 20 % noise), and bisects ``log s`` until the fraction of scored cells inside the central
95 % interval, over every frame after the first, equals ``target``. :func:`calibrate_process_noise` stores
it as ``model.calibration["Q_scale"]`` and in the model's checkpoint; it multiplies ``Q`` wherever
``Q="calibrated"`` is resolved (:meth:`FilterConfig.process_noise`). Like every calibration it is measured at
one sensing setting; other layouts and noise levels get the same scale.

Who tunes: ``dks-gym train`` at the end of training, ``dks-gym calibrate BENCHMARK --model KIND``, and the
calls that were asked to train (``train_if_missing=True``, e.g. a wrapper's ``ModelSpec``). Building an env or a
wrapper otherwise never does: a model without a scale runs with the unscaled Q and warns once
(:func:`~dks_gym.assimilation.config.process_noise_scale`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from ..dataset import Dataset
from ..models import FilterableModel
from ..models.checkpoint import update_calibration
from ..models.shipped import is_shipped
from .config import AssimilationConfig
from .episodes import AssimilationResult, run_assimilation


#: The coverage the tuned filter should reach over the held-out frames.
TARGET_COVERAGE = 0.95
#: Bisection bracket of the scale (2^-4 .. 2^12) and its steps: a final bracket of 2^(16/2^6), a factor 1.19.
SCALE_RANGE = (2.0**-4, 2.0**12)
BISECTIONS = 6
#: At most this many of the calibration trajectories are filtered per evaluation (evenly spread): the tuning
#: costs 7 filter runs of this batch with the predictive std (about 1 min for Burgers, 6 min for the dambreak
#: on one core).
MAX_TRAJECTORIES = 5


def held_out_trajectories(model: FilterableModel) -> list[int] | None:
    """The training trajectories the tuning filters: the model's calibration ones (held out from its training),
    at most :data:`MAX_TRAJECTORIES` evenly spread; None when its calibration names none."""
    held_out = (getattr(model, "calibration", None) or {}).get("trajectories")
    if held_out is None:
        return None
    index = [int(i) for i in torch.as_tensor(held_out).reshape(-1)]
    if len(index) > MAX_TRAJECTORIES:
        index = [index[int(round(k))] for k in np.linspace(0, len(index) - 1, MAX_TRAJECTORIES)]
    return index


def held_out_run(model: FilterableModel, dataset: Dataset, scale: float, trajectories: list[int], *,
                 noise_level: float = 0.2, n_sensors: int = 16) -> AssimilationResult:
    """The tuning's EKF run: ``trajectories`` (train split) with ``scale`` times the calibrated Q and P0."""
    config = AssimilationConfig(noise_level=noise_level, n_sensors=n_sensors, split="train")
    config = config.replace(Q=scale * model.calibration["Q"], P0="calibrated")
    return run_assimilation(model, dataset, config, trajectories=trajectories)


def held_out_coverage(model: FilterableModel, dataset: Dataset, scale: float, trajectories: list[int], *,
                      noise_level: float = 0.2, n_sensors: int = 16) -> float:
    """The EKF's 95 % coverage over frames 1..n_t-1 of :func:`held_out_run`."""
    result = held_out_run(model, dataset, scale, trajectories, noise_level=noise_level, n_sensors=n_sensors)
    return float(np.mean(result.step_coverage[:, 1:]))


def tune_process_noise(model: FilterableModel, dataset: Dataset, *, target: float = TARGET_COVERAGE,
                       noise_level: float = 0.2, n_sensors: int = 16, progress: bool = False) -> dict[str, Any]:
    """The scale ``s`` of the calibrated ``Q`` whose EKF covers ``target`` of the truth on the held-out frames.

    Bisection on ``log s`` within :data:`SCALE_RANGE` (the coverage grows with ``s``); returns ``scale``,
    ``coverage`` (at that scale) and ``evaluations`` [(scale, coverage)]. Does not change ``model``.
    ``progress``: a bar over the (at most ``BISECTIONS + 1``) filter runs.
    """
    from tqdm.auto import tqdm

    if not 0.0 < target < 1.0:
        raise ValueError(f"target coverage must lie in (0, 1), got {target!r}")
    trajectories = held_out_trajectories(model)
    if not trajectories or "Q" not in model.calibration:
        raise ValueError("the model has no calibrated Q and held-out trajectories (model.calibration['Q'], "
                         "['trajectories']); calibrate it first (dks_gym.models.calibrate)")
    lo, hi = (math.log(s) for s in SCALE_RANGE)
    evaluations: list[tuple[float, float]] = []
    bar = tqdm(total=BISECTIONS + 1, desc=f"tuning Q for {model.kind}", unit="run", disable=not progress,
               leave=False, dynamic_ncols=True)

    def coverage(log_scale: float) -> float:
        value = held_out_coverage(model, dataset, math.exp(log_scale), trajectories, noise_level=noise_level,
                                  n_sensors=n_sensors)
        evaluations.append((math.exp(log_scale), value))
        bar.set_postfix_str(f"scale {math.exp(log_scale):.3g}: coverage {value:.3f}", refresh=False)
        bar.update(1)
        return value

    try:
        if coverage(lo) < target:  # else already honest (or overcautious) at the smallest scale
            for _ in range(BISECTIONS):
                mid = 0.5 * (lo + hi)
                if coverage(mid) < target:
                    lo = mid
                else:
                    hi = mid
    finally:
        bar.close()
    best = min(evaluations, key=lambda e: abs(e[1] - target))
    return {"scale": best[0], "coverage": best[1], "evaluations": evaluations}


def calibrate_process_noise(model: FilterableModel, dataset: Dataset, *, progress: bool = True,
                            write: bool = True) -> float:
    """Tune the scale of ``model``'s calibrated Q now (:func:`tune_process_noise`), set
    ``model.calibration["Q_scale"]`` and, with ``write``, store it in the model's checkpoint
    (``model.checkpoint_path``; never in a shipped file). Returns the scale.

    A model whose calibration names no held-out trajectories (trained by an older dks-gym) gets 1."""
    calibration = dict(getattr(model, "calibration", None) or {})
    if "Q" not in calibration:
        raise ValueError(f"this {getattr(model, 'kind', '')} model has no calibrated Q: retrain it with "
                         "`dks-gym train ... --restart`")
    if "trajectories" not in calibration:
        scale = 1.0
    else:
        scale = float(tune_process_noise(model, dataset, progress=progress)["scale"])
    model.calibration = {**calibration, "Q_scale": torch.tensor(scale, dtype=torch.float64)}
    path = getattr(model, "checkpoint_path", None)
    if write and path is not None and not is_shipped(path):
        update_calibration(path, model.calibration)
    return scale


def tune_if_missing(model: FilterableModel, dataset: Dataset, *, progress: bool = True) -> None:
    """:func:`calibrate_process_noise` for a model that has a calibrated Q but no tuned scale (a model just
    trained by a call that was asked to train); nothing for any other."""
    calibration = getattr(model, "calibration", None) or {}
    if "Q" in calibration and "Q_scale" not in calibration:
        calibrate_process_noise(model, dataset, progress=progress)


__all__ = ["BISECTIONS", "SCALE_RANGE", "TARGET_COVERAGE", "calibrate_process_noise", "held_out_coverage",
           "held_out_run", "held_out_trajectories", "tune_if_missing", "tune_process_noise"]
