"""Extended Kalman filter in the latent space (paper Eqs. 13-17, SPEC section 4).

One step is a forecast from the analysis state followed, when a measurement arrives, by an update:

- forecast (Eqs. 13-14): ``z_f = f(z_a)``, ``P_f = F P_a F^T + Q`` with ``F = df/dz`` at ``z_a``;
- gain (Eq. 15): ``K = P_f J^T S^{-1}``, ``S = J P_f J^T + R``, with ``J = dh/dz`` at ``z_f`` and ``S^{-1}``
  formed from the Cholesky factor of ``S`` (an ``S`` that is not positive definite gives a NaN gain, flagged);
- mean (Eq. 16): ``z_a = z_f + K (y - h(z_f))``;
- covariance (Eq. 17) in Joseph form ``(I - K J) P_f (I - K J)^T + K R K^T``, then symmetrized. It equals
  ``(I - K J) P_f`` in exact arithmetic and stays symmetric positive definite in floating point
  (the form filterpy's ``KalmanFilter``/``ExtendedKalmanFilter`` use).

A forward run (no assimilation) is the same loop with the update switched off, ``step(assimilate=False)``:
its mean is exactly the model rollout ``z_{k+1} = f(z_k)``.
"""

from __future__ import annotations

import copy

import torch
from torch import Tensor

from .batch_elements import nonfinite_elements
from .covariance import CovarianceSpec, as_covariance, cholesky_or_nan, symmetrize
from .diagnostics import StepTimer, spectral_norm
from .divergence import DivergencePolicy, raise_if_diverged
from .dynamics import GaussianState, LatentDynamics
from .jacobians import JacobianMethod, forecast_with_jacobian, observe_with_jacobian
from .measurements import check_mask, check_measurement, mask_measurement
from .sequential import SequentialFilter


def ekf_forecast(
    state: GaussianState,
    dynamics: LatentDynamics,
    Q: CovarianceSpec = 1e-4,
    *,
    jacobian_method: JacobianMethod = "auto",
    check: bool = True,
) -> tuple[GaussianState, Tensor]:
    """EKF forecast (Eqs. 13-14) from an analysis state; returns the forecast state and ``F`` ``(B, r, r)``.

    With ``check=False`` non-finite results are returned for the caller to handle instead of raising
    :class:`~dks_gym.filters.FilterDivergence`.
    """
    z_a, P_a = state.mean, state.cov
    batch, r = z_a.shape
    z_f, F = forecast_with_jacobian(dynamics, z_a, jacobian_method)  # Eq. 13, F at the analysis state
    P_f = symmetrize(torch.baddbmm(as_covariance(Q, batch, r, like=z_a, name="Q"), F @ P_a, F.mT))  # Eq. 14
    if check:
        raise_if_diverged(nonfinite_elements(z_f, P_f), "EKF forecast")
    return GaussianState(z_f, P_f), F


def kalman_gain(P_f: Tensor, J: Tensor, R_mat: Tensor) -> tuple[Tensor, Tensor]:
    """Eq. 15: ``K = P_f J^T S^{-1}`` ``(B, r, m)`` with ``S = J P_f J^T + R`` symmetrized, and a ``(B,)`` mask of
    the elements whose ``S`` is not positive definite (their ``K`` is NaN, never a silent fallback).

    ``S^{-1}`` is formed from the Cholesky factor (``cholesky_inverse``): torch makes one LAPACK call per element
    either way, and the gain takes 0.6x the time of one by a Cholesky solve for the ``r`` right-hand sides at
    ``m = 16``, ``r = 32``, the same numbers to float32 round-off on the shipped models' episodes
    (docs/performance.md).
    """
    PJt = P_f @ J.mT
    L, singular = cholesky_or_nan(symmetrize(torch.baddbmm(R_mat, J, PJt)))
    return PJt @ torch.cholesky_inverse(L), singular


def joseph_covariance(P_f: Tensor, K: Tensor, J: Tensor, R_mat: Tensor, *, diagonal_R: bool = False) -> Tensor:
    """Eq. 17 in Joseph form, ``(I - K J) P_f (I - K J)^T + K R K^T``, symmetrized ``(B, r, r)``.

    ``diagonal_R``: ``R_mat`` is diagonal (a scalar or per-element variance, masked or not), so ``K R`` is
    ``K``'s columns scaled, the same numbers as the product.
    """
    eye = torch.eye(K.shape[1], dtype=K.dtype, device=K.device)
    I_KJ = torch.baddbmm(eye, K, J, alpha=-1.0)
    KR = K * R_mat.diagonal(dim1=-2, dim2=-1)[:, None, :] if diagonal_R else K @ R_mat
    return symmetrize((KR @ K.mT).baddbmm_(I_KJ @ P_f, I_KJ.mT))


def ekf_update(
    state: GaussianState,
    y: Tensor,
    dynamics: LatentDynamics,
    R: CovarianceSpec,
    *,
    mask: Tensor | None = None,
    jacobian_method: JacobianMethod = "auto",
    check: bool = True,
) -> tuple[GaussianState, Tensor]:
    """EKF update (Eqs. 15-17, Joseph form) of a forecast state with measurements ``y`` ``(B, m)``.

    Returns the analysis state and the gain ``K`` ``(B, r, m)``. ``R`` is the measurement-noise covariance
    (scalar, ``(B,)``, ``(m, m)`` or ``(B, m, m)``). ``mask`` ``(B, m)`` bool: the readings present; the
    update uses those rows of ``J`` and ``R`` only (the missing readings' gain columns are 0, their values are
    ignored). Raises ValueError for a malformed ``y`` or a non-finite reading that the mask calls present.
    """
    z_f, P_f = state.mean, state.cov
    batch = z_f.shape[0]
    h, J = observe_with_jacobian(dynamics, z_f, jacobian_method)
    m = h.shape[1]
    y = check_measurement(y, batch, m, like=z_f, mask=mask)
    mask = check_mask(mask, y)
    y, R_mat = mask_measurement(y, mask, as_covariance(R, batch, m, like=z_f, name="R"))
    if mask is not None:  # the missing rows observe nothing: zero rows of J, zero innovation
        J = J * mask.to(J.dtype)[..., None]
        h = torch.where(mask, h, y)

    K, singular = kalman_gain(P_f, J, R_mat)
    z_a = torch.baddbmm(z_f[..., None], K, (y - h)[..., None])[..., 0]  # Eq. 16
    diagonal_R = isinstance(R, (int, float)) or (isinstance(R, Tensor) and R.ndim <= 1)  # scalar or (B,)
    P_a = joseph_covariance(P_f, K, J, R_mat, diagonal_R=diagonal_R)
    if check:
        raise_if_diverged(nonfinite_elements(z_a, P_a) | singular, "EKF update")
    return GaussianState(z_a, P_a), K


class EKF(SequentialFilter):
    """Stateful batched EKF: ``reset(z0, P0)``, then ``step(y)`` per measurement (``assimilate=False``: forecast only).

    Parameters: ``dynamics`` (a :class:`LatentDynamics`); exactly one of ``R`` (measurement-noise
    covariance) or ``sigma`` (its standard deviation, scalar or ``(B,)``: ``R = sigma^2 I``); ``Q``
    process-noise covariance (default ``1e-4 I``); ``on_divergence``: ``"raise"`` (default) raises
    :class:`FilterDivergence` when an element's mean or covariance becomes non-finite, ``"reset"``
    restarts those elements from ``(z0, P0)`` and flags them in :attr:`diagnostics`;
    ``jacobian_method``: see :func:`~dks_gym.filters.jacobians.value_and_jacobian`.
    """

    def __init__(
        self,
        dynamics: LatentDynamics,
        *,
        R: CovarianceSpec | None = None,
        sigma: float | Tensor | None = None,
        Q: CovarianceSpec = 1e-4,
        on_divergence: DivergencePolicy = "raise",
        jacobian_method: JacobianMethod = "auto",
        record_diagnostics: bool = True,
    ) -> None:
        super().__init__(
            dynamics, R=R, sigma=sigma, Q=Q, on_divergence=on_divergence, record_diagnostics=record_diagnostics
        )
        if jacobian_method not in ("auto", "vmap", "loop"):
            raise ValueError(f"jacobian_method must be 'auto', 'vmap' or 'loop', got {jacobian_method!r}")
        self.jacobian_method = jacobian_method
        self.state: GaussianState | None = None
        self._constant_forecast_norm: Tensor | None = None

    def reset(self, z0: Tensor, P0: CovarianceSpec | None = None) -> None:
        """Start from mean ``z0`` ``(B, r)`` and covariance ``P0``.

        ``P0``: default ``I``; a scalar, ``(B,)``, ``(r, r)`` or ``(B, r, r)``; must be symmetric positive definite.
        """
        self._start(z0)
        z0 = torch.as_tensor(z0).detach().clone()
        self._initial = GaussianState(z0, self._initial_covariance(P0, z0))
        self.state = GaussianState(z0.clone(), self._initial.cov.clone())
        self._constant_forecast_norm: Tensor | None = None

    def _forecast_norm(self, F: Tensor) -> Tensor:
        """``||F||_2`` per element; computed once per episode when the dynamics give F as a constant (Koopman K)."""
        if not isinstance(self.dynamics.forecast_jacobian, Tensor):
            return spectral_norm(torch.nan_to_num(F, nan=0.0, posinf=0.0, neginf=0.0))
        if self._constant_forecast_norm is None:
            self._constant_forecast_norm = spectral_norm(torch.nan_to_num(F, nan=0.0, posinf=0.0, neginf=0.0))
        return self._constant_forecast_norm

    @property
    def mean(self) -> Tensor:
        """Current latent mean ``(B, r)``: the analysis after an assimilating step, the forecast otherwise."""
        self._require_reset()
        return self.state.mean

    @property
    def cov(self) -> Tensor:
        """Current covariance ``(B, r, r)``."""
        self._require_reset()
        return self.state.cov

    def lead(self, steps: int) -> "EKF":
        """A copy forecast ``steps`` steps ahead with no measurement (Eqs. 13-14 repeated); this filter is unchanged.

        For readings that arrive late: the analysis stays at the readings' time and the estimate now is its
        forecast. The copy is for reading (``mean``, ``cov``); it records no diagnostics.
        """
        self._require_reset()
        ahead = copy.copy(self)
        ahead.record_diagnostics = False
        state = self.state
        for _ in range(int(steps)):
            state, _ = ekf_forecast(state, self.dynamics, self._process_noise(state.mean),
                                    jacobian_method=self.jacobian_method, check=False)
        ahead.state = state
        return ahead

    def step(self, y: Tensor | None = None, assimilate: bool = True, mask: Tensor | None = None) -> Tensor:
        """Forecast one step and, if ``assimilate``, update with ``y`` ``(B, m)``; return the new mean ``(B, r)``.

        ``mask`` ``(B, m)`` bool: the readings present (default all); a step with none present is a forecast.
        """
        self._require_reset()
        state = self.state
        with StepTimer(state.mean.device) as timer:
            y_checked, mask = self._measurement(y, state.mean, mask) if assimilate else (None, None)
            new, F = ekf_forecast(
                state, self.dynamics, self._process_noise(state.mean), jacobian_method=self.jacobian_method, check=False
            )
            gain_norm = torch.zeros(self._batch, dtype=state.mean.dtype, device=state.mean.device)
            if assimilate and (mask is None or bool(mask.any())):
                R = self._measurement_noise(state.mean, y_checked.shape[1])
                new, K = ekf_update(new, y_checked, self.dynamics, R, mask=mask, jacobian_method=self.jacobian_method,
                                    check=False)
                self._m = y_checked.shape[1]
                if self.record_diagnostics:
                    gain_norm = spectral_norm(torch.nan_to_num(K, nan=0.0, posinf=0.0, neginf=0.0))
            # A non-finite forecast propagates into the update, so one check after the step covers both.
            restart = nonfinite_elements(new.mean, new.cov)
            if bool(restart.any()):
                self._resolve_divergence(restart, "update" if assimilate else "forecast")
                new = GaussianState(
                    torch.where(restart[:, None], self._initial.mean, new.mean),
                    torch.where(restart[:, None, None], self._initial.cov, new.cov),
                )
            self.state = new
            self.n_steps += 1
        if self.record_diagnostics:
            self._record(
                timer,
                forecast_norm=self._forecast_norm(F),
                gain_norm=gain_norm,
                spread=(new.cov.diagonal(dim1=-2, dim2=-1).mean(-1)).sqrt(),
                reset=restart,
                assimilated=assimilate,
            )
        return new.mean
