"""Torch threads per task (dks_gym.threads): the override order, restoring, the heavy calls using it, and the same
bits on one thread and two (MKL's strict mode)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import gymnasium as gym
import pytest
import torch

from dks_gym import threads
from dks_gym.threads import set_threads, threads_for, torch_threads


@pytest.fixture
def clean_threads(monkeypatch: pytest.MonkeyPatch):
    """No thread variables in the environment, no override; torch at 2 threads outside the calls."""
    for var in threads.ENV_VARS:
        monkeypatch.delenv(var, raising=False)
    previous = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    set_threads(None)
    torch.set_num_threads(previous)


def test_override_order(clean_threads, monkeypatch: pytest.MonkeyPatch) -> None:
    assert threads_for("train") == threads.TASK_THREADS["train"] == 1
    assert threads_for("simulate") is None
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert threads_for("train") == threads_for("simulate") == 3
    monkeypatch.setenv("DKS_GYM_THREADS", "4")
    assert threads_for("assimilate") == 4
    set_threads(5)
    assert threads_for("assimilate") == 5
    set_threads(None)
    assert threads_for("assimilate") == 4


@pytest.mark.parametrize("value", ["0", "two", "-1"])
def test_bad_thread_settings_are_refused(clean_threads, monkeypatch: pytest.MonkeyPatch, value: str) -> None:
    monkeypatch.setenv("DKS_GYM_THREADS", value)
    with pytest.raises(ValueError, match="DKS_GYM_THREADS"):
        threads_for("train")
    with pytest.raises(ValueError, match="positive integer"):
        set_threads(0)
    with pytest.raises(ValueError, match="unknown task"):
        threads_for("training")


def test_torch_threads_restores_the_callers_count(clean_threads) -> None:
    with torch_threads("train"):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == 2
    with pytest.raises(RuntimeError), torch_threads("assimilate"):
        raise RuntimeError("boom")
    assert torch.get_num_threads() == 2
    with torch_threads("simulate"):  # None: torch's own count
        assert torch.get_num_threads() == 2


def test_filter_and_training_run_on_the_chosen_threads(clean_threads, burgers_small: Path, tmp_path: Path) -> None:
    from dks_gym import FilterConfig, LatentFilter
    from dks_gym.dataset import load_dataset
    from dks_gym.models import build_model
    from dks_gym.models import train_model, training_schedule

    ds = load_dataset("burgers", "small", burgers_small)
    model = build_model("burgers", "mlp", 4, "lite", dataset=ds)
    seen: list[int] = []
    forecast = model.forecast
    model.forecast = lambda z, mu: (seen.append(torch.get_num_threads()), forecast(z, mu))[1]
    env = LatentFilter(gym.make("DKS/Burgers-v0", preset="small"), model=model, filter="ekf",
                       config=FilterConfig(Q="paper", P0="paper"))  # an untrained model has no calibration
    env.reset(seed=0)
    env.step(None)
    assert seen and set(seen) == {1}
    assert torch.get_num_threads() == 2
    set_threads(2)
    seen.clear()
    env.step(None)
    assert set(seen) == {2}
    set_threads(None)

    counts: list[int] = []
    train_model("burgers", "mlp", r=4, dataset=ds, schedule=training_schedule("burgers", "lite", steps=2, batch_size=2),
                path=tmp_path / "m.safetensors", progress=False,
                on_step=lambda step, terms: counts.append(torch.get_num_threads()))
    assert counts == [1, 1] and torch.get_num_threads() == 2


_SAME_BITS = """
import os
import dks_gym  # before the first product: it asks MKL for products independent of the thread count
import torch
from dks_gym.models import build_model
torch.manual_seed(0)
linear, x = torch.nn.Linear(64, 32), torch.randn(10, 64)  # 10 rows: a remainder row when split over 2 threads
xlstm = build_model("burgers", "xlstm", 32, "lite", seed=0)
z, mu = torch.randn(10, 32), torch.linspace(0.01, 1.0, 10)
outs = []
for n in (1, 2):
    torch.set_num_threads(n)
    with torch.no_grad():
        outs.append((linear(x), xlstm.rollout(z, mu, 30)))
same = all(torch.equal(a, b) for a, b in zip(*outs))
print(os.environ.get("MKL_CBWR") or "empty", int(same))
"""


def _same_bits(env: dict[str, str]) -> tuple[str, bool]:
    out = subprocess.run([sys.executable, "-c", _SAME_BITS], env=env, capture_output=True, text=True, check=True)
    mode, same = out.stdout.split()
    return mode, same == "1"


def test_products_and_a_rollout_give_the_same_bits_on_one_thread_and_two() -> None:
    env = {k: v for k, v in os.environ.items() if k != "MKL_CBWR"}
    mode, same = _same_bits(env)
    assert mode == ",".join(threads.BLAS_REPRODUCIBILITY[1:]) and same
    # A user's own setting is kept: an empty one is MKL's default mode, where the bits differ (on MKL)
    mode, same = _same_bits({**env, "MKL_CBWR": ""})
    assert mode == "empty"
    if same:
        pytest.skip("this BLAS gives the same bits on one thread and two even without MKL's strict mode")
