"""Tests of the latent-space filters against independent references.

References: filterpy's KalmanFilter / ExtendedKalmanFilter (step by step), torch-kf's KalmanFilter (a second
batched PyTorch implementation, skipped where it is not installed), analytic Jacobians, separate
unbatched runs, the exact Kalman filter (EnKF Monte-Carlo convergence rate), the discrete algebraic
Riccati equation (scipy), and DAPPER's published Lorenz-63 EnKF score.
"""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest
import scipy.linalg
import torch
from filterpy.kalman import ExtendedKalmanFilter, KalmanFilter

from dks_gym.filters import (
    EKF,
    EnKF,
    FilterDivergence,
    GaussianState,
    LatentDynamics,
    bind_param,
    ekf_forecast,
    ekf_update,
    enkf_forecast,
    enkf_update,
    ensemble_state,
    initial_ensemble,
    schur_localization,
    value_and_jacobian,
)
from dks_gym.filters.batch_elements import nonfinite_elements

F64 = torch.float64


def random_spd(rng: np.random.Generator, d: int, scale: float = 1.0) -> np.ndarray:
    M = rng.standard_normal((d, d))
    return scale * (M @ M.T / d + 0.5 * np.eye(d))


def stable_matrix(rng: np.random.Generator, d: int, radius: float = 0.95) -> np.ndarray:
    A = rng.standard_normal((d, d))
    return radius * A / np.max(np.abs(np.linalg.eigvals(A)))


def linear_system(seed: int = 0, r: int = 4, m: int = 3, n_steps: int = 30) -> dict:
    """A random linear-Gaussian system, its simulated measurement stream and noise covariances."""
    rng = np.random.default_rng(seed)
    A, H = stable_matrix(rng, r), rng.standard_normal((m, r))
    Q, R, P0 = random_spd(rng, r, 0.05), random_spd(rng, m, 0.3), random_spd(rng, r)
    z0 = rng.standard_normal(r)
    x = z0 + np.linalg.cholesky(P0) @ rng.standard_normal(r)
    ys = []
    for _ in range(n_steps):
        x = A @ x + np.linalg.cholesky(Q) @ rng.standard_normal(r)
        ys.append(H @ x + np.linalg.cholesky(R) @ rng.standard_normal(m))
    return {"A": A, "H": H, "Q": Q, "R": R, "P0": P0, "z0": z0, "ys": np.array(ys)}


def linear_dynamics(A: np.ndarray, H: np.ndarray, *, constant_jacobians: bool) -> LatentDynamics:
    At, Ht = torch.tensor(A), torch.tensor(H)
    return LatentDynamics(
        forecast=lambda z: z @ At.T.to(z),
        observe=lambda z: z @ Ht.T.to(z),
        forecast_jacobian=At if constant_jacobians else None,
        observe_jacobian=Ht if constant_jacobians else None,
    )


def filterpy_kf(sys: dict) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    r, m = sys["A"].shape[0], sys["H"].shape[0]
    kf = KalmanFilter(dim_x=r, dim_z=m)
    kf.x, kf.P, kf.F, kf.H, kf.Q, kf.R = sys["z0"].copy(), sys["P0"].copy(), sys["A"], sys["H"], sys["Q"], sys["R"]
    out = []
    for y in sys["ys"]:
        kf.predict()
        kf.update(y)
        out.append((kf.x.copy(), kf.P.copy(), kf.K.copy()))
    return out


# Nonlinear toy model: f(z) = A z + 0.1 sin(z), h(z) = tanh(H z).
def toy_f(z: torch.Tensor, A: torch.Tensor) -> torch.Tensor:
    return z @ A.mT + 0.1 * torch.sin(z)


def toy_h(z: torch.Tensor, H: torch.Tensor) -> torch.Tensor:
    return torch.tanh(z @ H.mT)


def toy_F(z: torch.Tensor, A: torch.Tensor) -> torch.Tensor:
    return A + 0.1 * torch.diag_embed(torch.cos(z))


def toy_J(z: torch.Tensor, H: torch.Tensor) -> torch.Tensor:
    return (1 - torch.tanh(z @ H.mT) ** 2)[..., None] * H


def toy_dynamics(A: np.ndarray, H: np.ndarray, *, analytic: bool, dtype=F64) -> LatentDynamics:
    At, Ht = torch.tensor(A, dtype=dtype), torch.tensor(H, dtype=dtype)
    return LatentDynamics(
        forecast=lambda z: toy_f(z, At),
        observe=lambda z: toy_h(z, Ht),
        forecast_jacobian=(lambda z: toy_F(z, At)) if analytic else None,
        observe_jacobian=(lambda z: toy_J(z, Ht)) if analytic else None,
    )


# ------------------------------------------------------------------------------- EKF vs filterpy


@pytest.mark.parametrize("constant_jacobians", [True, False])
def test_ekf_equals_filterpy_kalman_filter_on_linear_gaussian_system(constant_jacobians):
    sys = linear_system()
    ekf = EKF(
        linear_dynamics(sys["A"], sys["H"], constant_jacobians=constant_jacobians),
        R=torch.tensor(sys["R"]),
        Q=torch.tensor(sys["Q"]),
    )
    ekf.reset(torch.tensor(sys["z0"])[None], torch.tensor(sys["P0"]))
    for k, (y, (x_ref, P_ref, K_ref)) in enumerate(zip(sys["ys"], filterpy_kf(sys))):
        ekf.step(torch.tensor(y)[None])
        np.testing.assert_allclose(ekf.mean[0].numpy(), x_ref, rtol=0, atol=1e-10, err_msg=f"mean at step {k}")
        np.testing.assert_allclose(ekf.cov[0].numpy(), P_ref, rtol=0, atol=1e-10, err_msg=f"cov at step {k}")
        assert ekf.diagnostics.gain_norm[-1].item() == pytest.approx(np.linalg.norm(K_ref, 2), rel=1e-10)
    assert ekf.diagnostics.max_forecast_norm.item() == pytest.approx(np.linalg.norm(sys["A"], 2), rel=1e-12)


def test_spectral_norm_equals_the_largest_singular_value():
    """The diagnostics take ||M||_2 from the smaller Gram matrix; it must match numpy's SVD, both orientations."""
    from dks_gym.filters.diagnostics import spectral_norm

    torch.manual_seed(0)
    for shape in [(7, 32, 16), (7, 16, 32), (5, 32, 32), (3, 1, 8)]:
        M = torch.randn(shape)
        reference = np.linalg.norm(M.double().numpy(), 2, axis=(1, 2))
        np.testing.assert_allclose(spectral_norm(M).numpy(), reference, rtol=2e-6)
        np.testing.assert_allclose(spectral_norm(M.double()).numpy(), reference, rtol=1e-12)


def test_a_constant_forecast_norm_follows_a_reset_with_another_batch():
    """The norm of a constant F is computed once per episode: a reset with another batch size recomputes it."""
    sys = linear_system()
    ekf = EKF(linear_dynamics(sys["A"], sys["H"], constant_jacobians=True), sigma=0.1, Q=1e-3)
    expected = np.linalg.norm(sys["A"], 2)
    for batch in (1, 3):
        ekf.reset(torch.tensor(sys["z0"]).expand(batch, -1).clone())
        for y in sys["ys"][:3]:
            ekf.step(torch.tensor(y).expand(batch, -1))
        norms = ekf.diagnostics.stacked("forecast_norm")
        assert norms.shape == (3, batch)
        np.testing.assert_allclose(norms.numpy(), expected, rtol=1e-12)


def test_ekf_equals_filterpy_extended_kalman_filter_on_nonlinear_map():
    sys = linear_system(seed=1)
    A, H = sys["A"], sys["H"]
    r, m = A.shape[0], H.shape[0]

    def f(x):
        return A @ x + 0.1 * np.sin(x)

    def F(x):
        return A + 0.1 * np.diag(np.cos(x))

    def h(x):
        return np.tanh(H @ x)

    def J(x):
        return (1 - np.tanh(H @ x) ** 2)[:, None] * H

    ref = ExtendedKalmanFilter(dim_x=r, dim_z=m)
    ref.x, ref.P, ref.Q, ref.R = sys["z0"].copy(), sys["P0"].copy(), sys["Q"], sys["R"]
    ref.predict_x = lambda u=0: setattr(ref, "x", f(ref.x))  # filterpy propagates P with ref.F, set below at x_a

    ekf = EKF(toy_dynamics(A, H, analytic=True), R=torch.tensor(sys["R"]), Q=torch.tensor(sys["Q"]))
    ekf.reset(torch.tensor(sys["z0"])[None], torch.tensor(sys["P0"]))
    for k, y in enumerate(sys["ys"]):
        ref.F = F(ref.x)
        ref.predict()
        ref.update(y, HJacobian=J, Hx=h)
        ekf.step(torch.tensor(y)[None])
        np.testing.assert_allclose(ekf.mean[0].numpy(), ref.x, rtol=0, atol=1e-10, err_msg=f"mean at step {k}")
        np.testing.assert_allclose(ekf.cov[0].numpy(), ref.P, rtol=0, atol=1e-10, err_msg=f"cov at step {k}")


def test_step_functions_compose_to_the_class():
    sys = linear_system(seed=2)
    dyn = toy_dynamics(sys["A"], sys["H"], analytic=False)
    ekf = EKF(dyn, R=0.2, Q=0.01)
    z0 = torch.tensor(sys["z0"])[None]
    ekf.reset(z0)
    state = GaussianState(z0, torch.eye(4, dtype=F64)[None])
    for y in sys["ys"][:10]:
        y = torch.tensor(y)[None]
        ekf.step(y)
        state, _ = ekf_forecast(state, dyn, 0.01)
        state, _ = ekf_update(state, y, dyn, 0.2)
        torch.testing.assert_close(ekf.mean, state.mean, rtol=0, atol=0)
        torch.testing.assert_close(ekf.cov, state.cov, rtol=0, atol=0)


# ------------------------------------------------------------------------- batching, dtype, Jacobians


def test_batched_filters_equal_separate_runs():
    B = 4
    systems = [linear_system(seed=10 + b) for b in range(B)]
    A = torch.tensor(np.stack([s["A"] for s in systems]))
    H = torch.tensor(np.stack([s["H"] for s in systems]))
    ys = torch.tensor(np.stack([s["ys"] for s in systems], axis=1))  # (T, B, m)
    z0 = torch.tensor(np.stack([s["z0"] for s in systems]))
    P0 = torch.tensor(np.stack([s["P0"] for s in systems]))
    sigma = torch.tensor([0.2, 0.5, 1.0, 0.3], dtype=F64)
    Q = torch.tensor([1e-4, 1e-3, 1e-2, 1e-1], dtype=F64)

    # Per-element matrices enter through bind_param, so autodiff must keep each element's own A_b, H_b.
    batched = EKF(
        LatentDynamics(
            bind_param(lambda z, a: toy_f(z[:, None], a)[:, 0], A),
            bind_param(lambda z, h: toy_h(z[:, None], h)[:, 0], H),
        ),
        sigma=sigma,
        Q=Q,
    )
    batched.reset(z0, P0)
    singles = []
    for b in range(B):
        f = EKF(toy_dynamics(systems[b]["A"], systems[b]["H"], analytic=True), sigma=sigma[b].item(), Q=Q[b].item())
        f.reset(z0[b : b + 1], P0[b])
        singles.append(f)
    for y in ys:
        batched.step(y)
        for b, f in enumerate(singles):
            f.step(y[b : b + 1])
            torch.testing.assert_close(batched.mean[b], f.mean[0], rtol=1e-10, atol=1e-10)
            torch.testing.assert_close(batched.cov[b], f.cov[0], rtol=1e-10, atol=1e-10)


def test_float32_follows_the_inputs_and_agrees_with_float64():
    sys = linear_system(seed=3)
    results = {}
    for dtype in (torch.float32, F64):
        ekf = EKF(toy_dynamics(sys["A"], sys["H"], analytic=False, dtype=dtype), R=torch.tensor(sys["R"]), Q=1e-3)
        ekf.reset(torch.tensor(sys["z0"], dtype=dtype)[None])
        for y in sys["ys"]:
            ekf.step(torch.tensor(y, dtype=dtype)[None])
        assert ekf.mean.dtype == dtype and ekf.cov.dtype == dtype
        results[dtype] = (ekf.mean.double(), ekf.cov.double())
    torch.testing.assert_close(results[torch.float32][0], results[F64][0], rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(results[torch.float32][1], results[F64][1], rtol=1e-4, atol=1e-4)

    enkf = EnKF(toy_dynamics(sys["A"], sys["H"], analytic=False, dtype=torch.float32), sigma=0.5)
    enkf.reset(torch.zeros(2, 4))
    for y in sys["ys"][:5]:
        enkf.step(torch.tensor(y, dtype=torch.float32).expand(2, -1))
    assert enkf.mean.dtype == torch.float32 and enkf.ensemble.shape == (2, 20, 4)


@pytest.mark.parametrize("method", ["vmap", "loop"])
def test_autodiff_jacobians_equal_analytic_ones(method):
    rng = np.random.default_rng(4)
    B, r, m = 5, 4, 3
    A = torch.tensor(np.stack([stable_matrix(rng, r) for _ in range(B)]))
    H = torch.tensor(rng.standard_normal((B, m, r)))
    z = torch.tensor(rng.standard_normal((B, r)))
    f = bind_param(lambda x, a: toy_f(x[:, None], a)[:, 0], A)
    h = bind_param(lambda x, hh: toy_h(x[:, None], hh)[:, 0], H)
    value, F = value_and_jacobian(f, z, method)
    torch.testing.assert_close(value, toy_f(z[:, None], A)[:, 0], rtol=0, atol=1e-14)
    torch.testing.assert_close(F, toy_F(z, A), rtol=0, atol=1e-13)
    value, J = value_and_jacobian(h, z, method)
    s = 1 - torch.tanh(torch.einsum("bmr,br->bm", H, z)) ** 2
    torch.testing.assert_close(J, s[..., None] * H, rtol=0, atol=1e-13)


def test_ekf_with_autodiff_equals_ekf_with_analytic_jacobians():
    sys = linear_system(seed=5)
    runs = []
    for analytic in (True, False):
        ekf = EKF(toy_dynamics(sys["A"], sys["H"], analytic=analytic), R=torch.tensor(sys["R"]))
        ekf.reset(torch.tensor(sys["z0"])[None], torch.tensor(sys["P0"]))
        for y in sys["ys"]:
            ekf.step(torch.tensor(y)[None])
        runs.append((ekf.mean, ekf.cov))
    torch.testing.assert_close(runs[0][0], runs[1][0], rtol=0, atol=1e-12)
    torch.testing.assert_close(runs[0][1], runs[1][1], rtol=0, atol=1e-12)


# --------------------------------------------------------------------------------- forward runs


def test_forward_run_is_the_model_rollout_with_propagated_covariance():
    sys = linear_system(seed=6)
    A, Q, P0, z0 = (torch.tensor(sys[k]) for k in ("A", "Q", "P0", "z0"))
    ekf = EKF(linear_dynamics(sys["A"], sys["H"], constant_jacobians=False), sigma=1.0, Q=Q)
    ekf.reset(z0[None], P0)
    z, P = z0, P0
    for _ in range(20):
        ekf.step(assimilate=False)
        z, P = A @ z, A @ P @ A.T + Q
    torch.testing.assert_close(ekf.mean[0], z, rtol=0, atol=1e-13)
    torch.testing.assert_close(ekf.cov[0], P, rtol=0, atol=1e-12)
    assert not any(ekf.diagnostics.assimilated) and float(ekf.diagnostics.stacked("gain_norm").abs().max()) == 0.0

    enkf = EnKF(
        linear_dynamics(sys["A"], sys["H"], constant_jacobians=False), sigma=1.0, Q=0.0, n_members=7, generator=3
    )
    enkf.reset(z0[None], P0)
    E = enkf.ensemble.clone()
    for _ in range(20):
        enkf.step(assimilate=False)
        E = E @ A.T
    torch.testing.assert_close(enkf.ensemble, E, rtol=0, atol=1e-12)


# ------------------------------------------------------------------------------------------- EnKF


def test_enkf_converges_to_the_kalman_filter_at_the_monte_carlo_rate():
    sys = linear_system(seed=7, n_steps=8)
    ref = filterpy_kf(sys)
    n_seeds = 16
    dyn = linear_dynamics(sys["A"], sys["H"], constant_jacobians=True)
    members = [50, 200, 800, 3200]
    mean_err, cov_err = [], []
    for n in members:
        enkf = EnKF(dyn, R=torch.tensor(sys["R"]), Q=torch.tensor(sys["Q"]), n_members=n, generator=n)
        enkf.reset(torch.tensor(sys["z0"]).expand(n_seeds, -1), torch.tensor(sys["P0"]))
        e_mean = e_cov = 0.0
        for y, (x_ref, P_ref, _) in zip(sys["ys"], ref):
            enkf.step(torch.tensor(y).expand(n_seeds, -1))
            e_mean += ((enkf.mean - torch.tensor(x_ref)) ** 2).sum(-1).mean().item()
            e_cov += ((enkf.cov - torch.tensor(P_ref)) ** 2).sum((-2, -1)).mean().item()
        mean_err.append(math.sqrt(e_mean))
        cov_err.append(math.sqrt(e_cov))
    for name, err in (("mean", mean_err), ("cov", cov_err)):
        slope = np.polyfit(np.log(members), np.log(err), 1)[0]
        assert -0.75 < slope < -0.3, f"{name} error {err} falls with slope {slope:.2f}, expected about -0.5"
        assert err[-1] < err[0] / 4


def test_enkf_lorenz63_matches_dapper_pertobs_score():
    path = Path(__file__).resolve().parents[1] / "validation" / "lorenz63_enkf.py"
    spec = importlib.util.spec_from_file_location("lorenz63_enkf", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    result = bench.run_lorenz63_enkf(n_cycles=1000, n_seeds=4, seed=0)
    # DAPPER lists 0.65 for this setting; below ~0.3 would beat the near-optimal particle filter (0.27).
    assert 0.3 < result["rmse_a_mean"] < 1.0, result["rmse_a_per_seed"]


def test_enkf_is_reproducible_from_its_seed():
    sys = linear_system(seed=8, n_steps=5)
    dyn = toy_dynamics(sys["A"], sys["H"], analytic=False)
    means = []
    for seed in (1, 1, 2):
        enkf = EnKF(dyn, sigma=0.5, generator=seed)
        enkf.reset(torch.zeros(3, 4, dtype=F64))
        for y in sys["ys"]:
            enkf.step(torch.tensor(y).expand(3, -1))
        means.append(enkf.mean)
    assert torch.equal(means[0], means[1]) and not torch.equal(means[0], means[2])


def test_enkf_localization_hook_and_inflation():
    sys = linear_system(seed=9)
    dyn = linear_dynamics(sys["A"], sys["H"], constant_jacobians=False)
    E = initial_ensemble(torch.tensor(sys["z0"])[None], 1.0, 30, torch.Generator().manual_seed(0))
    y = torch.tensor(sys["ys"][0])[None]

    def update(**kw):
        return enkf_update(E, y, dyn, 0.3, torch.Generator().manual_seed(1), **kw)

    plain, K = update()
    same, _ = update(localization=schur_localization(torch.ones(4, 3)))
    torch.testing.assert_close(same, plain, rtol=0, atol=1e-14)
    taper = torch.ones(4, 3)
    taper[2] = 0.0
    local, K_local = update(localization=schur_localization(taper))
    assert torch.equal(local[..., 2], E[..., 2]) and not torch.equal(local[..., 0], E[..., 0])
    assert float(K_local[0, 2].abs().max()) == 0.0

    inflated, _ = update(inflation=1.5)
    torch.testing.assert_close(inflated.mean(1), plain.mean(1), rtol=0, atol=1e-12)
    torch.testing.assert_close(ensemble_state(inflated).cov, 1.5**2 * ensemble_state(plain).cov, rtol=1e-12, atol=1e-12)

    # Centred perturbations make the mean update exactly K (y - mean h(E)).
    torch.testing.assert_close(
        plain.mean(1), E.mean(1) + ((y - (E @ torch.tensor(sys["H"]).T).mean(1)) @ K[0].T), rtol=0, atol=1e-12
    )


def dapper_pertobs_analysis(E: np.ndarray, Eo: np.ndarray, R: np.ndarray, y: np.ndarray, D: np.ndarray) -> np.ndarray:
    """DAPPER's EnKF('PertObs') analysis (dapper/da_methods/ensemble.py), members as rows; D is subtracted from y."""
    N1 = E.shape[0] - 1
    A, Y = E - E.mean(0), Eo - Eo.mean(0)
    C = Y.T @ Y + R * N1
    KG = A.T @ np.linalg.solve(C.T, Y.T).T
    return E + (y - D - Eo) @ KG.T


@pytest.mark.parametrize("perturbations", ["centered", "raw"])
def test_enkf_update_equals_dapper_pertobs_analysis(perturbations):
    rng = np.random.default_rng(16)
    B, n, r, m = 2, 10, 4, 3
    H, R = rng.standard_normal((m, r)), random_spd(rng, m, 0.5)
    E = torch.tensor(rng.standard_normal((B, n, r)))
    y = torch.tensor(rng.standard_normal((B, m)))
    dyn = LatentDynamics(forecast=lambda z: z, observe=lambda z: toy_h(z, torch.tensor(H)))
    ours, _ = enkf_update(E, y, dyn, torch.tensor(R), torch.Generator().manual_seed(3), perturbations=perturbations)
    # Replay our draws as DAPPER's perturbations (it subtracts D where we add eps; same distribution).
    eps = (
        torch.randn((B, n, m), generator=torch.Generator().manual_seed(3), dtype=F64).numpy() @ np.linalg.cholesky(R).T
    )
    if perturbations == "centered":  # DAPPER's mean0: centre, then rescale by sqrt(N / (N - 1))
        eps = (eps - eps.mean(1, keepdims=True)) * math.sqrt(n / (n - 1))
    for b in range(B):
        Eo = toy_h(E[b], torch.tensor(H)).numpy()
        ref = dapper_pertobs_analysis(E[b].numpy(), Eo, R, y[b].numpy(), -eps[b])
        np.testing.assert_allclose(ours[b].numpy(), ref, rtol=0, atol=1e-12)


def test_enkf_process_noise_has_covariance_q():
    Q = torch.tensor(random_spd(np.random.default_rng(11), 3, 0.1))
    E = torch.zeros(2, 20000, 3, dtype=F64)
    dyn = LatentDynamics(forecast=lambda z: z, observe=lambda z: z)
    out = enkf_forecast(E, dyn, Q, torch.Generator().manual_seed(0))
    torch.testing.assert_close(ensemble_state(out).cov, Q.expand(2, 3, 3), rtol=0, atol=5e-3)


# ------------------------------------------------------------------------------------- bad input


def make_filter(kind: str, **kw):
    sys = linear_system(seed=12)
    dyn = kw.pop("dynamics", None) or linear_dynamics(sys["A"], sys["H"], constant_jacobians=False)
    cls = EKF if kind == "ekf" else EnKF
    return cls(dyn, sigma=0.5, **kw)


@pytest.mark.parametrize("kind", ["ekf", "enkf"])
def test_bad_measurements_raise_value_errors(kind):
    f = make_filter(kind)
    f.reset(torch.zeros(4, 4, dtype=F64))
    y = torch.zeros(4, 3, dtype=F64)
    y[1, 0], y[3, 2] = float("nan"), float("inf")
    with pytest.raises(ValueError, match=r"batch elements \[1, 3\]"):
        f.step(y)
    with pytest.raises(ValueError, match="measurement dimension changed"):
        f.step(torch.zeros(4, 5, dtype=F64))
    with pytest.raises(ValueError, match=r"\(B, m\) with B = 4"):
        f.step(torch.zeros(3, 3, dtype=F64))
    with pytest.raises(ValueError, match="needs a measurement"):
        f.step()
    f.step(torch.zeros(4, 3, dtype=F64))
    # A second observe map of another size (a sensor layout that changed size) is caught too.
    f.dynamics = LatentDynamics(forecast=f.dynamics.forecast, observe=lambda z: z[:, :2])
    with pytest.raises(ValueError, match="measurement dimension changed"):
        f.step(torch.zeros(4, 2, dtype=F64))


@pytest.mark.parametrize("kind", ["ekf", "enkf"])
def test_bad_initial_covariance_and_setup_raise_value_errors(kind):
    f = make_filter(kind)
    z0 = torch.zeros(2, 4, dtype=F64)
    asym = torch.eye(4, dtype=F64).repeat(2, 1, 1)
    asym[1, 0, 1] = 0.5
    with pytest.raises(ValueError, match=r"P0 is not symmetric in batch elements \[1\]"):
        f.reset(z0, asym)
    indefinite = torch.eye(4, dtype=F64).repeat(2, 1, 1)
    indefinite[0, 3, 3] = -1.0
    with pytest.raises(ValueError, match=r"P0 is not positive definite in batch elements \[0\]"):
        f.reset(z0, indefinite)
    with pytest.raises(ValueError, match="z0 must be"):
        f.reset(torch.zeros(4, dtype=F64))
    with pytest.raises(RuntimeError, match="reset"):
        make_filter(kind).step(torch.zeros(2, 3, dtype=F64))
    cls = EKF if kind == "ekf" else EnKF
    dyn = f.dynamics
    with pytest.raises(ValueError, match="exactly one of R"):
        cls(dyn, R=1.0, sigma=1.0)
    with pytest.raises(ValueError, match="R is not positive definite"):
        cls(dyn, R=torch.diag(torch.tensor([1.0, 0.0, 1.0])))
    with pytest.raises(ValueError, match="Q must be non-negative"):
        cls(dyn, sigma=1.0, Q=-1.0)
    with pytest.raises(ValueError, match="on_divergence"):
        cls(dyn, sigma=1.0, on_divergence="ignore")
    extra = {"jacobian_method": "numeric"} if kind == "ekf" else {"perturbations": "deterministic"}
    with pytest.raises(ValueError, match="must be"):
        cls(dyn, sigma=1.0, **extra)


def poisoned_dynamics(when: int, element: int, B: int):
    """Linear dynamics whose forecast turns batch element ``element`` to NaN at call ``when``."""
    sys = linear_system(seed=13)
    A, H = torch.tensor(sys["A"]), torch.tensor(sys["H"])
    calls = {"n": 0}

    def forecast(z):
        out = z @ A.T
        calls["n"] += 1
        if calls["n"] == when:
            out = out.clone()
            out.view(B, -1, out.shape[-1])[element] = float("nan")
        return out

    return LatentDynamics(forecast=forecast, observe=lambda z: z @ H.T)


@pytest.mark.parametrize("kind", ["ekf", "enkf"])
def test_divergence_raises_or_resets_the_affected_elements(kind):
    B = 3
    ys = torch.tensor(linear_system(seed=13)["ys"][:6]).expand(B, -1, -1).transpose(0, 1)
    z0 = torch.arange(B * 4, dtype=F64).reshape(B, 4) / 10

    f = make_filter(kind, dynamics=poisoned_dynamics(3, 1, B))
    f.reset(z0)
    with pytest.raises(FilterDivergence, match=r"batch elements \[1\]") as info:
        for y in ys:
            f.step(y)
    assert isinstance(info.value, RuntimeError) and f.n_steps == 2

    clean = make_filter(kind, generator=5) if kind == "enkf" else make_filter(kind)
    clean.dynamics = poisoned_dynamics(-1, 1, B)
    reset = make_filter(
        kind, dynamics=poisoned_dynamics(3, 1, B), on_divergence="reset", **({"generator": 5} if kind == "enkf" else {})
    )
    clean.reset(z0)
    reset.reset(z0)
    P0 = reset.cov.clone()
    for k, y in enumerate(ys):
        clean.step(y)
        reset.step(y)
        assert torch.isfinite(reset.mean).all() and torch.isfinite(reset.cov).all()
        if k == 2:
            torch.testing.assert_close(reset.mean[1], z0[1] if kind == "ekf" else reset._initial_ensemble[1].mean(0))
            torch.testing.assert_close(reset.cov[1], P0[1])
        keep = torch.tensor([0, 2])
        torch.testing.assert_close(reset.mean[keep], clean.mean[keep], rtol=0, atol=0)
    flags = reset.diagnostics.stacked("reset")
    assert flags[2].tolist() == [False, True, False] and int(flags.sum()) == 1


# ------------------------------------------------------------------------------- long-run health


def test_long_stream_keeps_covariance_symmetric_pd_and_converges_to_riccati():
    rng = np.random.default_rng(14)
    r, m, n_steps = 8, 4, 10_000
    A, H = stable_matrix(rng, r), rng.standard_normal((m, r))
    Q, R = random_spd(rng, r, 0.01), random_spd(rng, m, 0.5)
    ekf = EKF(
        linear_dynamics(A, H, constant_jacobians=True), R=torch.tensor(R), Q=torch.tensor(Q), record_diagnostics=False
    )
    ekf.reset(torch.zeros(1, r, dtype=F64))
    x = np.zeros(r)
    noise = rng.standard_normal((n_steps, r + m))
    Lq, Lr = np.linalg.cholesky(Q), np.linalg.cholesky(R)
    covs = torch.empty(n_steps, r, r, dtype=F64)
    for k in range(n_steps):
        x = A @ x + Lq @ noise[k, :r]
        ekf.step(torch.tensor(H @ x + Lr @ noise[k, r:])[None])
        covs[k] = ekf.cov[0]
    assert torch.equal(covs, covs.mT)
    assert float(torch.linalg.eigvalsh(covs)[:, 0].min()) > 0
    P_f = scipy.linalg.solve_discrete_are(A.T, H.T, Q, R)  # steady-state forecast covariance
    P_a = P_f - P_f @ H.T @ np.linalg.solve(H @ P_f @ H.T + R, H @ P_f)
    norms = torch.linalg.matrix_norm(covs, ord=2)
    assert float(norms.max()) <= 2 * max(1.0, np.linalg.norm(P_f, 2))
    np.testing.assert_allclose(covs[-1000:].numpy(), np.broadcast_to(P_a, (1000, r, r)), rtol=0, atol=1e-10)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("kind", ["ekf", "enkf"])
def test_cuda_matches_cpu(kind):
    sys = linear_system(seed=15)
    out = {}
    for device in ("cpu", "cuda"):
        A, H = torch.tensor(sys["A"], device=device), torch.tensor(sys["H"], device=device)
        dyn = LatentDynamics(lambda z, A=A: toy_f(z, A), lambda z, H=H: toy_h(z, H))
        f = EKF(dyn, sigma=0.5) if kind == "ekf" else EnKF(dyn, sigma=0.5, Q=0.0)
        f.reset(torch.zeros(2, 4, dtype=F64, device=device))
        if (
            kind == "enkf"
        ):  # generators differ across devices: share the initial ensemble, no perturbation noise on CPU vs GPU
            f.reset_ensemble(
                initial_ensemble(torch.zeros(2, 4, dtype=F64), 1.0, 20, torch.Generator().manual_seed(0)).to(device)
            )
            for y in sys["ys"][:10]:
                f.step(torch.tensor(y, device=device).expand(2, -1), assimilate=False)
        else:
            for y in sys["ys"]:
                f.step(torch.tensor(y, device=device).expand(2, -1))
        assert f.mean.device.type == device
        out[device] = (f.mean.cpu(), f.cov.cpu())
    torch.testing.assert_close(out["cuda"][0], out["cpu"][0], rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(out["cuda"][1], out["cpu"][1], rtol=1e-10, atol=1e-10)


# ------------------------------------------------------------------------------- EKF vs torch-kf


def torch_kf_run(torch_kf, sys: dict, R_kf: torch.Tensor, z0: torch.Tensor, P0: torch.Tensor, ys: torch.Tensor):
    kf = torch_kf.KalmanFilter(torch.tensor(sys["A"]).to(z0), torch.tensor(sys["H"]).to(z0),
                               torch.tensor(sys["Q"]).to(z0), R_kf, joseph_update=True)
    state = torch_kf.GaussianState(z0[..., None], P0)
    for y in ys:
        state = kf.update(kf.predict(state), y[..., None])
    return state.mean[..., 0], state.covariance


@pytest.mark.parametrize("R_kind", ["matrix", "per_element", "scalar"])
def test_ekf_steps_equal_torch_kf_with_the_joseph_update(R_kind):
    """torch-kf (a second batched PyTorch Kalman filter: LU inverse of S, no symmetrization) with
    joseph_update=True, predict then update for 8 steps of a batch of 4, in float64."""
    torch_kf = pytest.importorskip("torch_kf")
    sys = linear_system(seed=31, r=5, m=3)
    rng = np.random.default_rng(31)
    B, m = 4, 3
    R = {"matrix": torch.tensor(sys["R"]), "per_element": torch.tensor([0.1, 0.2, 0.4, 0.8], dtype=F64),
         "scalar": 0.3}[R_kind]
    variance = torch.as_tensor(R, dtype=F64)[..., None, None]  # torch-kf takes R as a matrix (stack)
    R_kf = torch.tensor(sys["R"]) if R_kind == "matrix" else variance * torch.eye(m, dtype=F64)
    z0 = torch.tensor(rng.standard_normal((B, 5)))
    P0 = torch.tensor(np.stack([random_spd(rng, 5) for _ in range(B)]))
    ys = torch.tensor(sys["ys"][:8, None] + rng.standard_normal((8, B, m)))
    dyn = linear_dynamics(sys["A"], sys["H"], constant_jacobians=True)
    state = GaussianState(z0, P0)
    for y in ys:
        state, _ = ekf_forecast(state, dyn, torch.tensor(sys["Q"]))
        state, _ = ekf_update(state, y, dyn, R)
    mean, cov = torch_kf_run(torch_kf, sys, R_kf, z0, P0, ys)
    torch.testing.assert_close(state.mean, mean, rtol=0, atol=1e-10)
    torch.testing.assert_close(state.cov, cov, rtol=0, atol=1e-10)


def test_float32_ekf_step_equals_torch_kf_at_the_benchmarked_size():
    """benchmarks/perf.py's torchkf case (r = 32, m = 16, float32) at B = 64: one step, equal to round-off."""
    torch_kf = pytest.importorskip("torch_kf")
    rng = np.random.default_rng(32)
    B, r, m = 64, 32, 16
    sys = {"A": np.linalg.qr(rng.standard_normal((r, r)))[0] * 0.99, "H": rng.standard_normal((m, r)),
           "Q": 1e-4 * np.eye(r)}
    z0 = torch.tensor(rng.standard_normal((B, r)), dtype=torch.float32)
    M = torch.tensor(rng.standard_normal((B, r, r)), dtype=torch.float32)
    P0, y = M @ M.mT / r + 0.1 * torch.eye(r), torch.tensor(rng.standard_normal((1, B, m)), dtype=torch.float32)
    dyn = linear_dynamics(sys["A"], sys["H"], constant_jacobians=True)
    forecast, _ = ekf_forecast(GaussianState(z0, P0), dyn, 1e-4)
    analysis, _ = ekf_update(forecast, y[0], dyn, 0.04)
    mean, cov = torch_kf_run(torch_kf, sys, 0.04 * torch.eye(m), z0, P0, y)
    assert float((analysis.mean - mean).abs().max() / mean.abs().max()) < 1e-5
    assert float((analysis.cov - cov).abs().max() / cov.abs().max()) < 1e-5


def test_nonfinite_elements_flags_exactly_the_elements_holding_nan_or_inf():
    """The check by each element's sum, against numpy's isfinite entry by entry: a NaN, an inf, a -inf, inf and
    -inf together are flagged; finite entries whose float32 sum overflows are not."""
    P, z = torch.zeros(7, 3, 3), torch.zeros(7, 3)
    P[1, 0, 0], P[2, 1, 2], P[3, 2, 2] = float("nan"), float("inf"), -float("inf")
    P[4, 0, 0], P[4, 1, 1] = float("inf"), -float("inf")
    P[5] = torch.finfo(torch.float32).max
    z[6, 1] = float("nan")
    expected = ~(np.isfinite(P.numpy()).reshape(7, -1).all(1) & np.isfinite(z.numpy()).all(1))
    assert nonfinite_elements(z, P).tolist() == expected.tolist() == [False, True, True, True, True, False, True]
    assert not nonfinite_elements(z[[0, 5]], P[[0, 5]]).any()


# ------------------------------------------------------------------------------- missing readings


@pytest.mark.parametrize(("constant_jacobians", "full_R"), [(True, True), (False, True), (True, False)])
def test_masked_ekf_update_equals_filterpy_with_the_rows_present(constant_jacobians, full_R):
    """A reading marked missing drops its row of H and its row and column of R: filterpy's update with the
    reduced H and R (a full R, so the cross terms matter; or a scalar variance, which the update scales K's
    columns by instead of multiplying by R) is the reference, element by element."""
    sys = linear_system(seed=21)
    A, H, Q, R, P0, z0 = sys["A"], sys["H"], sys["Q"], sys["R"], sys["P0"], sys["z0"]
    if not full_R:
        R = 0.3 * np.eye(3)
    masks = np.array([[True, False, True], [False, False, True], [True, True, True]])
    ekf = EKF(linear_dynamics(A, H, constant_jacobians=constant_jacobians), R=torch.tensor(R) if full_R else 0.3,
              Q=torch.tensor(Q))
    ekf.reset(torch.tensor(z0).expand(3, -1).clone(), torch.tensor(P0))
    y = np.tile(sys["ys"][0], (3, 1))
    with pytest.raises(ValueError, match="mask"):  # NaN without a mask is refused, saying what to pass
        ekf.step(torch.tensor(np.where(masks, y, np.nan)))
    ekf.step(torch.tensor(np.where(masks, y, np.nan)), mask=torch.tensor(masks))
    for b, present in enumerate(masks):
        kf = KalmanFilter(dim_x=4, dim_z=int(present.sum()))
        kf.x, kf.P, kf.F, kf.Q = z0.copy(), P0.copy(), A, Q
        kf.H, kf.R = H[present], R[np.ix_(present, present)]
        kf.predict()
        kf.update(y[b][present])
        np.testing.assert_allclose(ekf.mean[b].numpy(), kf.x, rtol=0, atol=1e-10)
        np.testing.assert_allclose(ekf.cov[b].numpy(), kf.P, rtol=0, atol=1e-10)


def test_masked_enkf_update_equals_a_direct_computation_with_the_rows_present():
    """The EnKF analysis with readings missing, against numpy with the reduced observation: same ensemble, same
    perturbation draws (a reading's perturbation does not depend on which others are present)."""
    sys = linear_system(seed=23)
    H, R = sys["H"], sys["R"]
    rng = np.random.default_rng(0)
    batch, n, r, m = 2, 8, 4, 3
    E = rng.standard_normal((batch, n, r))
    y = rng.standard_normal((batch, m))
    masks = np.array([[True, False, True], [False, True, False]])
    dyn = linear_dynamics(sys["A"], H, constant_jacobians=False)
    analysis, _ = enkf_update(torch.tensor(E), torch.tensor(np.where(masks, y, np.nan)), dyn, torch.tensor(R),
                              torch.Generator().manual_seed(5), mask=torch.tensor(masks))
    Z = torch.randn((batch, n, m), generator=torch.Generator().manual_seed(5), dtype=F64).numpy()
    for b, p in enumerate(masks):
        predicted = E[b] @ H[p].T
        A_dev, Y_dev = E[b] - E[b].mean(0), predicted - predicted.mean(0)
        C_zy, C_yy = A_dev.T @ Y_dev / (n - 1), Y_dev.T @ Y_dev / (n - 1)
        K = C_zy @ np.linalg.inv(C_yy + R[np.ix_(p, p)])
        eps = Z[b][:, p] @ np.linalg.cholesky(R[np.ix_(p, p)]).T
        eps = (eps - eps.mean(0)) * np.sqrt(n / (n - 1))
        expected = E[b] + (y[b][p] + eps - predicted) @ K.T
        np.testing.assert_allclose(analysis[b].numpy(), expected, rtol=0, atol=1e-10)


@pytest.mark.parametrize("kind", ["ekf", "enkf"])
def test_an_episode_without_readings_is_the_forward_run(kind):
    sys = linear_system(seed=22)
    dyn = linear_dynamics(sys["A"], sys["H"], constant_jacobians=False)
    nothing = torch.zeros(2, 3, dtype=torch.bool)

    def run(readings: bool) -> tuple[torch.Tensor, torch.Tensor]:
        f = EKF(dyn, sigma=0.5, Q=1e-3) if kind == "ekf" else EnKF(dyn, sigma=0.5, Q=1e-3, n_members=10)
        f.reset(torch.tensor(sys["z0"]).expand(2, -1).clone())
        for _ in range(10):
            if readings:
                f.step(torch.full((2, 3), float("nan"), dtype=F64), mask=nothing)
            else:
                f.step(assimilate=False)
        return f.mean, f.cov

    for a, b in zip(run(True), run(False)):
        assert torch.equal(a, b)


# ------------------------------------------------------------------------------- late readings


def test_lead_of_the_lagged_ekf_equals_filterpy_on_the_delay_augmented_system():
    """Readings d frames late: the EKF kept at the readings' time and led d steps ahead (EKF.lead) is the
    Kalman filter on the state stacked with its d previous values, observing the oldest (filterpy, built by
    hand): F_aug shifts the stack, H_aug = [0 ... 0 H], Q_aug = Q in the newest block. Step by step, the
    newest block of the augmented filter equals the lead; the lagged filter itself is unchanged by leading."""
    sys = linear_system(seed=41, n_steps=25)
    A, H, Q, R, P0, z0 = sys["A"], sys["H"], sys["Q"], sys["R"], sys["P0"], sys["z0"]
    r, m, d = A.shape[0], H.shape[0], 2
    n = r * (d + 1)
    kf = KalmanFilter(dim_x=n, dim_z=m)
    kf.F = np.zeros((n, n))
    kf.F[:r, :r] = A  # newest block advances; older blocks shift down by one
    for j in range(1, d + 1):
        kf.F[j * r:(j + 1) * r, (j - 1) * r:j * r] = np.eye(r)
    kf.H = np.zeros((m, n))
    kf.H[:, d * r:] = H
    kf.Q = scipy.linalg.block_diag(Q, np.zeros((d * r, d * r)))
    kf.R = R
    # The stack starts with z_0 in every block (no frames before 0): fully correlated copies of P0.
    kf.x = np.tile(z0, d + 1)
    kf.P = np.kron(np.ones((d + 1, d + 1)), P0)
    ekf = EKF(linear_dynamics(A, H, constant_jacobians=False), R=torch.tensor(R), Q=torch.tensor(Q))
    ekf.reset(torch.tensor(z0)[None], torch.tensor(P0))
    for k, y_now in enumerate(sys["ys"], start=1):  # y_now: the reading of frame k, delivered at k + d
        kf.predict()
        if k > d:  # at frame k the reading of frame k - d arrives
            kf.update(sys["ys"][k - d - 1])
            ekf.step(torch.tensor(sys["ys"][k - d - 1])[None])
        before = ekf.mean.clone()
        ahead = ekf.lead(min(k, d))
        assert torch.equal(ekf.mean, before)
        np.testing.assert_allclose(ahead.mean[0].numpy(), kf.x[:r], rtol=0, atol=1e-9)
        np.testing.assert_allclose(ahead.cov[0].numpy(), kf.P[:r, :r], rtol=0, atol=1e-9)
        np.testing.assert_allclose(ekf.mean[0].numpy(), kf.x[min(k, d) * r:(min(k, d) + 1) * r], rtol=0, atol=1e-9)


def test_enkf_lead_is_the_forecast_its_next_steps_would_make():
    """EnKF.lead(d) draws from a copy of the generator: equal to d forecast-only steps of the filter, which it
    leaves (generator included) as it was."""
    sys = linear_system(seed=42)
    dyn = linear_dynamics(sys["A"], sys["H"], constant_jacobians=False)
    f = EnKF(dyn, sigma=0.5, Q=1e-2, n_members=6, generator=3)
    f.reset(torch.tensor(sys["z0"]).expand(2, -1).clone())
    f.step(torch.tensor(sys["ys"][:1]).expand(2, -1))
    state, ensemble = f.generator.get_state(), f.ensemble.clone()
    ahead = f.lead(3)
    assert torch.equal(f.generator.get_state(), state) and torch.equal(f.ensemble, ensemble)
    for _ in range(3):
        f.step(assimilate=False)
    assert torch.equal(ahead.ensemble, f.ensemble)


# ------------------------------------------------------------------------------- sensor bias


@pytest.mark.parametrize("constant_jacobians", [True, False])
def test_bias_augmented_ekf_equals_filterpy_on_the_hand_built_augmented_system(constant_jacobians):
    """A drifting sensor bias estimated with the state: the EKF on augment_with_bias(dynamics) is filterpy's
    KalmanFilter on F_aug = [[A, 0], [0, I]], H_aug = [H, I], Q_aug = blockdiag(Q, drift^2 I), step by step;
    and it recovers a bias the plain filter cannot see."""
    from dks_gym.filters import augment_with_bias, augmented_covariance

    sys = linear_system(seed=31, n_steps=60)
    A, H, Q, R, P0, z0 = sys["A"], sys["H"], sys["Q"], sys["R"], sys["P0"], sys["z0"]
    r, m = A.shape[0], H.shape[0]
    bias = np.array([0.8, -0.5, 0.3])
    ys = sys["ys"] + bias  # a constant offset on every reading
    drift2, bias_var = 1e-6, 1.0
    ekf = EKF(augment_with_bias(linear_dynamics(A, H, constant_jacobians=constant_jacobians), m),
              R=torch.tensor(R), Q=augmented_covariance(torch.tensor(Q), r, m, drift2))
    ekf.reset(torch.tensor(np.r_[z0, np.zeros(m)])[None], augmented_covariance(torch.tensor(P0), r, m, bias_var))
    kf = KalmanFilter(dim_x=r + m, dim_z=m)
    kf.F = scipy.linalg.block_diag(A, np.eye(m))
    kf.H = np.hstack([H, np.eye(m)])
    kf.Q = scipy.linalg.block_diag(Q, drift2 * np.eye(m))
    kf.R, kf.P, kf.x = R, scipy.linalg.block_diag(P0, bias_var * np.eye(m)), np.r_[z0, np.zeros(m)]
    for y in ys:
        ekf.step(torch.tensor(y)[None])
        kf.predict()
        kf.update(y)
        np.testing.assert_allclose(ekf.mean[0].numpy(), kf.x, rtol=0, atol=1e-9)
        np.testing.assert_allclose(ekf.cov[0].numpy(), kf.P, rtol=0, atol=1e-9)
    estimate, spread = ekf.mean[0, r:].numpy(), np.sqrt(np.diag(ekf.cov[0].numpy())[r:])
    assert np.all(np.abs(estimate - bias) < 4 * spread) and np.all(spread < 0.5)


def test_bias_augmentation_keeps_a_jacobian_that_brings_its_readings():
    """A model's observe_jacobian may return (h, J) (the sensor-local decoder): the augmented one returns
    (h + b, [J, I]) and filters like the plain-J version."""
    from dks_gym.filters import augment_with_bias
    from dks_gym.filters.jacobians import observe_with_jacobian

    sys = linear_system(seed=32)
    Ht = torch.tensor(sys["H"])
    plain = LatentDynamics(lambda z: z, lambda z: z @ Ht.T, observe_jacobian=lambda z: Ht.expand(len(z), -1, -1))
    paired = LatentDynamics(lambda z: z, lambda z: z @ Ht.T,
                            observe_jacobian=lambda z: (z @ Ht.T, Ht.expand(len(z), -1, -1)))
    x = torch.randn(5, 4 + 3, dtype=F64)
    h1, J1 = observe_with_jacobian(augment_with_bias(plain, 3), x)
    h2, J2 = observe_with_jacobian(augment_with_bias(paired, 3), x)
    torch.testing.assert_close(h1, h2)
    torch.testing.assert_close(J1, J2)
    torch.testing.assert_close(h1, x[:, :4] @ Ht.T + x[:, 4:])
    torch.testing.assert_close(J1[:, :, 4:], torch.eye(3, dtype=F64).expand(5, 3, 3))


def test_a_malformed_mask_is_refused_clearly():
    sys = linear_system(seed=24)
    ekf = EKF(linear_dynamics(sys["A"], sys["H"], constant_jacobians=True), sigma=0.5)
    ekf.reset(torch.zeros(2, 4, dtype=F64))
    y = torch.tensor(np.tile(sys["ys"][0], (2, 1)))
    for mask in (torch.ones(2, 4, dtype=torch.bool), torch.ones(2, 3)):  # wrong shape, not boolean
        with pytest.raises(ValueError, match="mask must be a boolean tensor shaped like y"):
            ekf.step(y, mask=mask)
    y[0, 1] = float("nan")
    with pytest.raises(ValueError, match="NaN or inf in batch elements \\[0\\]"):  # NaN where the mask says present
        ekf.step(y, mask=torch.ones(2, 3, dtype=torch.bool))
