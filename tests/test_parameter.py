"""Joint state and parameter estimation (FilterConfig(parameter="estimate"), dks_gym.filters.parameter):
against filterpy's EKF on a hand-built augmented linear system, convergence where the parameter is
identifiable, the hidden-parameter env, pDMD's differentiable operator, and the refusals of bad input."""

from __future__ import annotations

import math
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from filterpy.kalman import ExtendedKalmanFilter
from gymnasium.utils.env_checker import check_env

import dks_gym  # noqa: F401  (registers the env ids)
from dks_gym.assimilation import FilterConfig
from dks_gym.filters import EKF, EnKF, augmented_covariance
from dks_gym.filters.parameter import ParameterCoordinate, augment_with_parameter

F64 = torch.float64


def _linear_system(seed: int = 0, n: int = 60) -> dict:
    """z_{k+1} = A z_k + b mu, y_k = H z_k + c mu + v_k with an unknown constant mu = 1.3 (range [0.5, 2]:
    estimated as mu itself, the range spanning less than a decade)."""
    rng = np.random.default_rng(seed)
    A = np.array([[0.9, 0.2], [-0.1, 0.8]])
    b, H, c = np.array([0.3, -0.2]), np.array([[1.0, 0.0], [0.5, 1.0]]), np.array([0.4, 0.1])
    mu, R, Q = 1.3, 0.05 ** 2, 1e-4
    z, ys = np.zeros(2), []
    for _ in range(n):
        z = A @ z + b * mu + rng.normal(0, math.sqrt(Q), 2)
        ys.append(H @ z + c * mu + rng.normal(0, math.sqrt(R), 2))
    return dict(A=A, b=b, H=H, c=c, mu=mu, R=R, Q=Q, ys=np.array(ys))


def _augmented_ekf(sys: dict) -> tuple[EKF, ParameterCoordinate]:
    A, b, H, c = (torch.tensor(sys[k]) for k in ("A", "b", "H", "c"))
    coordinate = ParameterCoordinate.for_range(0.5, 2.0)
    assert not coordinate.log
    dyn = augment_with_parameter(lambda z, mu: z @ A.T + mu[:, None] * b, lambda z, mu: z @ H.T + mu[:, None] * c,
                                 coordinate)
    ekf = EKF(dyn, sigma=math.sqrt(sys["R"]), Q=augmented_covariance(sys["Q"], 2, 1, 0.0))
    return ekf, coordinate


def test_the_augmented_ekf_equals_filterpy_on_the_hand_built_augmented_system() -> None:
    """Autodiff through the augmented maps gives filterpy's EKF on [[A, b], [0, 1]] and [H, c], step by step."""
    sys = _linear_system()
    ekf, coordinate = _augmented_ekf(sys)
    mean, std = coordinate.prior()  # uniform over [0.5, 2]: mean 1.25, std 1.5 / sqrt(12)
    assert (mean, std) == pytest.approx((1.25, 1.5 / math.sqrt(12)))
    x0, P0 = np.array([0.0, 0.0, mean]), np.diag([1.0, 1.0, std ** 2])
    ekf.reset(torch.tensor(x0)[None], torch.tensor(P0)[None])
    ref = ExtendedKalmanFilter(dim_x=3, dim_z=2)
    ref.x, ref.P, ref.R = x0.copy(), P0.copy(), sys["R"] * np.eye(2)
    ref.F = np.block([[sys["A"], sys["b"][:, None]], [np.zeros((1, 2)), np.ones((1, 1))]])
    ref.Q = np.diag([sys["Q"], sys["Q"], 0.0])
    H_aug = np.hstack([sys["H"], sys["c"][:, None]])
    for k, y in enumerate(sys["ys"]):
        ref.predict()
        ref.update(y, HJacobian=lambda x: H_aug, Hx=lambda x: H_aug @ x)
        ekf.step(torch.tensor(y)[None])
        np.testing.assert_allclose(ekf.mean[0].numpy(), ref.x, rtol=0, atol=1e-10, err_msg=f"mean at step {k}")
        np.testing.assert_allclose(ekf.cov[0].numpy(), ref.P, rtol=0, atol=1e-10, err_msg=f"cov at step {k}")


@pytest.mark.parametrize("kind", ["ekf", "enkf"])
def test_an_identifiable_parameter_converges_to_the_truth_inside_its_interval(kind: str) -> None:
    """With mu observable through the steady state (c != 0, b != 0), 60 noisy readings pin it to 2 % with the
    truth inside the central 95 % interval; the EnKF's members carry mu."""
    sys = _linear_system(seed=3)
    ekf, coordinate = _augmented_ekf(sys)
    mean, std = coordinate.prior()
    x0 = torch.tensor([[0.0, 0.0, mean]], dtype=F64)
    P0 = torch.diag(torch.tensor([1.0, 1.0, std ** 2], dtype=F64))[None]
    filt = ekf if kind == "ekf" else EnKF(ekf.dynamics, sigma=math.sqrt(sys["R"]), n_members=200,
                                          Q=augmented_covariance(sys["Q"], 2, 1, 0.0), generator=0)
    filt.reset(x0, P0)
    for y in sys["ys"]:
        filt.step(torch.tensor(y)[None])
    estimate, sd = filt.mean[0, -1].item(), filt.cov[0, -1, -1].sqrt().item()
    assert abs(estimate - sys["mu"]) < 0.02 * sys["mu"]
    assert abs(estimate - sys["mu"]) < 1.96 * sd < std  # inside its interval, which shrank from the prior's


def test_the_coordinate_is_log_where_the_range_spans_a_decade_and_moment_matches_a_given_prior() -> None:
    coordinate = ParameterCoordinate.for_range(0.01, 1.0)  # Burgers' nu
    assert coordinate.log
    mean, std = coordinate.prior()
    assert mean == pytest.approx(0.5 * (math.log(0.01) + math.log(1.0)))
    s_mean, s_std = coordinate.prior(0.3, 0.06)  # a log-normal with mean 0.3 and std 0.06
    draws = np.exp(np.random.default_rng(0).normal(s_mean, s_std, 400_000))
    assert draws.mean() == pytest.approx(0.3, rel=2e-3) and draws.std() == pytest.approx(0.06, rel=5e-3)
    assert bool(coordinate.outside(torch.tensor([math.log(1.2)])).item())
    assert not bool(coordinate.outside(torch.tensor([math.log(0.5)])).item())


@pytest.mark.parametrize("kwargs, match", [
    (dict(parameter="estimate", parameter_prior=(0.3, 0.0)), "std must be > 0"),
    (dict(parameter="estimate", parameter_prior=(0.3, -1.0)), "std must be > 0"),
    (dict(parameter="estimate", parameter_prior=(float("nan"), 0.1)), "two finite numbers"),
    (dict(parameter="estimate", parameter_prior=(0.3,)), "two finite numbers"),
    (dict(parameter_prior=(0.3, 0.1)), "set parameter='estimate'"),
    (dict(parameter="estimate", parameter_drift=-0.1), "parameter_drift must be"),
    (dict(parameter_drift=0.1), "parameter='estimate'"),
    (dict(parameter="guess"), "parameter must be"),
    (dict(parameter=float("inf")), "finite number"),
])
def test_bad_parameter_settings_are_refused(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        FilterConfig(**kwargs)


def test_a_prior_mean_outside_the_training_range_is_refused() -> None:
    config = FilterConfig(parameter="estimate", parameter_prior=(2.0, 0.1))
    with pytest.raises(ValueError, match=r"outside the training range \[0.01, 1\]"):
        config.parameter_state(0.01, 1.0)


def test_the_hidden_parameter_env_leaves_mu_out_of_info_and_passes_check_env(burgers_small: Path) -> None:
    env = gym.make("DKS/Burgers-v0", preset="small", parameter="hidden")
    check_env(env.unwrapped)
    _, info = env.reset(seed=0)
    assert "mu" not in info and math.isfinite(env.unwrapped.mu)  # kept for scoring
    _, _, _, _, info = env.step(0)
    assert "mu" not in info
    _, known = gym.make("DKS/Burgers-v0", preset="small").reset(seed=0)
    assert known["mu"] == env.unwrapped.mu
    with pytest.raises(ValueError, match="'known'.*'hidden'"):
        gym.make("DKS/Burgers-v0", preset="small", parameter="secret")


def test_a_filter_on_a_hidden_parameter_env_must_estimate_or_assume_it(burgers_paper: Path) -> None:
    """Told nothing, the wrapper says what to do; estimating, it puts mu's estimate and its scores in info."""
    from dks_gym.wrappers import LatentFilter

    env = gym.make("DKS/Burgers-v0", parameter="hidden")
    with pytest.raises(ValueError, match="parameter='estimate'"):
        LatentFilter(env, model="mlp").reset(seed=0)
    wrapped = LatentFilter(gym.make("DKS/Burgers-v0", parameter="hidden"), model="mlp",
                           config=FilterConfig(parameter="estimate"))
    _, info = wrapped.reset(seed=0, options={"trajectory": 3})
    for _ in range(20):
        _, _, _, _, info = wrapped.step(0)
    assert "mu" not in info
    assert 0.01 <= info["mu_estimate"] <= 1.0 and info["mu_std"] > 0
    assert info["mu_relative_error"] == pytest.approx(abs(info["mu_estimate"] - wrapped.unwrapped.mu)
                                                      / wrapped.unwrapped.mu)
    assert isinstance(info["mu_in_interval"], bool) and isinstance(info["mu_out_of_range"], bool)


def test_a_latency_that_leaves_no_reading_is_refused(burgers_small: Path) -> None:
    n = gym.make("DKS/Burgers-v0", preset="small").unwrapped.dataset.n_frames
    gym.make("DKS/Burgers-v0", preset="small", faults={"latency": n - 2})  # one reading arrives: accepted
    with pytest.raises(ValueError, match=f"latency of at most {n - 2}"):
        gym.make("DKS/Burgers-v0", preset="small", faults={"latency": n - 1})
    with pytest.raises(ValueError, match="without a reading"):
        gym.make("DKS/Burgers-v0", preset="small", faults={"latency": 150})


def test_pdmd_operator_is_differentiable_and_equals_the_pydmd_one(burgers_paper: Path) -> None:
    """The torch operator A~(mu) equals PyDMD's RBF interpolation and the Tikhonov fit (to the round-off of the
    RBF's ill-conditioned solve), and its derivative in mu equals a central difference of it."""
    from dks_gym.dataset import Dataset
    from dks_gym.models import load_model

    model = load_model("burgers", "pdmd", dataset=Dataset(burgers_paper), progress=False)
    mu = torch.tensor([0.0437, 0.3, 0.77, 0.95], dtype=F64)
    reference = model.online_operator(mu)
    assert (model.differentiable_operator(mu) - reference).abs().max() < 1e-5 * reference.abs().max()
    x = mu.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(model.differentiable_operator(x).sum(), x)
    h = 1e-4
    central = (model.differentiable_operator(mu + h).sum((1, 2)) - model.differentiable_operator(mu - h).sum((1, 2)))
    np.testing.assert_allclose(grad.numpy(), (central / (2 * h)).numpy(), rtol=1e-3)  # O(h^2) truncation


def test_the_estimated_parameter_works_with_bias_estimation_missing_readings_and_the_vector_env(
        burgers_paper: Path) -> None:
    """[z; s; b]: with sensor biases estimated on top and a quarter of the readings dropped, the filter runs,
    keeps mu's estimate in the training range's neighbourhood and returns the biases; the vector env on
    hidden-parameter envs gives the same per-element keys as arrays."""
    from dks_gym.wrappers import LatentFilter

    config = FilterConfig(parameter="estimate", bias_drift=0.0)
    env = LatentFilter(gym.make("DKS/Burgers-v0", parameter="hidden", faults={"dropout": 0.25}), model="mlp",
                       config=config)
    _, info = env.reset(seed=1, options={"trajectory": 5})
    for _ in range(15):
        _, _, _, _, info = env.step(0)
    assert not info["mask"].all()  # readings were missing
    assert env.assimilation.bias().shape == (1, 16) and np.isfinite(env.assimilation.bias()).all()
    assert 0.005 < info["mu_estimate"] < 2.0 and np.isfinite(info["mse"])
    venv = gym.make_vec("DKS/Burgers-v0", num_envs=3, vectorization_mode="vector_entry_point", model="mlp",
                        config=FilterConfig(parameter="estimate"), parameter="hidden")
    _, infos = venv.reset(seed=0)
    _, _, _, _, infos = venv.step(np.zeros(3, dtype=np.int64))
    assert "mu" not in infos and infos["mu_estimate"].shape == (3,) and infos["mu_in_interval"].dtype == bool
