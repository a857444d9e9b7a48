"""The batched core behind the filter wrappers: one latent model, one EKF/EnKF, B sensing environments.

:class:`LatentAssimilator` starts a filter for the current episodes of B ``SensingEnv`` objects (their mu,
noise sigma, sensors, initial condition), advances it with their readings, and decodes the estimate.
:class:`~dks_gym.wrappers.LatentFilter` is the B = 1 case, the vector env the B = N case, and the
evaluation harness runs every test trajectory of a benchmark through it at once.
"""

from __future__ import annotations

import numbers
import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch

from ..dataset import Dataset
from ..envs.sensing import SensingEnv
from ..filters import EKF, EnKF, LatentDynamics, bind_param
from ..filters.common import check_covariance_spec

FILTERS = ("ekf", "enkf", "none")
MODEL_KINDS = ("koopman", "pdmd", "mlp", "xlstm")
INITIAL_CONDITIONS = ("approximate", "exact")
REWARDS = ("mse", "normalized_mse")

# Per model, per dataset file: the approximate initial latent state (it costs one pass over the train split).
_APPROXIMATE_CACHE: "weakref.WeakKeyDictionary[Any, dict[str, torch.Tensor]]" = weakref.WeakKeyDictionary()


def approximate_initial_latent(model: Any, dataset: Dataset) -> torch.Tensor:
    """z0 = mean over the training trajectories of their encoded first frames (SPEC section 4), (r,).

    For pDMD the encoding is the POD projection, so this is the mean of their POD coefficients.
    """
    per_model = _APPROXIMATE_CACHE.setdefault(model, {})
    key = str(Path(dataset.path).resolve())
    if key not in per_model:
        first = np.asarray(dataset.fields("train")[:, 0], dtype=np.float32)
        mu = dataset.params("train")
        with torch.no_grad():
            z = torch.cat([model.encode(torch.from_numpy(first[i : i + 16]), torch.from_numpy(mu[i : i + 16]))
                           for i in range(0, len(first), 16)])
        per_model[key] = z.mean(0)
    return per_model[key]


class SensorRef:
    """The layouts the filter's observation operator reads, one row per batch element, (B, m).

    The wrapper updates ``current`` every step, so ``sensor_mode="select"`` layouts are followed.
    """

    def __init__(self, sensors: np.ndarray) -> None:
        self.current = np.atleast_2d(np.asarray(sensors, dtype=np.int64))

    def rows(self, n_rows: int, device: torch.device) -> torch.Tensor:
        """Sensor indices for ``n_rows`` stacked rows (row j belongs to batch element j // (n_rows // B))."""
        idx = torch.as_tensor(self.current, device=device)
        return idx.repeat_interleave(n_rows // idx.shape[0], dim=0)


def model_dynamics(model: Any, mu: torch.Tensor, sensors: SensorRef, channel: str) -> LatentDynamics:
    """The model as the filters see it: mu bound, h(z) = S(decode(z)) at each element's current sensors.

    Linear models hand the filter their constant operator (Koopman K(mu), pDMD A~(mu)), computed once
    per episode; the nonlinear ones give a Jacobian callable (autodiff, at the analysis state). pDMD's
    h is affine, so its Jacobian S diag(std) U_r is given exactly too.
    """
    c = model.shape.channels.index(channel)

    def observe(z: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
        fields = model.decode(z, m).flatten(2)[:, c]
        return fields.gather(1, sensors.rows(z.shape[0], fields.device))

    forecast = bind_param(model.forecast, mu)
    if model.kind in ("koopman", "pdmd"):
        with torch.no_grad():
            forecast_jacobian: Any = model.forecast_jacobian(
                torch.zeros(len(mu), model.r, dtype=mu.dtype, device=mu.device), mu)
    else:
        forecast_jacobian = bind_param(model.forecast_jacobian, mu)

    def pdmd_observe_jacobian(z: torch.Tensor) -> torch.Tensor:
        rows = sensors.current.repeat(z.shape[0] // len(sensors.current), axis=0)
        return torch.stack([model.observation_matrix(s, channel) for s in rows]).to(z)

    return LatentDynamics(forecast, bind_param(observe, mu), forecast_jacobian=forecast_jacobian,
                          observe_jacobian=pdmd_observe_jacobian if model.kind == "pdmd" else None)


def resolve_model(model: Any, benchmark: str, *, r: int | None, preset: str, T: int, device: str,
                  train_if_missing: bool, dataset: Dataset | None = None) -> Any:
    """A model object, or load the cached checkpoint named by ``model`` ("koopman", "pdmd", "mlp", "xlstm").

    ``r`` (default 32 for names) must match a given model object's latent dimension when it is passed.
    ``dataset``: the environment's dataset; a named checkpoint is looked up (and trained, with
    ``train_if_missing``) for that dataset's preset, and must have been trained on it.
    """
    if isinstance(model, str):
        if model not in MODEL_KINDS:
            raise ValueError(f"unknown model {model!r}; choose one of {', '.join(MODEL_KINDS)} or pass a model object")
        from ..models import load_model

        model = load_model(benchmark, model, r=32 if r is None else r, preset=preset, T=T, device=device,
                           dataset=dataset, train_if_missing=train_if_missing)
    for attr in ("encode", "decode", "forecast", "forecast_jacobian", "observe", "benchmark", "r", "kind"):
        if not hasattr(model, attr):
            raise TypeError(f"model must provide {attr!r} (see dks_gym.models.LatentModel), got {type(model).__name__}")
    if model.benchmark != benchmark:
        raise ValueError(f"the model was trained for {model.benchmark!r}, but the environment is {benchmark!r}")
    if r is not None and model.r != r:
        raise ValueError(f"the model has latent dimension r={model.r}, but r={r} was asked for")
    return model


def field_errors(estimate: torch.Tensor, truth: torch.Tensor, scored: tuple[int, ...],
                 std: torch.Tensor | None = None) -> torch.Tensor:
    """Eq. 18: MSE over the scored channels and all cells, per batch element; standardized when ``std`` is given."""
    diff = (estimate[:, list(scored)] - truth[:, list(scored)]).flatten(2)
    if std is not None:
        diff = diff / std[list(scored)].to(diff)[None, :, None]
    return diff.pow(2).mean(dim=(1, 2))


@dataclass(frozen=True)
class FilterConfig:
    """How to filter: the filter kind and its settings (defaults: SPEC section 4)."""

    filter: str = "ekf"
    initial: str = "approximate"
    P0: float = 1.0
    Q: float = 1e-4
    n_members: int = 20
    inflation: float = 1.0
    on_divergence: str = "raise"

    def __post_init__(self) -> None:
        if self.filter not in FILTERS:
            raise ValueError(f"unknown filter {self.filter!r}; choose one of {', '.join(FILTERS)}")
        if self.initial not in INITIAL_CONDITIONS:
            raise ValueError(f"unknown initial condition {self.initial!r}; choose 'approximate' or 'exact'")
        # Checked here, at construction, not first at reset(): the filter objects are only built then.
        # P0 and Q are a variance (times I), or a (B,), (r, r) or (B, r, r) tensor (see dks_gym.filters.common).
        check_covariance_spec(self.P0, "P0", definite=True)
        check_covariance_spec(self.Q, "Q", definite=False)
        n = self.n_members
        if isinstance(n, bool) or not isinstance(n, numbers.Integral) or n < 2:
            raise ValueError(f"n_members must be an integer >= 2 (an ensemble needs two members "
                             f"for a covariance), got {n!r}")
        inflation = self.inflation
        if isinstance(inflation, bool) or not isinstance(inflation, numbers.Real) \
                or not (1.0 <= float(inflation) < float("inf")):
            raise ValueError(f"inflation must be a finite factor >= 1 (1.0 = none), got {inflation!r}")
        if self.on_divergence not in ("raise", "reset"):
            raise ValueError(f"on_divergence must be 'raise' or 'reset', got {self.on_divergence!r}")

    def make(self, dynamics: LatentDynamics, sigma: torch.Tensor, seed: int) -> EKF | EnKF:
        """The filter object ("none" is the EKF loop run with the update off)."""
        if self.filter == "enkf":
            return EnKF(dynamics, sigma=sigma, Q=self.Q, n_members=self.n_members, inflation=self.inflation,
                        generator=seed, on_divergence=self.on_divergence)
        return EKF(dynamics, sigma=sigma, Q=self.Q, on_divergence=self.on_divergence)


class LatentAssimilator:
    """One latent model and one batched filter following the episodes of B sensing environments."""

    def __init__(self, model: Any, config: FilterConfig, *, device: str | torch.device = "cpu",
                 dtype: torch.dtype = torch.float32) -> None:
        self.model = model
        self.config = config
        self.device = torch.device(device)
        self.dtype = dtype
        self.sensors = SensorRef(np.zeros((1, 1), dtype=np.int64))
        self.filter: EKF | EnKF | None = None
        self._mu: torch.Tensor | None = None

    @property
    def assimilates(self) -> bool:
        return self.config.filter != "none"

    def start(self, envs: Sequence[SensingEnv], seed: int) -> None:
        """A fresh filter for the envs' current episodes (call right after resetting them)."""
        bench = envs[0].benchmark
        self._mu = torch.tensor([e.mu for e in envs], dtype=self.dtype, device=self.device)
        self.sensors.current = np.stack([e.sensors for e in envs])
        dynamics = model_dynamics(self.model, self._mu, self.sensors, bench.observed_channel)
        # A noise-free env (noise_level=0) still needs a positive R for the gain to exist.
        sigma = torch.tensor([max(e.sigma, 1e-12) for e in envs], dtype=self.dtype, device=self.device)
        self.filter = self.config.make(dynamics, sigma, seed)
        if self.config.initial == "exact":
            with torch.no_grad():
                z0 = self.model.encode(self.truth(envs), self._mu)
        else:
            z0 = approximate_initial_latent(self.model, envs[0].dataset).expand(len(envs), -1)
        self.filter.reset(z0.to(self.device, self.dtype).clone(), self.config.P0)

    def step(self, readings: np.ndarray, sensors: np.ndarray) -> None:
        """Forecast, and update with the readings (B, m) taken at ``sensors`` (B, m) unless forward-running."""
        if self.filter is None:
            raise RuntimeError("call reset() before step()")
        self.sensors.current = np.asarray(sensors)
        y = torch.as_tensor(np.asarray(readings), dtype=self.dtype, device=self.device)
        self.filter.step(y, assimilate=self.assimilates)

    def truth(self, envs: Sequence[SensingEnv]) -> torch.Tensor:
        return torch.as_tensor(np.stack([e.true_state for e in envs]), dtype=self.dtype, device=self.device)

    def estimate(self) -> torch.Tensor:
        """The decoded filter mean, (B, C, *grid), physical units."""
        with torch.no_grad():
            return self.model.decode(self.filter.mean.detach(), self._mu)

    def belief(self) -> np.ndarray:
        """[mean z; log diag P] per element, (B, 2r) float32."""
        var = self.filter.cov.diagonal(dim1=-2, dim2=-1).clamp_min(1e-30)
        return torch.cat([self.filter.mean, var.log()], dim=1).detach().cpu().numpy().astype(np.float32)

    def errors(self, estimate: torch.Tensor, envs: Sequence[SensingEnv]) -> tuple[np.ndarray, np.ndarray]:
        """Eq. 18 MSE per element in physical units, and the same over standardized channels."""
        bench = envs[0].benchmark
        truth = self.truth(envs).to(estimate)
        std = torch.as_tensor(envs[0].dataset.stats_std, device=estimate.device)
        mse = field_errors(estimate, truth, bench.scored_indices)
        nmse = field_errors(estimate, truth, bench.scored_indices, std)
        return mse.cpu().numpy(), nmse.cpu().numpy()

    def step_diagnostics(self) -> dict[str, np.ndarray]:
        """Gain norm, spread and (EKF) ||F_k||_2 of the last step, per element."""
        d = self.filter.diagnostics
        out = {"gain_norm": d.gain_norm[-1].cpu().numpy(), "spread": d.spread[-1].cpu().numpy()}
        if isinstance(self.filter, EKF):  # the EnKF uses no forecast Jacobian
            out["forecast_norm"] = d.forecast_norm[-1].cpu().numpy()
        return out
