"""Stochastic ensemble Kalman filter with perturbed observations in the latent space (paper Section IV.D, SPEC 4).

The ensemble ``E`` ``(B, n, r)`` (``n = 20`` members by default, drawn from ``N(z0, P0)``) is advanced
member by member through the forecast map with additive process noise ``N(0, Q)``, then updated in the
standard stochastic form (Burgers et al. 1998; Evensen 2009)::

    A = E - mean(E),  Y = h(E) - mean(h(E))                    anomalies
    C_zy = A^T Y / (n - 1),  C_yy = Y^T Y / (n - 1)             sample covariances
    K = C_zy (C_yy + R)^{-1}                                    Cholesky solve, no explicit inverse
    E_i <- E_i + K (y + eps_i - h(E_i)),  eps_i ~ N(0, R)       perturbed observations

As in DAPPER's ``EnKF('PertObs')`` the perturbations are centred by default: their ensemble mean is
removed (so the mean update is exactly ``K (y - mean h(E))``) and they are rescaled by ``sqrt(n / (n - 1))``
so that each keeps variance ``R`` (DAPPER's ``mean0``); ``perturbations="raw"`` uses the draws as they
are. The optional multiplicative inflation ``E <- mean + inflation (E - mean)`` is applied to the
analysis ensemble. An optional localization hook maps ``(C_zy, C_yy)`` to tapered versions before the
gain is formed (:func:`schur_localization` builds the usual Schur-product taper). A forward run is
``step(assimilate=False)``: the ensemble forecast with process noise, no update, no inflation.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable
from typing import Literal

import torch
from torch import Tensor

from .batch_elements import nonfinite_elements
from .covariance import CovarianceSpec, as_covariance, check_symmetric, cholesky_or_nan, psd_sqrt, symmetrize
from .diagnostics import StepTimer, spectral_norm
from .divergence import DivergencePolicy, raise_if_diverged
from .dynamics import GaussianState, LatentDynamics
from .jacobians import apply_rows
from .measurements import check_mask, check_measurement, mask_measurement
from .sequential import SequentialFilter

Localization = Callable[[Tensor, Tensor], tuple[Tensor, Tensor]]
Perturbations = Literal["centered", "raw"]


def _randn(shape: tuple[int, ...], like: Tensor, generator: torch.Generator | None) -> Tensor:
    if generator is not None and generator.device.type != like.device.type:
        raise ValueError(
            f"the generator lives on {generator.device} but the ensemble on {like.device}; "
            f"create it with torch.Generator(device={str(like.device)!r})"
        )
    return torch.randn(shape, generator=generator, dtype=like.dtype, device=like.device)


def initial_ensemble(
    z0: Tensor, P0: CovarianceSpec, n_members: int, generator: torch.Generator | None = None
) -> Tensor:
    """Draw ``n_members`` members per batch element from ``N(z0, P0)``: ``(B, n, r)``."""
    if n_members < 2:
        raise ValueError(f"an ensemble needs at least 2 members to estimate a covariance, got n_members={n_members}")
    batch, r = z0.shape
    P = as_covariance(P0, batch, r, like=z0, name="P0")
    check_symmetric(P, "P0", definite=True)
    L = torch.linalg.cholesky(symmetrize(P))
    return z0[:, None, :] + _randn((batch, n_members, r), z0, generator) @ L.mT


def ensemble_state(ensemble: Tensor) -> GaussianState:
    """Sample mean ``(B, r)`` and sample covariance ``(B, r, r)`` (divisor ``n - 1``) of an ensemble ``(B, n, r)``."""
    mean = ensemble.mean(1)
    A = ensemble - mean[:, None, :]
    return GaussianState(mean, symmetrize(A.mT @ A) / (ensemble.shape[1] - 1))


def enkf_forecast(
    ensemble: Tensor,
    dynamics: LatentDynamics,
    Q: CovarianceSpec = 1e-4,
    generator: torch.Generator | None = None,
    *,
    check: bool = True,
) -> Tensor:
    """Advance every member through ``f`` and add process noise ``N(0, Q)`` per member; ``(B, n, r) -> (B, n, r)``."""
    batch, n, r = ensemble.shape
    forecast = apply_rows(dynamics.forecast, ensemble, dynamics.stacked_rows)
    if forecast.shape != ensemble.shape:
        raise ValueError(f"forecast returned {tuple(forecast.shape[-1:])} values per member, expected r = {r}")
    Q_mat = as_covariance(Q, batch, r, like=ensemble, name="Q")
    if bool(Q_mat.any()):
        forecast = forecast + _randn((batch, n, r), ensemble, generator) @ psd_sqrt(Q_mat).mT
    if check:
        raise_if_diverged(nonfinite_elements(forecast), "EnKF forecast")
    return forecast


def enkf_update(
    ensemble: Tensor,
    y: Tensor,
    dynamics: LatentDynamics,
    R: CovarianceSpec,
    generator: torch.Generator | None = None,
    *,
    inflation: float = 1.0,
    localization: Localization | None = None,
    perturbations: Perturbations = "centered",
    mask: Tensor | None = None,
    check: bool = True,
) -> tuple[Tensor, Tensor]:
    """Stochastic EnKF analysis with perturbed observations; returns the analysis ensemble and the gain ``K``.

    ``mask`` ``(B, m)`` bool: the readings present; the analysis uses only those (the missing readings' gain
    columns are 0; the perturbations are drawn for every reading, so the present ones get the same draws).
    """
    batch, n, _ = ensemble.shape
    predicted = apply_rows(dynamics.observe, ensemble, dynamics.stacked_rows)  # (B, n, m)
    m = predicted.shape[-1]
    y = check_measurement(y, batch, m, like=ensemble, mask=mask)
    mask = check_mask(mask, y)
    y, R_mat = mask_measurement(y, mask, as_covariance(R, batch, m, like=ensemble, name="R"))
    if mask is not None:  # the missing readings predict nothing: no spread, no innovation
        predicted = predicted * mask.to(predicted.dtype)[:, None, :]

    A = ensemble - ensemble.mean(1, keepdim=True)
    Y = predicted - predicted.mean(1, keepdim=True)
    C_zy = A.mT @ Y / (n - 1)
    C_yy = Y.mT @ Y / (n - 1)
    if localization is not None:
        C_zy, C_yy = localization(C_zy, C_yy)
    L, singular = cholesky_or_nan(symmetrize(C_yy + R_mat))
    K = torch.cholesky_solve(C_zy.mT, L).mT

    eps = _randn((batch, n, m), ensemble, generator) @ torch.linalg.cholesky(R_mat).mT
    if perturbations == "centered":
        eps = (eps - eps.mean(1, keepdim=True)) * math.sqrt(n / (n - 1))
    elif perturbations != "raw":
        raise ValueError(f"perturbations must be 'centered' or 'raw', got {perturbations!r}")
    if mask is not None:
        eps = eps * mask.to(eps.dtype)[:, None, :]
    analysis = ensemble + (y[:, None, :] + eps - predicted) @ K.mT
    if inflation != 1.0:
        mean = analysis.mean(1, keepdim=True)
        analysis = mean + inflation * (analysis - mean)
    if check:
        raise_if_diverged(nonfinite_elements(analysis) | singular, "EnKF update")
    return analysis, K


def schur_localization(rho_zy: Tensor, rho_yy: Tensor | None = None) -> Localization:
    """Localization hook: ``C_zy`` times the taper ``rho_zy`` ``(r, m)``, ``C_yy`` times ``rho_yy`` ``(m, m)``."""

    def localize(C_zy: Tensor, C_yy: Tensor) -> tuple[Tensor, Tensor]:
        C_zy = C_zy * rho_zy.to(C_zy)
        if rho_yy is not None:
            C_yy = C_yy * rho_yy.to(C_yy)
        return C_zy, C_yy

    return localize


class EnKF(SequentialFilter):
    """Stateful batched stochastic EnKF: ``reset(z0, P0)``, then ``step(y)`` (``assimilate=False``: forecast only).

    Parameters as for :class:`~dks_gym.filters.EKF` (``R`` or ``sigma``, ``Q`` default ``1e-4 I``,
    ``on_divergence``), plus ``n_members`` (default 20), ``inflation`` (multiplicative factor on the
    analysis anomalies, default 1.0 = none), ``localization`` (hook ``(C_zy, C_yy) -> (C_zy, C_yy)``,
    default none), ``perturbations`` (``"centered"``, default, or ``"raw"``; see the module docstring)
    and ``generator``: a ``torch.Generator`` on the state's device, or an int seed from which one is
    created at every :meth:`reset` (default 0), so runs are reproducible.
    """

    def __init__(
        self,
        dynamics: LatentDynamics,
        *,
        R: CovarianceSpec | None = None,
        sigma: float | Tensor | None = None,
        Q: CovarianceSpec = 1e-4,
        n_members: int = 20,
        inflation: float = 1.0,
        localization: Localization | None = None,
        perturbations: Perturbations = "centered",
        generator: torch.Generator | int = 0,
        on_divergence: DivergencePolicy = "raise",
        record_diagnostics: bool = True,
    ) -> None:
        super().__init__(
            dynamics, R=R, sigma=sigma, Q=Q, on_divergence=on_divergence, record_diagnostics=record_diagnostics
        )
        if int(n_members) != n_members or n_members < 2:
            raise ValueError(f"n_members must be an integer >= 2, got {n_members}")
        if not (inflation >= 1.0 and inflation < float("inf")):
            raise ValueError(f"inflation must be a finite factor >= 1 (1.0 = none), got {inflation}")
        if localization is not None and not callable(localization):
            raise TypeError(
                "localization must be a callable (C_zy, C_yy) -> (C_zy, C_yy), e.g. schur_localization(rho)"
            )
        if not isinstance(generator, (torch.Generator, int)):
            raise TypeError(f"generator must be a torch.Generator or an int seed, got {type(generator).__name__}")
        self.n_members = int(n_members)
        self.inflation = float(inflation)
        self.localization = localization
        if perturbations not in ("centered", "raw"):
            raise ValueError(f"perturbations must be 'centered' or 'raw', got {perturbations!r}")
        self.perturbations = perturbations
        self._generator_spec = generator
        self.generator: torch.Generator | None = generator if isinstance(generator, torch.Generator) else None
        self.ensemble: Tensor | None = None

    def reset(self, z0: Tensor, P0: CovarianceSpec | None = None) -> None:
        """Draw ``n_members`` members per element from ``N(z0, P0)``; ``z0`` ``(B, r)``, ``P0`` default ``I``, SPD."""
        self._start(z0)
        z0 = torch.as_tensor(z0).detach()
        if isinstance(self._generator_spec, int):
            self.generator = torch.Generator(device=z0.device).manual_seed(self._generator_spec)
        self.reset_ensemble(
            initial_ensemble(z0, self._initial_covariance(P0, z0), self.n_members, self.generator), _started=True
        )

    def reset_ensemble(self, ensemble: Tensor, *, _started: bool = False) -> None:
        """Start from a given ensemble ``(B, n, r)`` (e.g. one shared with another filter)."""
        ensemble = torch.as_tensor(ensemble).detach()
        if ensemble.ndim != 3 or ensemble.shape[1] < 2:
            raise ValueError(f"ensemble must be (B, n, r) with n >= 2 members, got shape {tuple(ensemble.shape)}")
        if not _started:
            self._start(ensemble.mean(1))
            if isinstance(self._generator_spec, int):
                self.generator = torch.Generator(device=ensemble.device).manual_seed(self._generator_spec)
        self._initial_ensemble = ensemble.clone()
        self.ensemble = ensemble.clone()

    @property
    def mean(self) -> Tensor:
        """Ensemble mean ``(B, r)``."""
        self._require_reset()
        return self.ensemble.mean(1)

    @property
    def cov(self) -> Tensor:
        """Sample covariance ``(B, r, r)`` of the ensemble (divisor ``n - 1``)."""
        self._require_reset()
        return ensemble_state(self.ensemble).cov

    def lead(self, steps: int) -> "EnKF":
        """A copy whose members are forecast ``steps`` steps ahead with process noise and no measurement; this
        filter and its generator are unchanged (the copy draws from a copy of the generator, so its noise is
        the noise this filter's next forecasts would draw). For readings that arrive late (see
        :meth:`EKF.lead`); the copy is for reading (``mean``, ``cov``, ``ensemble``).
        """
        self._require_reset()
        ahead = copy.copy(self)
        ahead.record_diagnostics = False
        generator = self.generator
        if generator is not None:
            generator = torch.Generator(device=generator.device)
            generator.set_state(self.generator.get_state())
        E = self.ensemble
        for _ in range(int(steps)):
            E = enkf_forecast(E, self.dynamics, self._process_noise(E), generator, check=False)
        ahead.ensemble, ahead.generator = E, generator
        return ahead

    def step(self, y: Tensor | None = None, assimilate: bool = True, mask: Tensor | None = None) -> Tensor:
        """Forecast every member and, if ``assimilate``, update with ``y`` ``(B, m)``; return the mean ``(B, r)``.

        ``mask`` ``(B, m)`` bool: the readings present (default all); a step with none present is a forecast
        and draws no perturbations, so an episode without readings is the forward run.
        """
        self._require_reset()
        E = self.ensemble
        with StepTimer(E.device) as timer:
            y_checked, mask = self._measurement(y, E, mask) if assimilate else (None, None)
            E = enkf_forecast(E, self.dynamics, self._process_noise(E), self.generator, check=False)
            gain_norm = torch.zeros(self._batch, dtype=E.dtype, device=E.device)
            if assimilate and (mask is None or bool(mask.any())):
                E, K = enkf_update(
                    E,
                    y_checked,
                    self.dynamics,
                    self._measurement_noise(E, y_checked.shape[1]),
                    self.generator,
                    inflation=self.inflation,
                    localization=self.localization,
                    perturbations=self.perturbations,
                    mask=mask,
                    check=False,
                )
                self._m = y_checked.shape[1]
                if self.record_diagnostics:
                    gain_norm = spectral_norm(torch.nan_to_num(K, nan=0.0, posinf=0.0, neginf=0.0))
            restart = nonfinite_elements(E)
            if bool(restart.any()):
                self._resolve_divergence(restart, "update" if assimilate else "forecast")
                E = torch.where(restart[:, None, None], self._initial_ensemble, E)
            self.ensemble = E
            self.n_steps += 1
        if self.record_diagnostics:
            self._record(
                timer,
                forecast_norm=torch.full((self._batch,), float("nan"), dtype=E.dtype, device=E.device),
                gain_norm=gain_norm,
                spread=E.var(1).mean(-1).sqrt(),
                reset=restart,
                assimilated=assimilate,
            )
        return E.mean(1)
