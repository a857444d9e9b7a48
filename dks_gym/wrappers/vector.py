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

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from ..envs.sensing import SensingEnv
from .assimilator import REWARDS, FilterConfig, LatentAssimilator, resolve_model


class LatentFilterVectorEnv(VectorEnv):
    """``num_envs`` SensingEnvs of one benchmark assimilated by one batched EKF/EnKF (or forward run).

    Filter arguments are those of :class:`~dks_gym.wrappers.LatentFilter`; every other keyword goes to
    each :class:`~dks_gym.envs.SensingEnv` (``preset``, ``sensor_mode``, ``noise_level`` ...).
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(
        self,
        benchmark: str,
        num_envs: int = 1,
        *,
        model: Any = "koopman",
        filter: str = "ekf",
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
        **env_kwargs: Any,
    ) -> None:
        if not (isinstance(num_envs, int) and num_envs >= 1):
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        if reward not in REWARDS:
            raise ValueError(f"unknown reward {reward!r}; choose one of {', '.join(REWARDS)}")
        config = FilterConfig(filter=filter, initial=initial, P0=P0, Q=Q, n_members=n_members,
                              inflation=inflation, on_divergence=on_divergence)
        self.envs = [SensingEnv(benchmark, **env_kwargs) for _ in range(num_envs)]
        self.benchmark = self.envs[0].benchmark
        self.model = resolve_model(model, self.benchmark.name, r=r, preset=model_preset, T=T, device=device,
                                   train_if_missing=train_if_missing, dataset=self.envs[0].dataset)
        self.assimilator = LatentAssimilator(self.model, config, device=device, dtype=dtype)
        self.num_envs = num_envs
        self.reward_kind = reward
        self.seed_ = seed
        big = np.finfo(np.float32).max
        self.single_observation_space = spaces.Box(-big, big, shape=(2 * self.model.r,), dtype=np.float32)
        self.single_action_space = self.envs[0].action_space
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.render_mode = None

    @property
    def filter(self):
        """The running batched filter."""
        return self.assimilator.filter

    def reset(self, *, seed: int | list[int] | None = None, options: dict[str, Any] | None = None):
        if seed is None or isinstance(seed, int):
            seeds = [None if seed is None else seed + i for i in range(self.num_envs)]
        else:
            if len(seed) != self.num_envs:
                raise ValueError(f"got {len(seed)} seeds for {self.num_envs} environments")
            seeds = list(seed)
        results = [e.reset(seed=s, options=options) for e, s in zip(self.envs, seeds)]
        self.assimilator.start(self.envs, seed=self.seed_ if seeds[0] is None else seeds[0])
        return self.assimilator.belief(), self._infos([info for _, info in results])

    def step(self, actions: Any):
        if self.assimilator.filter is None:
            raise RuntimeError("call reset() before step()")
        actions = list(actions) if self.envs[0].sensor_mode == "select" else [None] * self.num_envs
        results = [e.step(a) for e, a in zip(self.envs, actions)]
        self.assimilator.step(np.stack([r[0] for r in results]), np.stack([r[4]["sensors"] for r in results]))
        infos = self._infos([r[4] for r in results])
        infos.update(self.assimilator.step_diagnostics())
        rewards = -(infos["mse"] if self.reward_kind == "mse" else infos["normalized_mse"]).astype(np.float64)
        terminated = np.array([r[2] for r in results])
        truncated = np.array([r[3] for r in results])
        obs = self.assimilator.belief()
        if np.any(terminated | truncated):
            # Episodes of one dataset have equal length, so they all end here; restart the whole batch.
            infos["final_obs"], infos["final_info"] = obs, dict(infos)
            infos["_final_obs"] = np.ones(self.num_envs, dtype=bool)
            infos["_final_info"] = np.ones(self.num_envs, dtype=bool)
            for e in self.envs:
                e.reset()
            self.assimilator.start(self.envs, seed=int(self.envs[0].noise_seed % (2**31)))
            obs = self.assimilator.belief()
        return obs, rewards, terminated, truncated, infos

    def _infos(self, env_infos: list[dict[str, Any]]) -> dict[str, Any]:
        infos: dict[str, Any] = {
            key: np.array([info[key] for info in env_infos])
            for key in ("mu", "time_index", "trajectory", "sigma", "sensors")
        }
        estimate = self.assimilator.estimate()
        infos["mse"], infos["normalized_mse"] = self.assimilator.errors(estimate, self.envs)
        infos["estimate"] = estimate.cpu().numpy().astype(np.float32)
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
    """Adapt a :class:`LatentFilterVectorEnv` to stable-baselines3's ``VecEnv`` API (dones, list of infos)."""
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
                info = {"mse": float(infos["mse"][i]), "mu": float(infos["mu"][i])}
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


def register_vector_entry_points() -> None:
    """Let ``gymnasium.make_vec(id, vectorization_mode="vector_entry_point")`` build a LatentFilterVectorEnv."""
    from ..benchmarks import BENCHMARKS

    for bench in BENCHMARKS.values():
        gym.spec(bench.env_id).vector_entry_point = "dks_gym.wrappers.vector:LatentFilterVectorEnv"
