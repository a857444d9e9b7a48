"""Calibration of a trained model: the errors the filters must assume, measured after training.

:func:`calibrate` measures a model's own errors (the latent process noise Q, the initial-condition
covariances P0, the decoder's reconstruction variance per cell) on held-out trajectories; training stores
them with the weights (``model.calibration``), and :mod:`dks_gym.assimilation.tuning` later tunes the scale
of Q on the same trajectories.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from ..dataset import Dataset
from .latent_model import LatentModel


def evenly_spread(n: int, most: int) -> list[int]:
    """At most ``most`` of the indices 0..n-1, evenly spread (all of them when n <= most)."""
    return sorted({int(round(i)) for i in np.linspace(0, n - 1, min(n, most))})


def _definite(cov: torch.Tensor, floor: float = 1e-6) -> torch.Tensor:
    """``cov`` + ``floor`` * (its mean variance) * I: definite in float32 too, whatever its rank."""
    return cov + floor * float(cov.trace()) / cov.shape[0] * torch.eye(cov.shape[0], dtype=cov.dtype)


@torch.no_grad()
def calibrate(model: LatentModel, dataset: Dataset, trajectories: Sequence[int], split: str = "train",
              chunk: int = 16) -> dict[str, torch.Tensor]:
    """What the filters need to know about a model's own errors, measured on ``trajectories`` of ``split``.

    ``Q`` (r, r) float64: the second moment of the latent one-step residuals z_{k+1} - F(z_k, mu) with
    z_k = E(x_k, mu) over every frame pair, the process noise a filter should assume (its mean, if any, is
    part of the error the filter must cover). ``P0`` (r, r) float64: the error covariance of the approximate
    initial condition, the spread of the encoded first frames of every training trajectory around their
    mean, plus ``Q``; ``P0_exact`` that of the exact one, ``Q``. Both with a floor of 1e-6 times their mean
    variance, so that they stay definite in float32. ``reconstruction_variance`` (C, *grid) float32: the mean over
    frames of (decode(encode(x)) - x)^2 per cell in physical units, the error a decoded estimate carries even
    with an exact latent state. ``trajectories`` (int64): the trajectories measured on, where the filter's scale
    of ``Q`` is tuned later (:func:`dks_gym.assimilation.tune_process_noise`). Frames are encoded ``chunk`` at a time.
    """
    device = model.stats_mean.device
    params = dataset.params(split)
    r = model.r
    q = torch.zeros(r, r, dtype=torch.float64)
    squares: torch.Tensor | None = None
    pairs = frames = 0
    for i in trajectories:
        x = torch.as_tensor(dataset.read(split, int(i)))
        mu = torch.full((x.shape[0],), float(params[int(i)]), dtype=torch.float64, device=device)
        z = torch.cat([model.encode(x[k:k + chunk].to(device), mu[k:k + chunk]) for k in range(0, len(x), chunk)])
        residual = (z[1:] - model.forecast(z[:-1], mu[1:])).double().cpu()
        q += residual.T @ residual
        pairs += residual.shape[0]
        for k in range(0, len(x), chunk):
            err = (model.decode(z[k:k + chunk], mu[k:k + chunk]).cpu() - x[k:k + chunk]).double() ** 2
            squares = err.sum(0) if squares is None else squares + err.sum(0)
        frames += x.shape[0]
    if not pairs:
        raise ValueError("calibrate needs at least one trajectory of at least two frames")
    q = q / pairs
    # The approximate initial condition is the mean encoded first frame of the training trajectories: its
    # error covariance is their spread around that mean (plus one step of model error, which keeps it
    # definite when the trajectories differ in few directions).
    train_params = dataset.params("train")
    n_train = len(train_params)
    z0 = []
    for k in range(0, n_train, chunk):
        first = np.stack([dataset.read("train", i, 0) for i in range(k, min(k + chunk, n_train))])
        z0.append(model.encode(torch.as_tensor(first).to(device), torch.as_tensor(train_params[k:k + chunk],
                                                                                   device=device)).double().cpu())
    z0 = torch.cat(z0)
    spread = z0 - z0.mean(0)
    p0 = _definite(spread.T @ spread / n_train + q)
    return {"Q": q, "P0": p0, "P0_exact": _definite(q), "reconstruction_variance": (squares / frames).float(),
            "trajectories": torch.tensor([int(i) for i in trajectories], dtype=torch.int64)}


__all__ = ["calibrate", "evenly_spread"]
