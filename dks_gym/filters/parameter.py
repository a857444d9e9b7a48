"""The physical parameter estimated with the state: dynamics over the augmented state ``[z; s]``.

When mu (nu, Re, nu_w) is unknown, the filter carries one more state component ``s``, a coordinate of mu
(:class:`ParameterCoordinate`: ``s = log mu`` where the training range spans a decade or more, as nu in
[0.01, 1] does, so that a step in ``s`` is a relative change of mu and mu stays positive; ``s = mu``
otherwise). ``z`` follows the model with ``mu = mu(s)``, ``s`` persists (a random walk when it drifts: its
step variance is the parameter block of Q), and the sensors read ``h(z, mu(s))``::

    z_{k+1} = f(z_k, mu(s_k)),    s_{k+1} = s_k (+ w_k),    y_k = S decode(z_k, mu(s_k)) + v_k

The EKF's Jacobians of the augmented maps, ``[[df/dz, df/ds], [0, 1]]`` and ``[dh/dz, dh/ds]``, come from
autodiff through the model (Koopman through ``matrix_exp`` of A(mu), the MLP and xLSTM through the
embedding e(mu), pDMD through its RBF interpolant in mu); the EnKF's members each carry their own ``s``.
:func:`augment_with_parameter` builds the dynamics and :func:`~dks_gym.filters.augmented_covariance` the
block-diagonal Q and P0, as for the sensor biases (:mod:`dks_gym.filters.bias`), which stack on top.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from .dynamics import LatentDynamics

ParamMap = Callable[[Tensor, Tensor], Tensor]
#: Where the training range spans at least this ratio, the filter estimates log mu instead of mu.
LOG_RATIO = 10.0


@dataclass(frozen=True)
class ParameterCoordinate:
    """How the filter represents mu over the training range ``[low, high]``: ``s = log mu`` (``log=True``) or
    ``s = mu``. Built by :meth:`for_range`, which chooses log where ``high / low >= LOG_RATIO``."""

    low: float
    high: float
    log: bool

    @classmethod
    def for_range(cls, low: float, high: float) -> "ParameterCoordinate":
        """The coordinate for a training range (log where it spans a decade or more and is positive)."""
        low, high = float(low), float(high)
        if not (math.isfinite(low) and math.isfinite(high) and low < high):
            raise ValueError(f"the parameter's training range must be finite with low < high, got [{low}, {high}]")
        return cls(low, high, bool(low > 0 and high / low >= LOG_RATIO))

    def to_param(self, s: Tensor) -> Tensor:
        """mu of the coordinate ``s``."""
        return s.exp() if self.log else s

    def from_param(self, mu: float) -> float:
        """The coordinate of ``mu``."""
        return math.log(mu) if self.log else float(mu)

    def prior(self, mean: float | None = None, std: float | None = None) -> tuple[float, float]:
        """The Gaussian prior of ``s`` (mean, std): by default the mean and standard deviation of a uniform over
        the training range in this coordinate; from a prior ``(mean, std)`` of mu in physical units, the
        log-normal with those moments (log coordinate) or the same numbers (linear)."""
        if mean is None:
            a, b = (math.log(self.low), math.log(self.high)) if self.log else (self.low, self.high)
            return 0.5 * (a + b), (b - a) / math.sqrt(12.0)
        if not self.log:
            return float(mean), float(std)
        var = math.log1p((std / mean) ** 2)  # log-normal moment matching: E[mu] = mean, Var[mu] = std^2
        return math.log(mean) - 0.5 * var, math.sqrt(var)

    def interval(self, s: Tensor, std: Tensor, z: float = 1.959963984540054) -> tuple[Tensor, Tensor]:
        """The central 95 % interval of mu (by default) from a Gaussian ``s`` with standard deviation ``std``."""
        return self.to_param(s - z * std), self.to_param(s + z * std)

    def outside(self, s: Tensor) -> Tensor:
        """True where ``mu(s)`` lies outside the training range (the model extrapolates there)."""
        mu = self.to_param(s)
        return (mu < self.low) | (mu > self.high)


def augment_with_parameter(forecast: ParamMap, observe: ParamMap, coordinate: ParameterCoordinate,
                           stacked_rows: bool = True) -> LatentDynamics:
    """The dynamics over ``[z; s]`` ``(N, r + 1)`` from the model's maps ``forecast(z, mu)`` and
    ``observe(z, mu)`` (row-wise, ``mu`` of shape ``(N,)``): ``z -> forecast(z, mu(s))``, ``s -> s``, read as
    ``observe(z, mu(s))``. No Jacobians are given: the filters differentiate the augmented maps."""

    def augmented_forecast(x: Tensor) -> Tensor:
        z, s = x[:, :-1], x[:, -1]
        return torch.cat([forecast(z, coordinate.to_param(s)), s[:, None]], dim=1)

    def augmented_observe(x: Tensor) -> Tensor:
        return observe(x[:, :-1], coordinate.to_param(x[:, -1]))

    return LatentDynamics(augmented_forecast, augmented_observe, stacked_rows=stacked_rows)


__all__ = ["LOG_RATIO", "ParameterCoordinate", "augment_with_parameter"]
