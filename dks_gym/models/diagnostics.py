"""Diagnostics of a trained model: its one-step error against persistence and its reconstruction floor."""

from __future__ import annotations


import torch

from ..dataset import Dataset
from .latent_model import LatentModel
from .windows import WindowSampler


@torch.no_grad()
def one_step_error(
    model: LatentModel, dataset: Dataset, split: str = "train", *, max_pairs: int = 2048, batch_size: int = 128,
    seed: int = 0,
) -> dict[str, float]:
    """Mean squared one-step error of decode(forecast(encode(x_k))) against x_{k+1}, and of persistence.

    Physical units, over the dataset's scored channels and all grid cells, averaged over (trajectory, k)
    pairs of ``split``: all of them, or ``max_pairs`` drawn with ``seed`` if there are more. The
    persistence ("no change") error is that of predicting x_{k+1} = x_k on the same pairs;
    ``reconstruction_mse`` is that of decode(encode(x_k)) against x_k, the floor under the model's
    decoded error (an encoder-decoder cannot predict better than it reconstructs).
    """
    sampler = WindowSampler(dataset, 1, seed=seed, split=split, in_memory=False)
    n_pairs = sampler.n_windows
    if n_pairs <= max_pairs:
        index = torch.arange(n_pairs)
    else:
        index = torch.randperm(n_pairs, generator=torch.Generator().manual_seed(seed))[:max_pairs].sort().values
    traj, start = sampler.trajectories[index // (sampler.n_t - 1)], index % (sampler.n_t - 1)
    scored = [dataset.channels.index(c) for c in dataset.scored_channels]
    device = model.stats_mean.device
    sums = torch.zeros(3, dtype=torch.float64)

    def total(a: torch.Tensor, b: torch.Tensor) -> float:
        return float(((a - b) ** 2).double().mean(dim=tuple(range(1, a.ndim))).sum())

    for lo in range(0, len(index), batch_size):
        x, mu = sampler.windows(traj[lo: lo + batch_size], start[lo: lo + batch_size])
        x, mu = x.to(device), mu.to(device)
        z = model.encode(x[:, 0], mu)
        pred = model.decode(model.forecast(z, mu), mu)
        target = x[:, 1, scored]
        sums[0] += total(pred[:, scored], target)
        sums[1] += total(x[:, 0, scored], target)
        sums[2] += total(model.decode(z, mu)[:, scored], x[:, 0, scored])
    n = len(index)
    return {"model_mse": float(sums[0]) / n, "persistence_mse": float(sums[1]) / n,
            "reconstruction_mse": float(sums[2]) / n, "pairs": n}


__all__ = ["one_step_error"]
