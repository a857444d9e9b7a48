"""The TorchRL adapter of the batched vector env (dks_gym.wrappers.torchrl_env): its specs pass torchrl's
check_env_specs, its rewards are the vector env's own, and without torchrl it says which extra to install."""

from __future__ import annotations

import multiprocessing
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from gymnasium import spaces

from dks_gym.dataset import Dataset
from dks_gym.models import build_model
from dks_gym.models.calibration import calibrate
from dks_gym.wrappers import LatentFilterVectorEnv

#: A select-mode layout: 32 candidate cells of the 1024 of the Burgers grid.
CANDIDATES = np.arange(0, 1024, 32)


@pytest.fixture(scope="module", autouse=True)
def start_method():
    """Importing torchrl sets the global multiprocessing start method to spawn where none is set; the test files
    that run after this one in the same worker get it back as it was."""
    before = multiprocessing.get_start_method(allow_none=True)
    yield
    if multiprocessing.get_start_method(allow_none=True) != before:
        multiprocessing.set_start_method(before, force=True)


@pytest.fixture(scope="module")
def model(burgers_small: Path):
    """An untrained lite Koopman model with its calibration (the adapter's plumbing does not need training)."""
    ds = Dataset(burgers_small)
    out = build_model("burgers", "koopman", r=8, preset="lite", dataset=ds, seed=0)
    out.calibration = calibrate(out, ds, [0, 1])
    return out


def _venv(model, mode: str, num_envs: int = 3) -> LatentFilterVectorEnv:
    select = {"sensor_mode": "select", "candidates": CANDIDATES} if mode == "select" else {}
    return LatentFilterVectorEnv("burgers", num_envs, model=model, filter="ekf", uncertainty=False, preset="small",
                                 **select)


@pytest.mark.parametrize("mode", ["fixed", "select"])
def test_check_env_specs(model, mode: str) -> None:
    pytest.importorskip("torchrl")
    from torchrl.data import Categorical, MultiCategorical
    from torchrl.envs.utils import check_env_specs

    from dks_gym.wrappers import TorchRLEnv

    env = TorchRLEnv(_venv(model, mode))
    assert env.batch_size == torch.Size([3])
    assert env.observation_spec["observation"].shape == (3, 16)
    assert env.observation_spec["observation"].dtype == torch.float32
    assert isinstance(env.action_spec, MultiCategorical if mode == "select" else Categorical)
    assert env.action_spec.shape == ((3, 16) if mode == "select" else (3,))
    check_env_specs(env, seed=0)
    check_env_specs(env, seed=0, break_when_any_done="both")
    env.close()


def test_rewards_are_the_vector_envs_own_across_an_episode_end(model) -> None:
    """Random select-mode actions through TorchRL's step_and_maybe_reset give, step by step, the rewards the
    vector env itself gives for the same seed and actions; the step that ends the episodes returns their last
    belief (done) and the reset after it the first belief of the episodes the vector env restarted."""
    pytest.importorskip("torchrl")
    from dks_gym.wrappers import TorchRLEnv

    env, venv = TorchRLEnv(_venv(model, "select")), _venv(model, "select")
    steps = venv.envs[0].dataset.n_frames + 4  # past the end of the first episodes
    actions = np.random.default_rng(0).integers(0, len(CANDIDATES), size=(steps, 3, 16))

    env.set_seed(7)
    td = env.reset()
    obs, _ = venv.reset(seed=7)
    np.testing.assert_array_equal(td["observation"].numpy(), obs)
    ends = []
    for k in range(steps):
        td["action"] = torch.as_tensor(actions[k])
        out, td = env.step_and_maybe_reset(td)
        obs, rewards, terminated, truncated, infos = venv.step(actions[k])
        np.testing.assert_array_equal(out["next", "reward"].squeeze(-1).numpy(), rewards.astype(np.float32))
        np.testing.assert_array_equal(out["next", "done"].squeeze(-1).numpy(), terminated | truncated)
        if "final_obs" in infos:
            ends.append(k)
            np.testing.assert_array_equal(out["next", "observation"].numpy(), infos["final_obs"])
        else:
            np.testing.assert_array_equal(out["next", "observation"].numpy(), obs)
        np.testing.assert_array_equal(td["observation"].numpy(), obs)
    assert ends == [venv.envs[0].dataset.n_frames - 2]


def test_a_partial_reset_is_refused(model) -> None:
    pytest.importorskip("torchrl")
    from tensordict import TensorDict

    from dks_gym.wrappers import TorchRLEnv

    env = TorchRLEnv(_venv(model, "fixed"))
    env.reset()
    with pytest.raises(ValueError, match="all of its envs or none"):
        env.reset(TensorDict({"_reset": torch.tensor([[True], [False], [False]])}, batch_size=[3]))


def test_action_specs_of_other_gymnasium_spaces() -> None:
    pytest.importorskip("torchrl")
    from torchrl.data import Binary, Bounded

    from dks_gym.wrappers.torchrl_env import action_spec

    box = action_spec(spaces.Box(-1.0, 2.0, shape=(4,), dtype=np.float32), 2)
    assert isinstance(box, Bounded) and box.shape == (2, 4) and box.dtype == torch.float32
    assert float(box.space.low.min()) == -1.0 and float(box.space.high.max()) == 2.0
    assert isinstance(action_spec(spaces.MultiBinary(5), 2), Binary)
    with pytest.raises(ValueError, match="starting at"):
        action_spec(spaces.Discrete(3, start=1), 2)
    with pytest.raises(TypeError, match="no TorchRL spec"):
        action_spec(spaces.Tuple([spaces.Discrete(2)]), 2)


def test_without_torchrl_the_adapter_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    """With torchrl unimportable (its modules masked), asking for TorchRLEnv raises an ImportError naming the
    extra; dks_gym.wrappers itself still imports."""
    for name in [n for n in sys.modules if n == "torchrl" or n.startswith("torchrl.")] or ["torchrl"]:
        monkeypatch.setitem(sys.modules, name, None)
    monkeypatch.delitem(sys.modules, "dks_gym.wrappers.torchrl_env", raising=False)
    import dks_gym.wrappers

    with pytest.raises(ImportError, match=r'pip install "dks-gym\[torchrl\]"'):
        dks_gym.wrappers.TorchRLEnv
    with pytest.raises(ImportError, match=r'pip install "dks-gym\[torchrl\]"'):
        from dks_gym.wrappers.torchrl_env import TorchRLEnv  # noqa: F401


def test_importing_the_wrappers_does_not_import_torchrl() -> None:
    code = "import sys, dks_gym.wrappers; print('torchrl' in sys.modules, 'tensordict' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"]
