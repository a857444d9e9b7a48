"""What the EKF and the EnKF classes share: noise specs, measurement checks, the divergence policy, records."""

from __future__ import annotations

import torch
from torch import Tensor

from .batch_elements import element_list
from .covariance import CovarianceSpec, as_covariance, check_covariance_spec, check_symmetric, floating_like, symmetrize
from .diagnostics import Diagnostics, StepTimer
from .divergence import DivergencePolicy, raise_if_diverged
from .dynamics import LatentDynamics
from .measurements import check_mask, check_measurement


class SequentialFilter:
    """What the :class:`~dks_gym.filters.EKF` and :class:`~dks_gym.filters.EnKF` classes share.

    Holds the dynamics and noise specs, validates measurements (fixed dimension ``m`` between resets),
    applies the divergence policy, and records :class:`Diagnostics`.
    """

    def __init__(
        self,
        dynamics: LatentDynamics,
        *,
        R: CovarianceSpec | None,
        sigma: float | Tensor | None,
        Q: CovarianceSpec,
        on_divergence: DivergencePolicy,
        record_diagnostics: bool,
    ) -> None:
        if not isinstance(dynamics, LatentDynamics):
            raise TypeError(f"dynamics must be a LatentDynamics, got {type(dynamics).__name__}")
        if (R is None) == (sigma is None):
            raise ValueError(
                "give exactly one of R (measurement-noise covariance) or sigma (its standard deviation, R = sigma^2 I)"
            )
        if sigma is not None:
            if torch.as_tensor(sigma).ndim > 1:
                raise ValueError(
                    f"sigma must be a scalar or (B,), got shape {tuple(torch.as_tensor(sigma).shape)}; "
                    "pass a full covariance as R"
                )
            check_covariance_spec(sigma, "sigma", definite=True)
        else:
            check_covariance_spec(R, "R", definite=True)
        check_covariance_spec(Q, "Q", definite=False)
        if on_divergence not in ("raise", "reset"):
            raise ValueError(f"on_divergence must be 'raise' or 'reset', got {on_divergence!r}")
        self.dynamics = dynamics
        self.R = R
        self.sigma = sigma
        self.Q = Q
        self.on_divergence = on_divergence
        self.record_diagnostics = record_diagnostics
        self.diagnostics = Diagnostics()
        self.n_steps = 0
        self._m: int | None = None
        self._batch: int | None = None

    def _require_reset(self) -> None:
        if self._batch is None:
            raise RuntimeError(f"{type(self).__name__}.reset(z0, P0) must be called before step()")

    def _start(self, z0: Tensor) -> tuple[int, int]:
        z0 = torch.as_tensor(z0)
        if z0.ndim != 2:
            raise ValueError(
                f"z0 must be (B, r), got shape {tuple(z0.shape)}; "
                "add a leading batch dimension (z0[None]) for one system"
            )
        if not z0.is_floating_point():
            raise ValueError(f"z0 must be a float32/float64 tensor, got {z0.dtype}")
        if not torch.isfinite(z0).all():
            raise ValueError(f"z0 contains NaN or inf in batch elements {element_list(~torch.isfinite(z0).all(1))}")
        self._batch, r = z0.shape
        self._m = None
        self._Q_key = self._R_key = None
        self.n_steps = 0
        self.diagnostics = Diagnostics()
        return self._batch, r

    def _initial_covariance(self, P0: CovarianceSpec | None, z0: Tensor) -> Tensor:
        batch, r = z0.shape
        P = as_covariance(1.0 if P0 is None else P0, batch, r, like=z0, name="P0")
        check_symmetric(P, "P0", definite=True)
        return symmetrize(P).clone()

    def _process_noise(self, like: Tensor) -> Tensor:
        """``Q`` as ``(B, r, r)`` on the state's dtype/device (built in that dtype, so float64 stays exact)."""
        key = (like.dtype, like.device)
        if getattr(self, "_Q_key", None) != key:
            self._Q_cache = as_covariance(self.Q, self._batch, like.shape[-1], like=like, name="Q")
            self._Q_key = key
        return self._Q_cache

    def _measurement_noise(self, like: Tensor, m: int) -> Tensor:
        """``R`` on the state's dtype/device: its variance (a scalar or ``(B,)``) when ``R`` is a multiple of I
        (built from ``sigma``, or a scalar or ``(B,)`` R), which the EKF update uses to scale the gain's columns
        instead of multiplying by R; ``(B, m, m)`` otherwise."""
        key = (like.dtype, like.device, m)
        if getattr(self, "_R_key", None) != key:
            if self.sigma is not None:
                name, variance = "sigma", floating_like(self.sigma, like) ** 2
            else:
                name, variance = "R", floating_like(self.R, like)
            R = as_covariance(variance, self._batch, m, like=like, name=name)  # checks the shape, once
            self._R_cache, self._R_key = (variance if variance.ndim <= 1 else R), key
        return self._R_cache

    def _measurement(self, y: Tensor | None, like: Tensor, mask: Tensor | None = None) -> tuple[Tensor, Tensor | None]:
        """The checked measurement and mask (None: every reading present)."""
        if y is None:
            raise ValueError(
                "step(y, assimilate=True) needs a measurement y of shape (B, m); "
                "use step(assimilate=False) for a forward run"
            )
        if mask is not None:
            mask = torch.as_tensor(mask, device=like.device)
        y = check_measurement(y, self._batch, self._m, like, mask)
        return y, check_mask(mask, y)

    def _resolve_divergence(self, bad: Tensor, what: str) -> None:
        """Raise :class:`FilterDivergence` for the flagged elements unless the policy is ``'reset'``."""
        if self.on_divergence == "raise":
            raise_if_diverged(bad, f"{type(self).__name__} step {self.n_steps + 1} ({what})")

    def _record(
        self,
        timer: StepTimer,
        *,
        forecast_norm: Tensor,
        gain_norm: Tensor,
        spread: Tensor,
        reset: Tensor,
        assimilated: bool,
    ) -> None:
        if self.record_diagnostics:
            d = self.diagnostics
            d.forecast_norm.append(forecast_norm.detach())
            d.gain_norm.append(gain_norm.detach())
            d.spread.append(spread.detach())
            d.reset.append(reset.detach())
            d.wall_time.append(timer.seconds)
            d.assimilated.append(assimilated)
