"""Sensor bias estimated with the state: the dynamics over the augmented state ``[z; b]`` (DAPPER style).

A drifting sensor reads ``h(z) + b`` with ``b`` a random walk per sensor (:class:`~dks_gym.envs.SensorFaults`
``drift``). Augmenting the latent state with ``b`` lets the EKF or EnKF estimate it: ``z`` follows the model,
``b`` persists (its random-walk steps are the bias block of the process noise), and the sensors read
``h(z) + b``. :func:`augment_with_bias` builds those dynamics from the model's, :func:`augmented_covariance`
the block-diagonal ``Q`` or ``P0``; the filters need nothing else::

    dyn = augment_with_bias(dynamics, m)
    ekf = EKF(dyn, sigma=sigma, Q=augmented_covariance(Q, r, m, drift**2))
    ekf.reset(torch.cat([z0, torch.zeros(B, m)], 1), augmented_covariance(P0, r, m, bias_variance))
    z, b = ekf.mean[:, :r], ekf.mean[:, r:]
"""

from __future__ import annotations

import torch
from torch import Tensor

from .covariance import CovarianceSpec, as_covariance
from .dynamics import LatentDynamics


def _bias_block(x: Tensor, m: int) -> tuple[Tensor, Tensor]:
    return x[:, :-m], x[:, -m:]


def augment_with_bias(dynamics: LatentDynamics, m: int) -> LatentDynamics:
    """The dynamics over ``[z; b]`` ``(N, r + m)``: ``z -> f(z)``, ``b -> b``, read as ``h(z) + b``.

    The Jacobians the model supplies are extended by blocks (``[[F, 0], [0, I]]`` and ``[J, I]``), a
    constant one staying constant; where it supplies none, autodiff runs through the augmented maps.
    """
    if int(m) != m or m < 1:
        raise ValueError(f"m (the number of sensors whose bias is estimated) must be a positive integer, got {m!r}")

    def forecast(x: Tensor) -> Tensor:
        z, b = _bias_block(x, m)
        return torch.cat([dynamics.forecast(z), b], dim=1)

    def observe(x: Tensor) -> Tensor:
        z, b = _bias_block(x, m)
        return dynamics.observe(z) + b

    return LatentDynamics(forecast, observe, forecast_jacobian=_forecast_jacobian(dynamics.forecast_jacobian, m),
                          observe_jacobian=_observe_jacobian(dynamics, m), stacked_rows=dynamics.stacked_rows)


def _block_forecast(F: Tensor, m: int) -> Tensor:
    """``[[F, 0], [0, I_m]]`` for ``F`` ``(r, r)`` or ``(B, r, r)``."""
    r = F.shape[-1]
    out = torch.zeros(*F.shape[:-2], r + m, r + m, dtype=F.dtype, device=F.device)
    out[..., :r, :r] = F
    out[..., r:, r:] = torch.eye(m, dtype=F.dtype, device=F.device)
    return out


def _forecast_jacobian(spec, m: int):
    if spec is None:
        return None
    if isinstance(spec, Tensor):
        return _block_forecast(spec, m)
    return lambda x: _block_forecast(spec(_bias_block(x, m)[0]), m)


def _block_observe(J: Tensor, m: int) -> Tensor:
    """``[J, I_m]`` for ``J`` ``(m, r)`` or ``(B, m, r)``."""
    eye = torch.eye(m, dtype=J.dtype, device=J.device).expand(*J.shape[:-2], m, m)
    return torch.cat([J, eye], dim=-1)


def _observe_jacobian(dynamics: LatentDynamics, m: int):
    spec = dynamics.observe_jacobian
    if spec is None:
        return None
    if isinstance(spec, Tensor):
        return _block_observe(spec, m)

    def jacobian(x: Tensor):
        z, b = _bias_block(x, m)
        result = spec(z)
        if isinstance(result, tuple):  # (h(z), J): the readings come with it
            h, J = result
            return h + b, _block_observe(J, m)
        return _block_observe(result, m)

    return jacobian


def augmented_covariance(latent: CovarianceSpec, r: int, m: int, bias: CovarianceSpec) -> Tensor:
    """The block-diagonal ``(r + m, r + m)`` covariance of ``[z; b]`` from the latent one (a variance or an
    ``(r, r)`` matrix) and the bias one (a variance or an ``(m, m)`` matrix): a process noise ``Q`` (the bias
    block being the random walk's step variance, ``drift**2``) or an initial ``P0``."""
    like = torch.zeros((), dtype=torch.float64)
    for value, name in ((latent, "latent"), (bias, "bias")):
        if torch.as_tensor(value).ndim not in (0, 2):
            raise ValueError(f"the {name} covariance must be a variance or a square matrix, "
                             f"got shape {tuple(torch.as_tensor(value).shape)}")
    top = as_covariance(latent, 1, r, like=like, name="latent covariance")[0]
    bottom = as_covariance(bias, 1, m, like=like, name="bias covariance")[0]
    return torch.block_diag(top, bottom)
