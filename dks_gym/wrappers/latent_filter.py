"""LatentFilter: a latent model inside an EKF or EnKF, wrapped around a SensingEnv (paper Section II.E).

The wrapper turns the raw sensor stream into a belief over the latent state z (dimension r) and a
reconstruction of the full field. Per step: the env advances one frame and reads the sensors; the
assimilation core forecasts z with the model (Eq. 13-14) and, unless ``filter="forward"``, updates it
with the readings (Eq. 15-17) through h(z) = S(decode(z)) at the sensors the env actually read (so
``sensor_mode="select"`` layouts are followed step by step).

* observation: ``[mean z (r); log diag P (r)]`` as float32, the filter's belief;
* ``info["estimate"]``: the decoded mean, ``(C, *grid)`` in physical units; ``info["mse"]``,
  ``info["normalized_mse"]``, ``gain_norm``, ``spread`` and (EKF) ``forecast_norm`` = ||F_k||_2;
* with ``uncertainty=True`` (default) ``info["estimate_std"]``, the predictive std of every cell
  (``(C, *grid)``, physical units: the filter's latent covariance pushed through the decoder, plus the
  decoder's reconstruction variance when given), and its scores ``coverage`` (of the central 95 %
  interval), ``nees`` (mean per cell) and ``crps`` over the scored channels;
  wall time per DA step is in ``wrapper.filter.diagnostics`` (in info it would break determinism);
* reward: minus the MSE over the scored channels against ``env.unwrapped.true_state`` (physical units),
  or over standardized channels with ``reward="normalized_mse"``.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from ..assimilation import Assimilation, FilterConfig, Snapshot, resolve_model, tune_if_missing
from ..envs.sensing import SensingEnv

REWARDS = ("mse", "normalized_mse")


def build_assimilation(base: SensingEnv, model: Any, filter: str | None, config: FilterConfig | None, *,
                       r: int | None, model_preset: str, T: int, reward: str, device: str, dtype: torch.dtype,
                       train_if_missing: bool, uncertainty: bool = True,
                       reconstruction_var: Any = None) -> Assimilation:
    """The assimilation core a filter wrapper runs: the model resolved for the env's dataset, the config
    with ``filter`` (when given) as its kind. Shared by :class:`LatentFilter` and the vector env."""
    if reward not in REWARDS:
        raise ValueError(f"unknown reward {reward!r}; choose one of {', '.join(REWARDS)}")
    config = FilterConfig() if config is None else config
    if not isinstance(config, FilterConfig):
        raise TypeError(f"config must be a dks_gym.FilterConfig, got {type(config).__name__}")
    if filter is not None:
        config = dataclasses.replace(config, kind=filter)
    latent = resolve_model(model, base.benchmark.name, r=r, preset=model_preset, T=T, device=device,
                           train_if_missing=train_if_missing, dataset=base.dataset)
    if train_if_missing and isinstance(model, str):  # asked to prepare a missing model: tune it too
        tune_if_missing(latent, base.dataset)
    return Assimilation(latent, config, device=device, dtype=dtype, uncertainty=uncertainty,
                        reconstruction_var=reconstruction_var)


def belief_space(r: int) -> spaces.Box:
    """The belief [mean z (r); log diag P (r)] as a float32 Box."""
    big = np.finfo(np.float32).max
    return spaces.Box(-big, big, shape=(2 * r,), dtype=np.float32)


class LatentFilter(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Assimilate a SensingEnv's readings into a latent model's state with an EKF, an EnKF or a forward run.

    ``model``: "koopman", "pdmd", "mlp", "xlstm" (a cached checkpoint of ``model_preset``, ``r``
    (default 32) and multi-step horizon ``T``, trained on the env's dataset; ``train_if_missing=True`` trains
    it, otherwise a missing checkpoint raises ``CheckpointMissing``) or a model object.
    ``filter``: "ekf", "enkf" or "forward" (default: ``config.kind``, "ekf"). ``config``: a
    :class:`~dks_gym.FilterConfig` with everything else (initial condition, P0, Q, ensemble size, inflation,
    localization, divergence policy, seed); R = sigma^2 I comes from the env.
    ``uncertainty``: put ``estimate_std`` and its scores (``coverage``, ``nees``, ``crps``) in ``info``
    (default True; it costs r decoder Jacobian-vector products per step, or one decode per EnKF member:
    False for speed). ``reconstruction_var``: the decoder's reconstruction-error variance per cell
    ``(C, *grid)`` (:func:`~dks_gym.assimilation.reconstruction_variance`), added to the variance.
    """

    def __init__(
        self,
        env: gym.Env,
        model: Any = "koopman",
        filter: str | None = None,
        *,
        config: FilterConfig | None = None,
        r: int | None = None,
        model_preset: str = "lite",
        T: int = 1,
        reward: str = "mse",
        device: str = "cpu",
        dtype: torch.dtype = torch.float32,
        train_if_missing: bool = False,
        uncertainty: bool = True,
        reconstruction_var: Any = None,
    ) -> None:
        args = {k: v for k, v in locals().items() if k not in ("self", "env", "__class__")}
        gym.utils.RecordConstructorArgs.__init__(self, **args)
        super().__init__(env)
        base = env.unwrapped
        if not isinstance(base, SensingEnv):
            raise TypeError(f"LatentFilter wraps a dks_gym SensingEnv, got {type(base).__name__}")
        self.assimilation = build_assimilation(base, model, filter, config, r=r, model_preset=model_preset, T=T,
                                               reward=reward, device=device, dtype=dtype,
                                               train_if_missing=train_if_missing, uncertainty=uncertainty,
                                               reconstruction_var=reconstruction_var)
        self.model = self.assimilation.model
        self.config = self.assimilation.config
        self.reward_kind = reward
        self.observation_space = belief_space(self.model.r)
        self.estimate: np.ndarray | None = None
        self.estimate_std: np.ndarray | None = None

    @property
    def filter(self):
        """The running filter (an EKF or EnKF object, with ``.mean``, ``.cov``, ``.diagnostics``)."""
        return self.assimilation.filter

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        _, info = self.env.reset(seed=seed, options=options)
        snap = self.assimilation.start([self.env.unwrapped], seed=self.config.seed if seed is None else seed)
        return self.assimilation.belief()[0], self._info(info, snap)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        obs, _, terminated, truncated, info = self.env.step(action)
        snap = self.assimilation.step([self.env.unwrapped], obs[None], info["sensors"][None])
        info = self._info(info, snap)
        info.update({k: float(v[0]) for k, v in snap.diagnostics.items()})
        reward = -(info["mse"] if self.reward_kind == "mse" else info["normalized_mse"])
        return self.assimilation.belief()[0], reward, terminated, truncated, info

    def _info(self, info: dict[str, Any], snap: Snapshot) -> dict[str, Any]:
        self.estimate = snap.estimate[0].cpu().numpy().astype(np.float32)
        info = dict(info)
        info.update(estimate=self.estimate, mse=float(snap.mse[0]), normalized_mse=float(snap.normalized_mse[0]),
                    latent_mean=snap.latent_mean[0])
        if snap.estimate_std is not None:
            self.estimate_std = snap.estimate_std[0].cpu().numpy().astype(np.float32)
            info.update(estimate_std=self.estimate_std, coverage=float(snap.coverage[0]), nees=float(snap.nees[0]),
                        crps=float(snap.crps[0]))
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
            [(f"truth {base.render_channel}", truth), (f"estimate ({self.config.kind})", est),
             ("error", est - truth)],
            base.sensors, base.fluid_mask,
        )
