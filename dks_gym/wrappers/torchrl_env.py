"""The batched vector env as a TorchRL ``EnvBase`` (the optional ``torchrl`` extra).

:class:`TorchRLEnv` wraps a :class:`~dks_gym.wrappers.LatentFilterVectorEnv` of N envs as one TorchRL env of
batch size ``[N]``: ``observation`` is the belief (float32, 2r), ``action`` the env's action (a
``Categorical`` of one value in ``sensor_mode="fixed"``, a ``MultiCategorical`` of the candidate indices in
``"select"``), ``reward`` the vector env's reward as float32 ``(N, 1)``, and ``done``, ``terminated``,
``truncated`` booleans ``(N, 1)``.

The vector env restarts the whole batch in the step that ends its episodes (they all have the same length);
that step here returns the terminal belief with ``done`` set, and the reset that TorchRL then asks for
returns the first belief of the episodes the vector env already started. A reset of only some envs (a
partial ``_reset`` mask) is refused: one batched filter runs all N episodes in step.

This module imports torchrl when it is imported; ``dks_gym.wrappers`` imports it only when ``TorchRLEnv`` is
asked for, so torchrl stays optional.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from gymnasium import spaces

from .vector import LatentFilterVectorEnv

try:
    from tensordict import TensorDict, TensorDictBase
    from torchrl.data import Binary, Bounded, Categorical, Composite, MultiCategorical, TensorSpec, Unbounded
    from torchrl.envs import EnvBase
except ImportError as exc:  # pragma: no cover - depends on the install
    raise ImportError('TorchRLEnv needs torchrl: pip install "dks-gym[torchrl]"') from exc

DONE_KEYS = ("done", "terminated", "truncated")


def action_spec(space: spaces.Space, num_envs: int, device: torch.device | str | None = None) -> TensorSpec:
    """The TorchRL spec of ``num_envs`` stacked actions of the Gymnasium ``space`` (Discrete, MultiDiscrete,
    MultiBinary or Box; a Discrete or MultiDiscrete must start at 0, as TorchRL's categorical specs do)."""
    if isinstance(space, (spaces.Discrete, spaces.MultiDiscrete)) and np.any(space.start != 0):
        raise ValueError(f"a {type(space).__name__} space starting at {space.start} has no TorchRL spec")
    if isinstance(space, spaces.Discrete):
        return Categorical(int(space.n), shape=(num_envs,), dtype=torch.int64, device=device)
    if isinstance(space, spaces.MultiDiscrete):
        nvec = torch.as_tensor(space.nvec, dtype=torch.int64).expand(num_envs, *space.nvec.shape)
        return MultiCategorical(nvec.clone(), dtype=torch.int64, device=device)
    if isinstance(space, spaces.MultiBinary):
        return Binary(shape=(num_envs, *space.shape), dtype=torch.int8, device=device)
    if isinstance(space, spaces.Box):
        dtype = torch.from_numpy(np.zeros(0, dtype=space.dtype)).dtype
        low = torch.as_tensor(space.low, dtype=dtype).expand(num_envs, *space.shape)
        high = torch.as_tensor(space.high, dtype=dtype).expand(num_envs, *space.shape)
        return Bounded(low.clone(), high.clone(), shape=(num_envs, *space.shape), dtype=dtype, device=device)
    raise TypeError(f"no TorchRL spec for a {type(space).__name__} action space")


class TorchRLEnv(EnvBase):
    """A :class:`~dks_gym.wrappers.LatentFilterVectorEnv` as a TorchRL env of batch size ``[num_envs]``.

    ``device``: where the tensordicts live (default CPU; the filter runs on its model's device either way).
    ``set_seed(s)`` seeds the next reset: env i starts from seed ``s + i``, as ``venv.reset(seed=s)`` does.
    """

    def __init__(self, venv: LatentFilterVectorEnv, *, device: torch.device | str | None = None) -> None:
        super().__init__(device=device, batch_size=torch.Size([venv.num_envs]))
        self.venv = venv
        n = venv.num_envs
        self.observation_spec = Composite(
            observation=Unbounded(shape=(n, *venv.single_observation_space.shape), dtype=torch.float32,
                                  device=self.device),
            shape=(n,), device=self.device)
        self.action_spec = action_spec(venv.single_action_space, n, self.device)
        self.reward_spec = Unbounded(shape=(n, 1), dtype=torch.float32, device=self.device)
        self.done_spec = Composite(
            {key: Categorical(2, shape=(n, 1), dtype=torch.bool, device=self.device) for key in DONE_KEYS},
            shape=(n,), device=self.device)
        self._seed: int | None = None
        # The first belief of the episodes the vector env started in the step that ended the last ones.
        self._next_start: np.ndarray | None = None

    def _set_seed(self, seed: int | None) -> None:
        self._seed = seed

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        mask = None if tensordict is None else tensordict.get("_reset", None)
        if mask is not None and not mask.all():
            if mask.any():
                raise ValueError("TorchRLEnv resets all of its envs or none: one batched filter runs the N "
                                 "episodes in step (they all end together)")
            return self._output(self.venv.assimilation.belief())
        if self._next_start is not None and self._seed is None:
            belief = self._next_start
        else:
            belief, _ = self.venv.reset(seed=self._seed)
            self._seed = None
        self._next_start = None
        return self._output(belief)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action").detach().cpu().numpy()
        belief, rewards, terminated, truncated, infos = self.venv.step(action)
        self._next_start = None
        if "final_obs" in infos:
            self._next_start, belief = belief, infos["final_obs"]
        out = self._output(belief, terminated, truncated)
        out.set("reward", torch.as_tensor(rewards, dtype=torch.float32, device=self.device).unsqueeze(-1))
        return out

    def _output(self, belief: np.ndarray, terminated: np.ndarray | None = None,
                truncated: np.ndarray | None = None) -> TensorDictBase:
        """The tensordict of a belief and its done flags (all False when none are given: after a reset)."""
        n = self.venv.num_envs
        terminated = np.zeros(n, dtype=bool) if terminated is None else np.asarray(terminated, dtype=bool)
        truncated = np.zeros(n, dtype=bool) if truncated is None else np.asarray(truncated, dtype=bool)
        flags = {"terminated": terminated, "truncated": truncated, "done": terminated | truncated}
        out = {key: torch.as_tensor(value, device=self.device).reshape(n, 1) for key, value in flags.items()}
        out["observation"] = torch.as_tensor(np.asarray(belief, dtype=np.float32), device=self.device)
        return TensorDict(out, batch_size=self.batch_size, device=self.device)

    def close(self, *, raise_if_closed: bool = True) -> None:
        """Close the vector env and its SensingEnvs."""
        self.venv.close()
        super().close(raise_if_closed=raise_if_closed)
