"""N sensing environments under one batched latent filter: a Gymnasium VectorEnv and a stable-baselines3 VecEnv.

``LatentFilterVectorEnv`` steps N ``SensingEnv`` copies and advances all N filter states with a single
batched filter call (one forecast, one update, one decode for the whole batch), rather than N filters.
Every episode of a dataset has the same length, so the N episodes end together and the whole batch is
reset in the same step (``AutoresetMode.SAME_STEP``: the returned observation is the first one of the
new episodes; the last one is in ``infos["final_obs"]``).

``make_vec("DKS/Burgers-v0", num_envs=N, vectorization_mode="vector_entry_point", model=..., filter=...)``
builds one; :class:`SB3VecEnv` adapts it to stable-baselines3's ``VecEnv`` interface.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from ..assimilation import FilterConfig, ModelLike, Snapshot
from ..envs.sensing import SensingEnv
from .building import Uncertainty, belief_space, build_assimilation, refuses_moved_keywords


class LatentFilterVectorEnv(VectorEnv):
    """``num_envs`` SensingEnvs of one benchmark assimilated by one batched EKF/EnKF (or forward run).

    ``model`` (a kind name, a :class:`~dks_gym.models.ModelSpec` or a model object), ``filter``, ``config``,
    ``reward`` and ``uncertainty`` are those of :class:`~dks_gym.wrappers.LatentFilter`; every other keyword
    goes to each :class:`~dks_gym.envs.SensingEnv` (``preset``, ``sensor_mode``, ``noise_level`` ...).
    ``uncertainty`` (default True) puts ``estimate_std`` (N, C, *grid) and the scores ``coverage``, ``nees``,
    ``crps``, ``spread_skill`` (N,) in the infos; ``uncertainty=False`` skips their cost (RL training).
    The infos hold the single env's keys batched: ``mse``, ``normalized_mse``, ``relative_l2``, ``score`` (N,),
    ``estimate`` (N, C, *grid) and ``relative_l2_channels`` ``{scored channel: (N,)}``.
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP}

    @refuses_moved_keywords
    def __init__(
        self,
        benchmark: str,
        num_envs: int = 1,
        *,
        model: ModelLike = "koopman",
        filter: str | None = None,
        config: FilterConfig | None = None,
        reward: str = "mse",
        uncertainty: bool | Uncertainty = True,
        **env_kwargs: Any,
    ) -> None:
        if not (isinstance(num_envs, int) and num_envs >= 1):
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        self.envs = [SensingEnv(benchmark, **env_kwargs) for _ in range(num_envs)]
        self.benchmark = self.envs[0].benchmark
        self.assimilation = build_assimilation(self.envs[0], model, filter, config, reward=reward,
                                               uncertainty=uncertainty)
        self.model = self.assimilation.model
        self.config = self.assimilation.config
        self.num_envs = num_envs
        self.reward_kind = reward
        self.single_observation_space = belief_space(self.model.r)
        self.single_action_space = self.envs[0].action_space
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.render_mode = None
        self._started = False

    @property
    def filter(self):
        """The running batched filter."""
        return self.assimilation.filter

    def reset(self, *, seed: int | list[int] | None = None, options: dict[str, Any] | None = None):
        if seed is None or isinstance(seed, int):
            seeds = [None if seed is None else seed + i for i in range(self.num_envs)]
        else:
            if len(seed) != self.num_envs:
                raise ValueError(f"got {len(seed)} seeds for {self.num_envs} environments")
            seeds = list(seed)
        results = [e.reset(seed=s, options=options) for e, s in zip(self.envs, seeds)]
        snap = self.assimilation.start(self.envs, seed=self.config.seed if seeds[0] is None else seeds[0])
        self._started = True
        return self.assimilation.belief(), self._infos([info for _, info in results], snap)

    def step(self, actions: Any):
        if not self._started:
            raise RuntimeError("call reset() before step()")
        actions = list(actions) if self.envs[0].sensor_mode == "select" else [None] * self.num_envs
        results = [e.step(a) for e, a in zip(self.envs, actions)]
        snap = self.assimilation.step(self.envs, np.stack([r[0] for r in results]),
                                      np.stack([r[4]["sensors"] for r in results]))
        infos = self._infos([r[4] for r in results], snap)
        infos.update(snap.diagnostics)
        rewards = -(infos["mse"] if self.reward_kind == "mse" else infos["normalized_mse"]).astype(np.float64)
        terminated = np.array([r[2] for r in results])
        truncated = np.array([r[3] for r in results])
        obs = self.assimilation.belief()
        if np.any(terminated | truncated):
            # Episodes of one dataset have equal length, so they all end here; restart the whole batch.
            infos["final_obs"], infos["final_info"] = obs, dict(infos)
            infos["_final_obs"] = np.ones(self.num_envs, dtype=bool)
            infos["_final_info"] = np.ones(self.num_envs, dtype=bool)
            for e in self.envs:
                e.reset()
            self.assimilation.start(self.envs, seed=int(self.envs[0].noise_seed % (2**31)))
            obs = self.assimilation.belief()
        return obs, rewards, terminated, truncated, infos

    def _infos(self, env_infos: list[dict[str, Any]], snap: Snapshot) -> dict[str, Any]:
        infos: dict[str, Any] = {
            key: np.array([info[key] for info in env_infos])
            for key in ("mu", "time_index", "trajectory", "sigma", "sensors", "mask")
            if key in env_infos[0]  # mu is not there on envs that hide it
        }
        infos["mse"], infos["normalized_mse"] = snap.mse, snap.normalized_mse
        infos["relative_l2"], infos["score"] = snap.relative_l2, snap.score
        infos["relative_l2_channels"] = dict(zip(self.benchmark.scored_channels, snap.channel_relative_l2.T))
        infos["estimate"] = snap.estimate.cpu().numpy().astype(np.float32)
        if snap.estimate_std is not None:
            infos["estimate_std"] = snap.estimate_std.cpu().numpy().astype(np.float32)
            infos["coverage"], infos["nees"], infos["crps"] = snap.coverage, snap.nees, snap.crps
            infos["spread_skill"] = snap.spread_skill
        infos.update(snap.parameter or {})
        return infos

    def close_extras(self, **kwargs: Any) -> None:
        for e in self.envs:
            e.close()


def _sb3_base():
    try:
        from stable_baselines3.common.vec_env.base_vec_env import VecEnv
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ImportError("SB3VecEnv needs stable-baselines3: pip install 'dks-gym[agents]'") from exc
    return VecEnv


def SB3VecEnv(venv: LatentFilterVectorEnv):  # noqa: N802 - a class factory, so SB3 stays an optional import
    """Adapt a :class:`LatentFilterVectorEnv` to stable-baselines3's ``VecEnv`` API (dones, list of infos: per
    env ``mse``, ``mu``, ``relative_l2``, ``score``, ``relative_l2_channels`` as the single env has them)."""
    base = _sb3_base()

    class _SB3VecEnv(base):
        def __init__(self, venv: LatentFilterVectorEnv) -> None:
            self.venv = venv
            super().__init__(venv.num_envs, venv.single_observation_space, venv.single_action_space)
            self._actions = None

        def reset(self) -> np.ndarray:
            seeds = [s for s in self._seeds] if any(s is not None for s in self._seeds) else None
            obs, _ = self.venv.reset(seed=seeds)
            self._reset_seeds()
            return obs

        def step_async(self, actions: np.ndarray) -> None:
            self._actions = actions

        def step_wait(self):
            obs, rewards, terminated, truncated, infos = self.venv.step(self._actions)
            dones = terminated | truncated
            out = []
            for i in range(self.num_envs):
                info = {name: float(infos[name][i]) for name in ("mse", "mu", "relative_l2", "score")}
                info["relative_l2_channels"] = {c: float(v[i]) for c, v in infos["relative_l2_channels"].items()}
                if dones[i]:
                    info["terminal_observation"] = infos["final_obs"][i]
                    info["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
                out.append(info)
            return obs, rewards.astype(np.float32), dones, out

        def close(self) -> None:
            self.venv.close()

        def get_attr(self, attr_name: str, indices=None) -> list:
            return [getattr(e, attr_name) for e in self._envs(indices)]

        def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
            for e in self._envs(indices):
                setattr(e, attr_name, value)

        def env_method(self, method_name: str, *args: Any, indices=None, **kwargs: Any) -> list:
            return [getattr(e, method_name)(*args, **kwargs) for e in self._envs(indices)]

        def env_is_wrapped(self, wrapper_class: type, indices=None) -> list[bool]:
            return [False for _ in self._envs(indices)]

        def _envs(self, indices) -> list[SensingEnv]:
            return [self.venv.envs[i] for i in self._get_indices(indices)]

    return _SB3VecEnv(venv)

