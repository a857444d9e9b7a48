"""The wrappers take a model: the FilterableModel Protocol, ModelSpec lookups and the refused old keywords."""

from __future__ import annotations

import inspect
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import dks_gym  # noqa: F401  (registers the env ids)
from dks_gym.assimilation import resolve_model, tuning
from dks_gym.dataset import Dataset
from dks_gym.models import FILTERABLE_MEMBERS, FilterableModel, ModelSpec, build_model, load_model
from dks_gym.wrappers import LatentFilter, LatentFilterVectorEnv, Uncertainty

KINDS = ("koopman", "pdmd", "mlp", "xlstm")


@pytest.mark.parametrize("kind", KINDS)
def test_every_model_class_is_a_filterable_model(kind: str) -> None:
    model = build_model("burgers", kind, r=4, preset="lite")
    assert isinstance(model, FilterableModel)
    for name in FILTERABLE_MEMBERS:
        assert hasattr(model, name), name
    for name in ("encode", "decode", "forecast", "filter_forecast_jacobian", "filter_observe_jacobian"):
        assert callable(getattr(model, name)), name


def test_the_protocol_lists_what_the_core_reads() -> None:
    assert set(FILTERABLE_MEMBERS) == {"benchmark", "kind", "r", "shape", "calibration", "encode", "decode",
                                       "forecast", "filter_forecast_jacobian", "filter_observe_jacobian"}


def test_an_object_without_the_members_is_refused_by_name() -> None:
    class Half:
        benchmark, kind, r = "burgers", "mine", 4

    assert not isinstance(Half(), FilterableModel)
    with pytest.raises(TypeError, match="FilterableModel.*Half lacks 'shape', 'calibration', 'encode'"):
        resolve_model(Half(), "burgers")


def test_the_wrappers_take_at_most_six_arguments_and_name_where_the_old_ones_went(burgers_small: Path) -> None:
    params = list(inspect.signature(LatentFilter.__init__).parameters)
    assert params == ["self", "env", "model", "filter", "config", "reward", "uncertainty"]
    env = gym.make("DKS/Burgers-v0", preset="small")
    for keyword, hint in (("r", r"ModelSpec\(kind, r="), ("model_preset", "preset="), ("T", "T="),
                          ("device", "device="), ("train_if_missing", "train_if_missing=True"),
                          ("dtype", r"\.double\(\)"), ("reconstruction_var", r"Uncertainty\(reconstruction_var")):
        with pytest.raises(TypeError, match=hint):
            LatentFilter(env, "koopman", **{keyword: 1})
        with pytest.raises(TypeError, match=hint):
            LatentFilterVectorEnv("burgers", 1, preset="small", **{keyword: 1})
    with pytest.raises(TypeError, match="uncertainty must be"):
        LatentFilter(env, build_model("burgers", "koopman", r=4, preset="lite"), uncertainty="yes")
    with pytest.raises(TypeError, match="config must be"):
        LatentFilter(env, build_model("burgers", "koopman", r=4, preset="lite"), config={"kind": "ekf"})


def test_a_spec_checks_its_fields() -> None:
    assert ModelSpec("koopman") == ModelSpec("koopman", r=32, preset="lite", T=1, device="cpu")
    with pytest.raises(ValueError, match="unknown model"):
        ModelSpec("transformer")
    with pytest.raises(ValueError, match="unknown model preset"):
        ModelSpec("koopman", preset="huge")
    with pytest.raises(ValueError, match="r must be a positive integer"):
        ModelSpec("koopman", r=0)


def test_a_spec_trains_a_missing_model_and_tunes_it_as_load_model_would(burgers_small: Path, tmp_path: Path,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("DKS_GYM_HOME", str(tmp_path))  # a model cache of its own
    monkeypatch.setattr(tuning, "BISECTIONS", 1)
    spec = ModelSpec("pdmd", r=4, train_if_missing=True)
    env = LatentFilter(gym.make("DKS/Burgers-v0", data_path=str(burgers_small)), spec, "ekf")
    assert env.model.r == 4 and "Q_scale" in env.model.calibration
    assert env.spec.additional_wrappers[-1].kwargs["model"] == spec  # RecordConstructorArgs keeps the spec
    cached = load_model("burgers", "pdmd", r=4, dataset=Dataset(burgers_small))
    assert cached.checkpoint_path == env.model.checkpoint_path and "Q_scale" in cached.calibration
    env.reset(seed=0)
    on = env.step(None)[4]
    env.close()
    again = LatentFilter(gym.make("DKS/Burgers-v0", data_path=str(burgers_small)), cached, "ekf",
                         uncertainty=Uncertainty(reconstruction_var=0.0))
    again.reset(seed=0)
    off = again.step(None)[4]
    assert off["mse"] == on["mse"] and np.all(off["estimate_std"] <= on["estimate_std"] + 1e-6)
    again.close()
