"""LatentFilter: a latent model inside an EKF or EnKF, wrapped around a SensingEnv (paper Section II.E).

The wrapper turns the raw sensor stream into a belief over the latent state z (dimension r) and a
reconstruction of the full field. Per step: the env advances one frame and reads the sensors; the
filter forecasts z with the model (Eq. 13-14) and, unless ``filter="none"`` (the forward run), updates
it with the readings (Eq. 15-17) through h(z) = S(decode(z)) at the sensors the env actually read
(so ``sensor_mode="select"`` layouts are followed step by step).

* observation: ``[mean z (r); log diag P (r)]`` as float32, the filter's belief;
* ``info["estimate"]``: the decoded mean, ``(C, *grid)`` in physical units; ``info["mse"]``;
* reward: minus the MSE over the scored channels against ``env.unwrapped.true_state`` (physical units),
  or over standardized channels with ``reward="normalized_mse"``.
"""

from __future__ import annotations

import weakref
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from ..dataset import Dataset
from ..envs.sensing import SensingEnv
from ..filters import EKF, EnKF, LatentDynamics, bind_param

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
    observe_jacobian = None
    if model.kind == "pdmd":
        def observe_jacobian(z: torch.Tensor) -> torch.Tensor:
            rows = sensors.current.repeat(z.shape[0] // len(sensors.current), axis=0)
            return torch.stack([model.observation_matrix(s, channel) for s in rows]).to(z)
    return LatentDynamics(forecast, bind_param(observe, mu), forecast_jacobian=forecast_jacobian,
                          observe_jacobian=observe_jacobian)


def resolve_model(model: Any, benchmark: str, *, r: int | None, preset: str, T: int, device: str,
                  train_if_missing: bool) -> Any:
    """A model object, or load the cached checkpoint named by ``model`` ("koopman", "pdmd", "mlp", "xlstm").

    ``r`` (default 32 for names) must match a given model object's latent dimension when it is passed.
    """
    if isinstance(model, str):
        if model not in MODEL_KINDS:
            raise ValueError(f"unknown model {model!r}; choose one of {', '.join(MODEL_KINDS)} or pass a model object")
        from ..models import load_model

        model = load_model(benchmark, model, r=32 if r is None else r, preset=preset, T=T, device=device,
                           train_if_missing=train_if_missing)
    for attr in ("encode", "decode", "forecast", "forecast_jacobian", "observe", "benchmark", "r", "kind"):
        if not hasattr(model, attr):
            raise TypeError(f"model must provide {attr!r} (see dks_gym.models.LatentModel), got {type(model).__name__}")
    if model.benchmark != benchmark:
        raise ValueError(f"the model was trained for {model.benchmark!r}, but the environment is {benchmark!r}")
    if r is not None and model.r != r:
        raise ValueError(f"the model has latent dimension r={model.r}, but r={r} was asked for")
    return model


def make_filter(kind: str, dynamics: LatentDynamics, *, sigma: torch.Tensor, Q: float, n_members: int,
                inflation: float, seed: int, on_divergence: str) -> EKF | EnKF:
    """The filter object for ``kind`` ("ekf", "enkf"; "none" runs the EKF loop with the update off)."""
    if kind == "enkf":
        return EnKF(dynamics, sigma=sigma, Q=Q, n_members=n_members, inflation=inflation, generator=seed,
                    on_divergence=on_divergence)
    return EKF(dynamics, sigma=sigma, Q=Q, on_divergence=on_divergence)


def field_errors(estimate: torch.Tensor, truth: torch.Tensor, scored: tuple[int, ...],
                 std: torch.Tensor | None = None) -> torch.Tensor:
    """Eq. 18: MSE over the scored channels and all cells, per batch element; standardized when ``std`` is given."""
    diff = (estimate[:, list(scored)] - truth[:, list(scored)]).flatten(2)
    if std is not None:
        diff = diff / std[list(scored)].to(diff)[None, :, None]
    return diff.pow(2).mean(dim=(1, 2))


class LatentFilter(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Assimilate a SensingEnv's readings into a latent model's state with an EKF, an EnKF or no update."""

    def __init__(
        self,
        env: gym.Env,
        model: Any = "koopman",
        filter: str = "ekf",
        *,
        r: int | None = None,
        model_preset: str = "lite",
        T: int = 1,
        initial: str = "approximate",
        P0: float = 1.0,
        Q: float = 1e-4,
        n_members: int = 20,
        inflation: float = 1.0,
        reward: str = "mse",
        device: str = "cpu",
        dtype: torch.dtype = torch.float32,
        seed: int = 0,
        on_divergence: str = "raise",
        train_if_missing: bool = False,
    ) -> None:
        args = {k: v for k, v in locals().items() if k not in ("self", "env", "__class__")}
        gym.utils.RecordConstructorArgs.__init__(self, **args)
        super().__init__(env)
        base = env.unwrapped
        if not isinstance(base, SensingEnv):
            raise TypeError(f"LatentFilter wraps a dks_gym SensingEnv, got {type(base).__name__}")
        if filter not in FILTERS:
            raise ValueError(f"unknown filter {filter!r}; choose one of {', '.join(FILTERS)}")
        if initial not in INITIAL_CONDITIONS:
            raise ValueError(f"unknown initial condition {initial!r}; choose 'approximate' or 'exact'")
        if reward not in REWARDS:
            raise ValueError(f"unknown reward {reward!r}; choose one of {', '.join(REWARDS)}")
        self.model = resolve_model(model, base.benchmark.name, r=r, preset=model_preset, T=T, device=device,
                                   train_if_missing=train_if_missing)
        self.filter_kind = filter
        self.initial = initial
        self.P0, self.Q = P0, Q
        self.n_members, self.inflation, self.seed = n_members, inflation, seed
        self.on_divergence = on_divergence
        self.reward_kind = reward
        self.device = torch.device(device)
        self.dtype = dtype
        r = self.model.r
        big = np.finfo(np.float32).max
        self.observation_space = spaces.Box(-big, big, shape=(2 * r,), dtype=np.float32)
        self._sensors = SensorRef(base.sensors)
        self._std = torch.as_tensor(base.dataset.stats_std, dtype=dtype, device=self.device)
        self.filter: EKF | EnKF | None = None
        self.estimate: np.ndarray | None = None

    # Gymnasium API ---------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        _, info = self.env.reset(seed=seed, options=options)
        base = self.env.unwrapped
        self._sensors.current = np.atleast_2d(base.sensors)
        mu = torch.tensor([base.mu], dtype=self.dtype, device=self.device)
        dynamics = model_dynamics(self.model, mu, self._sensors, base.benchmark.observed_channel)
        sigma = torch.tensor([max(base.sigma, 1e-12)], dtype=self.dtype, device=self.device)
        self.filter = make_filter(self.filter_kind, dynamics, sigma=sigma, Q=self.Q, n_members=self.n_members,
                                  inflation=self.inflation, seed=self.seed if seed is None else seed,
                                  on_divergence=self.on_divergence)
        if self.initial == "exact":
            with torch.no_grad():
                x0 = torch.as_tensor(base.true_state[None], dtype=self.dtype, device=self.device)
                z0 = self.model.encode(x0, mu)
        else:
            z0 = approximate_initial_latent(self.model, base.dataset).to(self.dtype)[None]
        self.filter.reset(z0.to(self.device, self.dtype), self.P0)
        return self._belief(), self._estimate_info(info)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        if self.filter is None:
            raise RuntimeError("call reset() before step()")
        obs, _, terminated, truncated, info = self.env.step(action)
        self._sensors.current = np.atleast_2d(info["sensors"])
        y = torch.as_tensor(obs, dtype=self.dtype, device=self.device)[None]
        self.filter.step(y, assimilate=self.filter_kind != "none")
        info = self._estimate_info(info)
        d = self.filter.diagnostics
        # Wall time per step stays in self.filter.diagnostics: in info it would break step determinism.
        info.update(gain_norm=float(d.gain_norm[-1][0]), spread=float(d.spread[-1][0]))
        if isinstance(self.filter, EKF):  # the EnKF uses no forecast Jacobian
            info["forecast_norm"] = float(d.forecast_norm[-1][0])
        reward = -(info["mse"] if self.reward_kind == "mse" else info["normalized_mse"])
        return self._belief(), reward, terminated, truncated, info

    # Belief and estimate ---------------------------------------------------------------------------
    def _belief(self) -> np.ndarray:
        mean = self.filter.mean[0]
        var = self.filter.cov[0].diagonal().clamp_min(1e-30)
        return torch.cat([mean, var.log()]).detach().cpu().numpy().astype(np.float32)

    def _estimate_info(self, info: dict[str, Any]) -> dict[str, Any]:
        base = self.env.unwrapped
        mu = torch.tensor([base.mu], dtype=self.dtype, device=self.device)
        with torch.no_grad():
            estimate = self.model.decode(self.filter.mean.detach(), mu)
        truth = torch.as_tensor(base.true_state[None], dtype=estimate.dtype, device=estimate.device)
        scored = base.benchmark.scored_indices
        mse = float(field_errors(estimate, truth, scored)[0])
        nmse = float(field_errors(estimate, truth, scored, self._std)[0])
        self.estimate = estimate[0].cpu().numpy().astype(np.float32)
        info = dict(info)
        info.update(estimate=self.estimate, mse=mse, normalized_mse=nmse,
                    latent_mean=self.filter.mean[0].detach().cpu().numpy())
        return info

    def render(self) -> np.ndarray | None:
        base = self.env.unwrapped
        if base.render_mode != "rgb_array":
            gym.logger.warn("render() needs the env made with render_mode='rgb_array'")
            return None
        from ..envs.render import render_panels

        c = base.benchmark.channels.index(base.render_channel)
        truth, est = base.true_state[c], self.estimate[c]
        return render_panels(
            base.benchmark, base.dataset.coords,
            [(f"truth {base.render_channel}", truth), (f"estimate ({self.filter_kind})", est),
             ("error", est - truth)],
            base.sensors, base.fluid_mask,
        )
