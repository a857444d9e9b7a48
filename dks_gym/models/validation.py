"""Validation along a training run: the held-out trajectories, the validation loss, best weights, early stopping.

The ``lite`` schedules hold out a fraction of the training trajectories (:func:`validation_trajectories`, by
trajectory, seeded); :class:`ValidationMonitor` measures the loss of Eq. 10/11 on their windows every
``eval_every`` steps, keeps the best-on-validation weights and says when the run stops early.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from ..dataset import Dataset
from .latent_model import NeuralLatentModel
from .loss import training_loss
from .windows import WindowSampler


def validation_trajectories(n_train: int, fraction: float, seed: int) -> list[int]:
    """The training trajectories held out for validation: ``round(fraction * n_train)`` of them (at least one
    when ``fraction`` > 0, and never all), drawn with ``seed``, sorted."""
    if fraction <= 0:
        return []
    n_val = min(n_train - 1, max(1, round(fraction * n_train)))
    if n_val < 1:
        raise ValueError(f"a validation split needs at least two training trajectories, got {n_train}")
    return sorted(np.random.default_rng(seed).permutation(n_train)[:n_val].tolist())


class ValidationMonitor:
    """The loss (Eq. 10/11 terms) on held-out trajectories every ``eval_every`` steps; keeps the best weights
    and says when to stop early (``patience`` validations without a 1 % improvement).

    The windows are fixed: every (trajectory, start) pair of the validation trajectories, or ``max_windows``
    of them drawn with ``seed``. Its state (``history``, the best weights) is saved with the checkpoint and
    replayed on resume, so a resumed run stops where an uninterrupted one would.
    """

    def __init__(self, dataset: Dataset, trajectories: Sequence[int], horizon: int, *, eval_every: int, patience: int,
                 batch_size: int, max_windows: int = 256, seed: int = 0) -> None:
        self.sampler = WindowSampler(dataset, horizon, seed=seed, trajectories=trajectories)
        self.trajectories = [int(i) for i in trajectories]
        n = self.sampler.n_windows
        index = torch.arange(n) if n <= max_windows else torch.randperm(
            n, generator=torch.Generator().manual_seed(seed))[:max_windows].sort().values
        span = self.sampler.n_t - horizon
        self._windows = (self.sampler.trajectories[index // span], index % span)
        self.eval_every, self.patience, self.batch_size = int(eval_every), int(patience), int(batch_size)
        self.history: list[torch.Tensor] = []  # (5,) per validation: step, total, reconstruction, prediction, latent
        self.best_state: dict[str, torch.Tensor] | None = None
        self.best_step, self.best_loss = 0, math.inf
        self._reference, self._since = math.inf, 0

    @property
    def stopped(self) -> bool:
        """Whether the patience has run out."""
        return bool(self.patience) and self._since >= self.patience

    def due(self, step: int) -> bool:
        """Whether a validation follows optimizer step ``step`` (1-based: steps done)."""
        return self.eval_every > 0 and step % self.eval_every == 0

    @torch.no_grad()
    def loss(self, model: NeuralLatentModel) -> torch.Tensor:
        """Mean (4,) loss terms over the validation windows, in eval mode."""
        was_training = model.training
        model.eval()
        device = model.stats_mean.device
        total, count = torch.zeros(4, dtype=torch.float64), 0
        traj, start = self._windows
        for lo in range(0, len(traj), self.batch_size):
            x, mu = self.sampler.windows(traj[lo: lo + self.batch_size], start[lo: lo + self.batch_size])
            _, terms = training_loss(model, x.to(device), mu.to(device))
            total += terms.double().cpu() * x.shape[0]
            count += x.shape[0]
        model.train(was_training)
        return (total / count).float()

    def evaluate(self, model: NeuralLatentModel, step: int) -> None:
        """Record the validation loss at ``step``; keep the weights if they are the best so far."""
        terms = self.loss(model)
        self._record(step, terms)
        if step == self.best_step:
            self.best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}

    def _record(self, step: int, terms: torch.Tensor) -> None:
        self.history.append(torch.cat([torch.tensor([float(step)]), terms.float()]))
        value = float(terms[0])
        if value < self.best_loss:
            self.best_loss, self.best_step = value, step
        if value < 0.99 * self._reference:
            self._reference, self._since = value, 0
        else:
            self._since += 1

    def restore(self, history: torch.Tensor, best_state: dict[str, torch.Tensor]) -> None:
        """Replay a saved history (m, 5) and take the saved best weights."""
        for row in history.float():
            self._record(int(row[0]), row[1:])
        self.best_state = {k: v.clone() for k, v in best_state.items()}

    def stacked(self) -> torch.Tensor:
        """The history as an (m, 5) tensor (an empty (0, 5) one before the first validation)."""
        return torch.stack(self.history) if self.history else torch.zeros(0, 5)


__all__ = ["ValidationMonitor", "validation_trajectories"]
