"""SHRED (:mod:`dks_gym.models.shred`) as an :class:`~dks_gym.evaluation.estimators.Estimator`: the leaderboard's
SHRED row is scored by the same harness as a user's method, on the protocol's paper layout.

``fit`` trains SHRED on the training split with the test episodes' sensors, noise level and faults (its own
noisy training readings, :class:`~dks_gym.models.shred.ShredConfig` ``noise_seeds`` realizations); ``estimate``
at frame k is :meth:`~dks_gym.models.shred.Shred.reconstruct_frame` of the readings of frames 1..k, which is
what SHRED's whole-episode reconstruction gives at frame k.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..models.shred import Shred, ShredConfig
from .estimators import TrainingData


class ShredEstimator:
    """SHRED trained on the training split by :meth:`fit`, then estimating each frame from its reading history."""

    def __init__(self, config: ShredConfig = ShredConfig(), progress: bool = False) -> None:
        self.config, self.progress = config, progress
        self.shred: Shred | None = None

    def fit(self, train: TrainingData) -> None:
        """Train SHRED (:meth:`~dks_gym.models.shred.Shred.fit`) on ``train``'s split, sensors, noise and faults."""
        self.shred = Shred(train.dataset, train.sensors, noise_level=train.noise_level, faults=train.faults,
                           config=self.config).fit(progress=self.progress)

    @property
    def rank(self) -> int:
        """The number of POD coefficients SHRED outputs (its config's rank, capped by the data)."""
        if self.shred is None or self.shred.network is None:
            raise RuntimeError("call fit() first")
        return int(self.shred.network.decoder[-1].out_features)

    def estimate(self, readings: np.ndarray, sensors: np.ndarray, mu: float) -> np.ndarray:
        """The field at the frame of the last reading, from the readings of frames 1..k ``(k, m)``."""
        if self.shred is None:
            raise RuntimeError("call fit() before estimate()")
        if not np.array_equal(sensors, self.shred.layout):
            raise ValueError("SHRED reads the layout it was trained on; these readings come from other sensors")
        return self.shred.reconstruct_frame(readings, mu)

    def describe(self) -> dict[str, Any]:
        """SHRED's settings and training outcome (:meth:`~dks_gym.models.shred.Shred.describe`)."""
        return {} if self.shred is None else self.shred.describe()


__all__ = ["ShredEstimator"]
