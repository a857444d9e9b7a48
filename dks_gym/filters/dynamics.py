"""The model as the filters see it (paper Section II.E, SPEC section 4): batched callables, and the belief.

The filters never see a model, only callables over batched tensors (DAPPER style): a
:class:`LatentDynamics` bundles the forecast map ``f`` (Eq. 13), the observation map ``h``, and
optionally their Jacobians. Everything in :mod:`dks_gym.filters` carries a leading batch dimension ``B``
(many environments or trajectories at once) and follows the dtype and device of the state it is given.

Conventions that hold for every function in :mod:`dks_gym.filters`:

- a latent mean is ``(B, r)``, a covariance ``(B, r, r)``, an ensemble ``(B, n, r)``, a measurement
  ``(B, m)``;
- a noise covariance (``Q``, ``R``, ``P0``) may be given as a scalar variance, a ``(B,)`` tensor of
  per-element variances, a ``(d, d)`` matrix shared by the batch, or a ``(B, d, d)`` stack (a
  diagonal covariance is passed as ``torch.diag(v)``: a 1-D tensor always means one variance per
  batch element; see :mod:`~dks_gym.filters.covariance`);
- the callables act row by row: ``forecast(z)`` maps ``(N, r) -> (N, r)`` and ``observe(z)`` maps
  ``(N, r) -> (N, m)`` for ``N = k * B`` where each batch element owns ``k`` consecutive rows
  (``k = 1`` for the EKF, ``k = n`` members for the EnKF). :func:`bind_param` builds such a callable
  from a model function ``g(z, mu)`` and a per-element parameter ``mu`` of shape ``(B,)``. A callable
  that only accepts exactly ``B`` rows can set ``LatentDynamics(stacked_rows=False)``; the EnKF then
  calls it once per member.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from torch import Tensor

Map = Callable[[Tensor], Tensor]
JacobianSpec = Map | Tensor | None


@dataclass(frozen=True)
class LatentDynamics:
    """The model as the filters see it: forecast ``f`` and observation ``h`` over batched latent states.

    ``forecast(z)``: ``(N, r) -> (N, r)``, the one-step latent map with the physical parameter already
    bound (Eq. 13). ``observe(z)``: ``(N, r) -> (N, m)``, the decoded sensor values ``S(G(z))``.
    ``forecast_jacobian`` / ``observe_jacobian``: ``None`` (autodiff), a callable ``z -> (B, r, r)`` /
    ``(B, m, r)``, or a constant tensor (``(r, r)`` or ``(B, r, r)``, e.g. the Koopman matrix ``K(mu)``;
    ``(m, r)`` or ``(B, m, r)``, e.g. pDMD's ``S U_r``); a callable ``observe_jacobian`` may also return the
    pair ``(h(z), J)`` when it computes the values on the way (the neural models' sensor-local Jacobian), which
    spares the filter a decode. ``stacked_rows``: whether the callables accept ``k * B`` rows (see the module
    docstring).
    """

    forecast: Map
    observe: Map
    forecast_jacobian: JacobianSpec = None
    observe_jacobian: JacobianSpec = None
    stacked_rows: bool = True

    def __post_init__(self) -> None:
        for name in ("forecast", "observe"):
            if not callable(getattr(self, name)):
                raise TypeError(
                    f"LatentDynamics.{name} must be a callable over (B, r) tensors, "
                    f"got {type(getattr(self, name)).__name__}"
                )
        for name in ("forecast_jacobian", "observe_jacobian"):
            value = getattr(self, name)
            if value is not None and not callable(value) and not isinstance(value, Tensor):
                raise TypeError(
                    f"LatentDynamics.{name} must be None (autodiff), a callable or a tensor, got {type(value).__name__}"
                )


def bind_param(fn: Callable[[Tensor, Tensor], Tensor], mu: Tensor) -> Map:
    """Bind a per-element parameter ``mu`` ``(B, ...)`` to ``fn(z, mu)`` so that it accepts ``k * B`` stacked rows.

    Row ``j`` of the argument belongs to batch element ``j // k``; ``mu`` is repeated accordingly.
    """
    batch = mu.shape[0]

    def bound(z: Tensor) -> Tensor:
        if z.shape[0] % batch != 0:
            raise ValueError(f"got {z.shape[0]} rows, not a multiple of the batch size {batch} that mu was bound with")
        return fn(z, mu.repeat_interleave(z.shape[0] // batch, dim=0))

    return bound


@dataclass
class GaussianState:
    """A batch of Gaussian beliefs: ``mean`` ``(B, r)`` and ``cov`` ``(B, r, r)``."""

    mean: Tensor
    cov: Tensor

    def __post_init__(self) -> None:
        if self.mean.ndim != 2:
            raise ValueError(
                f"mean must be (B, r), got shape {tuple(self.mean.shape)}; "
                "add a leading batch dimension (z[None]) for one system"
            )
        batch, r = self.mean.shape
        if self.cov.shape != (batch, r, r):
            raise ValueError(f"cov must be (B, r, r) = {(batch, r, r)} to match the mean, got {tuple(self.cov.shape)}")
