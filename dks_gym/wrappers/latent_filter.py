"""LatentFilter: a latent model inside an EKF or EnKF, wrapped around a SensingEnv (paper Section II.E).

The wrapper turns the raw sensor stream into a belief over the latent state z (dimension r) and a
reconstruction of the full field. Per step: the env advances one frame and reads the sensors; the
assimilation core forecasts z with the model (Eq. 13-14) and, unless ``filter="forward"``, updates it
with the readings (Eq. 15-17) through h(z) = S(decode(z)) at the sensors the env actually read (so
``sensor_mode="select"`` layouts are followed step by step).

* observation: ``[mean z (r); log diag P (r)]`` as float32, the filter's belief;
* ``info["estimate"]``: the decoded mean, ``(C, *grid)`` in physical units; ``info["mse"]``,
  ``info["normalized_mse"]``, ``gain_norm``, ``spread`` and (EKF) ``forecast_norm`` = ||F_k||_2;
* ``info["relative_l2"]``: ||estimate - truth|| / ||truth|| over the scored channels and every cell (those of
  the MSE, physical units; NaN where the truth is 0: :func:`~dks_gym.assimilation.relative_l2_errors`),
  ``info["score"]`` = 100 (1 - relative_l2) (the Common Task Framework's; negative beyond a relative error
  of 1), ``info["relative_l2_channels"]``: ``{scored channel: its relative L2 error}``;
* with ``uncertainty=True`` (default) ``info["estimate_std"]``, the predictive std of every cell
  (``(C, *grid)``, physical units: the filter's latent covariance pushed through the decoder, plus the
  decoder's reconstruction variance: ``Uncertainty(reconstruction_var=...)``, else the model's calibrated
  one), and its scores ``coverage`` (of the central 95 % interval), ``nees`` (mean per cell), ``crps`` and
  ``spread_skill`` (sqrt(mean std^2 / MSE): 1 when calibrated, :mod:`~dks_gym.assimilation.spread`) over the
  scored channels;
  wall time per DA step is in ``wrapper.filter.diagnostics`` (in info it would break determinism);
* with ``FilterConfig(parameter="estimate")`` (mu estimated with the state; needed on an env made with
  ``parameter="hidden"``): ``mu_estimate``, ``mu_std``, the central 95 % interval ``mu_low``, ``mu_high``,
  ``mu_out_of_range`` (the estimate left the training range: the model extrapolates), and its scores against
  the env's true mu, ``mu_relative_error`` and ``mu_in_interval``, and ``mu_std_ratio`` (the estimated
  coordinate's std over its prior's: near 1, the sensors have not identified mu);
* reward: minus the MSE over the scored channels against ``env.unwrapped.true_state`` (physical units),
  or over standardized channels with ``reward="normalized_mse"``.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from ..assimilation import FilterConfig, ModelLike, Snapshot
from ..envs.sensing import SensingEnv
from .building import Uncertainty, belief_space, build_assimilation, refuses_moved_keywords


class LatentFilter(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Assimilate a SensingEnv's readings into a latent model's state with an EKF, an EnKF or a forward run.

    ``model``: a model object (a :class:`~dks_gym.models.FilterableModel`, e.g. from
    :func:`~dks_gym.load_model`), a kind name ("koopman", "pdmd", "mlp", "xlstm": the user's cached or the
    shipped lite model with r = 32, T = 1, on the CPU, for the env's dataset; a missing one raises
    ``CheckpointMissing``) or a :class:`~dks_gym.models.ModelSpec` for any other lookup (``r``, ``preset``,
    ``T``, ``device``; ``train_if_missing=True`` trains a missing model and tunes its Q scale). The filter
    runs on the model's device and in its dtype.
    ``filter``: "ekf", "enkf" or "forward" (default: ``config.kind``, "ekf"). ``config``: a
    :class:`~dks_gym.FilterConfig` with everything else (initial condition, P0, Q, ensemble size, inflation,
    localization, divergence policy, seed); R = sigma^2 I comes from the env.
    ``uncertainty``: put ``estimate_std`` and its scores (``coverage``, ``nees``, ``crps``, ``spread_skill``) in
    ``info`` (default True; with the EKF it costs a few decodes per step, or one decode per EnKF member:
    False for speed); :class:`~dks_gym.wrappers.Uncertainty` ``(reconstruction_var=...)`` switches it on with
    the decoder's reconstruction-error variance per cell ``(C, *grid)`` of your choice
    (:func:`~dks_gym.assimilation.reconstruction_variance`; default the model's calibrated one).
    """

    @refuses_moved_keywords
    def __init__(
        self,
        env: gym.Env,
        model: ModelLike = "koopman",
        filter: str | None = None,
        *,
        config: FilterConfig | None = None,
        reward: str = "mse",
        uncertainty: bool | Uncertainty = True,
    ) -> None:
        gym.utils.RecordConstructorArgs.__init__(self, model=model, filter=filter, config=config, reward=reward,
                                                 uncertainty=uncertainty)
        super().__init__(env)
        base = env.unwrapped
        if not isinstance(base, SensingEnv):
            raise TypeError(f"LatentFilter wraps a dks_gym SensingEnv, got {type(base).__name__}")
        self.assimilation = build_assimilation(base, model, filter, config, reward=reward, uncertainty=uncertainty)
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
                    relative_l2=float(snap.relative_l2[0]), score=float(snap.score[0]),
                    relative_l2_channels=dict(zip(self.env.unwrapped.benchmark.scored_channels,
                                                  map(float, snap.channel_relative_l2[0]))),
                    latent_mean=snap.latent_mean[0])
        if snap.estimate_std is not None:
            self.estimate_std = snap.estimate_std[0].cpu().numpy().astype(np.float32)
            info.update(estimate_std=self.estimate_std, coverage=float(snap.coverage[0]), nees=float(snap.nees[0]),
                        crps=float(snap.crps[0]), spread_skill=float(snap.spread_skill[0]))
        for name, values in (snap.parameter or {}).items():
            info[name] = bool(values[0]) if values.dtype == bool else float(values[0])
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
