"""LatentFilter: a latent model inside an EKF or EnKF, wrapped around a SensingEnv (paper Section II.E).

The wrapper turns the raw sensor stream into a belief over the latent state z (dimension r) and a
reconstruction of the full field. Per step: the env advances one frame and reads the sensors; the
filter forecasts z with the model (Eq. 13-14) and, unless ``filter="none"`` (the forward run), updates
it with the readings (Eq. 15-17) through h(z) = S(decode(z)) at the sensors the env actually read
(so ``sensor_mode="select"`` layouts are followed step by step).

* observation: ``[mean z (r); log diag P (r)]`` as float32, the filter's belief;
* ``info["estimate"]``: the decoded mean, ``(C, *grid)`` in physical units; ``info["mse"]``,
  ``info["normalized_mse"]``, ``gain_norm``, ``spread`` and (EKF) ``forecast_norm`` = ||F_k||_2;
  wall time per DA step is in ``wrapper.filter.diagnostics`` (in info it would break determinism);
* reward: minus the MSE over the scored channels against ``env.unwrapped.true_state`` (physical units),
  or over standardized channels with ``reward="normalized_mse"``.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from ..envs.sensing import SensingEnv
from .assimilator import REWARDS, FilterConfig, LatentAssimilator, resolve_model


class LatentFilter(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Assimilate a SensingEnv's readings into a latent model's state with an EKF, an EnKF or no update.

    ``model``: "koopman", "pdmd", "mlp", "xlstm" (a cached checkpoint of ``model_preset``, ``r``
    (default 32) and multi-step horizon ``T``, trained on the env's dataset; ``train_if_missing=True`` trains
    it) or a model object.
    ``filter``: "ekf", "enkf" or "none" (forward run). ``initial``: "approximate" (mean encoded first
    frame of the training trajectories) or "exact" (encode the true first frame). ``P0``, ``Q``: initial
    and process covariances (multiples of I); R = sigma^2 I from the env. EnKF: ``n_members``,
    ``inflation``; ``seed`` seeds its draws when ``reset`` gets none.
    """

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
        if reward not in REWARDS:
            raise ValueError(f"unknown reward {reward!r}; choose one of {', '.join(REWARDS)}")
        config = FilterConfig(filter=filter, initial=initial, P0=P0, Q=Q, n_members=n_members,
                              inflation=inflation, on_divergence=on_divergence)
        self.model = resolve_model(model, base.benchmark.name, r=r, preset=model_preset, T=T, device=device,
                                   train_if_missing=train_if_missing, dataset=base.dataset)
        self.assimilator = LatentAssimilator(self.model, config, device=device, dtype=dtype)
        self.filter_kind = filter
        self.reward_kind = reward
        self.seed = seed
        big = np.finfo(np.float32).max
        self.observation_space = spaces.Box(-big, big, shape=(2 * self.model.r,), dtype=np.float32)
        self.estimate: np.ndarray | None = None

    @property
    def filter(self):
        """The running filter (an EKF or EnKF object, with ``.mean``, ``.cov``, ``.diagnostics``)."""
        return self.assimilator.filter

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        _, info = self.env.reset(seed=seed, options=options)
        self.assimilator.start([self.env.unwrapped], seed=self.seed if seed is None else seed)
        return self.assimilator.belief()[0], self._with_estimate(info)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        obs, _, terminated, truncated, info = self.env.step(action)
        self.assimilator.step(obs[None], info["sensors"][None])
        info = self._with_estimate(info)
        info.update({k: float(v[0]) for k, v in self.assimilator.step_diagnostics().items()})
        reward = -(info["mse"] if self.reward_kind == "mse" else info["normalized_mse"])
        return self.assimilator.belief()[0], reward, terminated, truncated, info

    def _with_estimate(self, info: dict[str, Any]) -> dict[str, Any]:
        estimate = self.assimilator.estimate()
        mse, nmse = self.assimilator.errors(estimate, [self.env.unwrapped])
        self.estimate = estimate[0].cpu().numpy().astype(np.float32)
        info = dict(info)
        info.update(estimate=self.estimate, mse=float(mse[0]), normalized_mse=float(nmse[0]),
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
