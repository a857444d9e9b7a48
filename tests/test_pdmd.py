"""pDMD baseline: streamed POD, ParametricDMD fit, reconstruction, online operator A~(mu) (Appendix A.1)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from dks_gym.models import PDMD, build_model, streamed_pod

X_GRID = np.linspace(0.0, 2.0 * np.pi, 1024, endpoint=False)  # the Burgers grid
TIME = 0.005 * np.arange(60)
TRAIN_MU = np.linspace(0.01, 1.0, 16)
TEST_MU = 0.5 * (TRAIN_MU[1:] + TRAIN_MU[:-1])[::3]


def travelling_waves(mus: np.ndarray, mu_dependent_decay: bool = False) -> np.ndarray:
    """(n, n_t, 1, 1024) family u = 0.5 + sum_j a_j(mu) e^{-g_j t} sin(j x - w_j t + phi_j(mu)), j = 1..3.

    With decay rates independent of mu every trajectory lives in the same 6 POD modes and follows the
    same 6 DMD eigenvalues, so pDMD at r = 6 is exact; a mu-dependent decay g_j = mu j^2 is not.
    """
    out = np.empty((len(mus), len(TIME), 1, len(X_GRID)), np.float32)
    for i, mu in enumerate(mus):
        u = np.full((len(TIME), len(X_GRID)), 0.5)
        for j in (1, 2, 3):
            decay = mu * j**2 if mu_dependent_decay else 0.3 * j**2
            phase = j * X_GRID[None] - 4.0 * j * TIME[:, None] + mu * j
            u += (1 + mu) / j * np.exp(-decay * TIME)[:, None] * np.sin(phase)
        out[i, :, 0] = u
    return out


def fitted(r: int = 6, mu_dependent_decay: bool = False) -> tuple[PDMD, np.ndarray]:
    data = travelling_waves(TRAIN_MU, mu_dependent_decay)
    model = build_model("burgers", "pdmd", r=r, stats_mean=[0.5], stats_std=[0.8])
    model.fit(data, TRAIN_MU)
    return model, data


def relative_error(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def test_streamed_pod_matches_dense_svd():
    rng = np.random.default_rng(0)
    n, m, r = 400, 140, 10
    u, _ = np.linalg.qr(rng.standard_normal((n, m)))
    v, _ = np.linalg.qr(rng.standard_normal((m, m)))
    x = (u * 0.6 ** np.arange(m)) @ v.T  # snapshots as columns, geometric spectrum
    blocks = np.split(x.T, 7)  # seven "trajectories" of 20 snapshots (rows)
    pod = streamed_pod(len(blocks), lambda b: torch.as_tensor(blocks[b]), r, seed=1)
    u_ref, s_ref, _ = np.linalg.svd(x, full_matrices=False)
    np.testing.assert_allclose(pod["singular_values"].numpy(), s_ref[:r], rtol=1e-9)
    basis = pod["basis"].numpy()
    np.testing.assert_allclose(basis.T @ basis, np.eye(r), atol=1e-12)
    np.testing.assert_allclose(basis @ basis.T, u_ref[:, :r] @ u_ref[:, :r].T, atol=1e-9)  # same subspace
    coeffs = np.concatenate([c.numpy() for c in pod["coefficients"]])
    np.testing.assert_allclose(coeffs, x.T @ basis, atol=1e-12)
    assert pod["passes"] == 4  # range finder, two power iterations, projection
    assert pod["energy"] == pytest.approx(np.sum(s_ref[:r] ** 2) / np.sum(s_ref**2), rel=1e-12)


def test_pdmd_reconstructs_its_training_trajectories():
    model, data = fitted(r=6)
    r = model.r
    coeffs = model.interpolated_coefficients(TRAIN_MU)  # Eq. A3 at the training parameters
    recon = model.decode(torch.as_tensor(coeffs.reshape(-1, r)), None).numpy().reshape(data.shape)
    z0 = model.encode(torch.as_tensor(data[:, 0], dtype=torch.float64), TRAIN_MU)
    rollout = model.rollout(z0, torch.as_tensor(TRAIN_MU), len(TIME) - 1)  # A~(mu) applied recursively
    rolled = model.decode(rollout.reshape(-1, r), None).numpy().reshape(data.shape)
    assert relative_error(recon, data) < 1e-5
    assert relative_error(rolled, data) < 1e-5
    assert model.fit_info["pod_energy"] == pytest.approx(1.0, abs=1e-10)


def test_pdmd_truncation_error_on_a_family_beyond_rank_r():
    coarse, data = fitted(r=6, mu_dependent_decay=True)
    fine, _ = fitted(r=12, mu_dependent_decay=True)
    errors = []
    for model in (coarse, fine):
        coeffs = model.interpolated_coefficients(TRAIN_MU)
        recon = model.decode(torch.as_tensor(coeffs.reshape(-1, model.r)), None).numpy().reshape(data.shape)
        errors.append(relative_error(recon, data))
    assert 1e-5 < errors[0] < 1e-2  # per-parameter decay rates do not fit one rank-6 monolithic DMD
    assert errors[1] < 1e-5  # r = 12 resolves it


def test_online_operator_ignores_noise_level_directions():
    # r = 12 exceeds the 6-mode numerical rank of this family: POD modes 7-12 carry float32 noise only.
    model, data = fitted(r=12)
    test = travelling_waves(TEST_MU)
    z0 = model.encode(torch.as_tensor(test[:, 0], dtype=torch.float64), TEST_MU)
    rollout = model.rollout(z0, torch.as_tensor(TEST_MU), len(TIME) - 1)
    recon = model.decode(rollout.reshape(-1, 12), None).numpy().reshape(test.shape)
    assert relative_error(recon, test) < 1e-5
    assert torch.linalg.matrix_norm(model.online_operator(TEST_MU), ord=2).max() < 1.01
    model.pinv_rtol = 1e-15  # numpy's float64 default keeps the noise directions: the rollout leaves
    model._operator_cache.clear()  # the data (this is why the default cutoff is float32's)
    assert torch.linalg.matrix_norm(model.online_operator(TEST_MU), ord=2).max() > 2


def test_matches_parametric_dmd_with_ezyrb_pod_on_dense_data():
    ezyrb = pytest.importorskip("ezyrb")  # a dev-only cross-check: the models extra does not install it
    from pydmd import DMD, ParametricDMD

    POD, RBF = ezyrb.POD, ezyrb.RBF

    model, data = fitted(r=6, mu_dependent_decay=True)
    normalized = (data[:, :, 0].astype(np.float64) - 0.5) / 0.8  # (n, n_t, N)
    reference = ParametricDMD(DMD(svd_rank=6), POD("svd", rank=6), RBF(kernel="multiquadric"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        reference.fit(normalized.transpose(0, 2, 1), TRAIN_MU)
    reference.parameters = TEST_MU
    expected = np.real(reference.reconstructed_data).transpose(0, 2, 1) * 0.8 + 0.5  # (n, n_t, N)
    coeffs = model.interpolated_coefficients(TEST_MU)
    ours = model.decode(torch.as_tensor(coeffs.reshape(-1, 6)), None).numpy().reshape(expected.shape)
    assert relative_error(ours, expected) < 1e-6


def test_interpolant_is_the_multiquadric_rbf():
    from scipy.interpolate import RBFInterpolator

    model, _ = fitted(r=6, mu_dependent_decay=True)
    forecast = model.parametric_dmd().forecasted_modal_coefficients  # (n_train, r, n_t) DMD coefficients
    epsilon = TRAIN_MU.max() - TRAIN_MU.min()  # ezyrb's default shape parameter for one parameter
    ours = model.interpolated_coefficients(TEST_MU)
    for kernel, should_match in (("multiquadric", True), ("thin_plate_spline", False)):
        expected = np.stack(
            [
                RBFInterpolator(TRAIN_MU[:, None], forecast[:, :, k], kernel=kernel, epsilon=epsilon)(TEST_MU[:, None])
                for k in range(len(TIME))
            ],
            axis=1,
        ).real
        assert np.allclose(ours, expected, rtol=1e-8, atol=1e-10) == should_match


@pytest.mark.parametrize(
    "points, new_points",
    [
        (TRAIN_MU[:, None], TEST_MU[:, None]),  # the Burgers viscosity range, evenly spaced
        (np.geomspace(0.01, 1.0, 9)[:, None], np.geomspace(0.012, 0.9, 7)[:, None]),  # uneven spacing
        (np.linspace(59.5, 990.5, 12)[:, None], np.array([[60.0], [333.3], [990.0]])),  # the Reynolds range
        (np.array([[0.1], [0.2], [0.45], [0.5]]), np.array([[0.0], [0.3], [0.7]])),  # extrapolation too
        (np.random.default_rng(3).uniform([0.01, 50.0], [1.0, 900.0], (15, 2)),  # two parameters, unequal edges
         np.random.default_rng(4).uniform([0.01, 50.0], [1.0, 900.0], (6, 2))),
        (np.c_[np.linspace(0.01, 1.0, 8), np.full(8, 3.0)], np.c_[np.linspace(0.1, 0.9, 5), np.full(5, 3.0)]),
    ],
    ids=["burgers-nu", "geometric", "reynolds", "extrapolate", "2d", "2d-flat-edge"],
)
def test_multiquadric_rbf_equals_ezyrb_rbf(points, new_points):
    """The adapter predicts what ezyrb's RBF(kernel="multiquadric") predicts (real, complex, multi-output)."""
    ezyrb = pytest.importorskip("ezyrb")
    from dks_gym.models.rbf import MultiquadricRBF, default_epsilon

    rng = np.random.default_rng(len(points))
    values = {
        "multi-output": rng.standard_normal((len(points), 5)) * np.array([1.0, 1e-3, 10.0, 1e3, 0.5]),
        "complex": rng.standard_normal((len(points), 3)) + 1j * rng.standard_normal((len(points), 3)),
        "smooth": np.c_[np.sin(3 * points.sum(axis=1)), np.exp(-points[:, 0])],
    }
    for name, y in values.items():
        reference = ezyrb.RBF(kernel="multiquadric")
        reference.fit(points, y)
        ours = MultiquadricRBF().fit(points, y)
        assert ours.fitted_epsilon == reference.epsilon, name
        expected = reference.predict(new_points)
        np.testing.assert_allclose(ours.predict(new_points), expected, rtol=1e-12, atol=1e-12 * np.abs(y).max())
    if points.shape[1] == 1:
        assert default_epsilon(points) == pytest.approx(np.ptp(points))  # one parameter: its range
    # The check can fail: another shape parameter gives other predictions.
    other = MultiquadricRBF(epsilon=0.5 * default_epsilon(points)).fit(points, values["smooth"])
    assert not np.allclose(other.predict(new_points), expected, rtol=1e-6, atol=1e-9)


def test_pdmd_online_operator_equals_the_one_with_ezyrb_rbf():
    """A pDMD whose ParametricDMD interpolates with ezyrb's RBF gives the same coefficients and A~(mu)."""
    ezyrb = pytest.importorskip("ezyrb")
    from pydmd import DMD, ParametricDMD

    from dks_gym.models.pdmd import _ReducedCoordinates

    model, _ = fitted(r=6, mu_dependent_decay=True)
    reference, _ = fitted(r=6, mu_dependent_decay=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        pdmd = ParametricDMD(DMD(svd_rank=6), _ReducedCoordinates(), ezyrb.RBF(kernel="multiquadric"))
        coeffs = reference.train_coefficients.numpy().transpose(0, 2, 1)
        pdmd.fit(np.ascontiguousarray(coeffs), reference.train_params.numpy())
    reference._pdmd = pdmd
    mu = np.r_[TEST_MU, TRAIN_MU[[0, 7]], 0.005]
    np.testing.assert_allclose(model.interpolated_coefficients(mu), reference.interpolated_coefficients(mu),
                               rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(model.online_operator(mu).numpy(), reference.online_operator(mu).numpy(),
                               rtol=1e-10, atol=1e-12)


def test_online_operator_reproduces_the_interpolated_coefficients():
    model, _ = fitted(r=6, mu_dependent_decay=True)
    coeffs = model.interpolated_coefficients(TEST_MU)  # (n, n_t, r)
    ops = model.online_operator(TEST_MU).numpy()
    for a, zk in zip(ops, coeffs):
        np.testing.assert_allclose(a @ zk[:-1].T, zk[1:].T, atol=1e-7 * np.abs(zk).max())  # Eq. A4 residual
        rcond = model.online_rtol(zk[:-1].T.shape)
        lstsq = np.linalg.lstsq(zk[:-1], zk[1:], rcond=rcond)[0].T  # independent least squares, same cutoff
        np.testing.assert_allclose(a, lstsq, atol=1e-8)
    z = torch.as_tensor(coeffs[:, 3])
    mu = torch.as_tensor(TEST_MU)
    torch.testing.assert_close(model.forecast(z, mu).numpy(), coeffs[:, 4], atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(model.forecast_jacobian(z, mu), torch.as_tensor(ops))


def test_encode_decode_observe_in_physical_units():
    rng = np.random.default_rng(2)
    modes = rng.standard_normal((5, 3, 64, 64))
    t = np.arange(40)
    mus = np.array([100.0, 300.0, 500.0, 800.0])
    waves = [np.cos(0.1 * np.outer(t, np.arange(1, 6)) + m / 100) for m in mus]
    data = np.stack([np.einsum("tk,kcxy->tcxy", w, modes) for w in waves])
    mean, std = np.array([1.0, -2.0, 1e3]), np.array([0.5, 2.0, 50.0])
    data = (data * std[:, None, None] + mean[:, None, None]).astype(np.float32)
    model = build_model("cylinder", "pdmd", r=5, stats_mean=mean, stats_std=std)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        model.fit(data, mus)
    x = torch.as_tensor(data[1, 7:9], dtype=torch.float64)
    z = model.encode(x, 300.0)
    torch.testing.assert_close(model.decode(z, 300.0), x, rtol=1e-5, atol=1e-5 * 1e3)  # data in the span
    sensors = np.array([5, 700, 4095])
    y = model.observe(z, 300.0, sensors, channel=2)
    torch.testing.assert_close(y, x.flatten(2)[:, 2, sensors], rtol=1e-5, atol=1e-2)
    jac = model.observation_matrix(sensors, 2).double()
    ref = torch.autograd.functional.jacobian(lambda v: model.observe(v[None], 300.0, sensors, 2)[0], z[0])
    torch.testing.assert_close(jac, ref)


def test_fit_streams_from_h5py_and_state_dict_round_trips(tmp_path):
    h5py = pytest.importorskip("h5py")
    data = travelling_waves(TRAIN_MU)
    with h5py.File(tmp_path / "d.h5", "w") as f:
        f.create_dataset("fields", data=data, chunks=(1, *data.shape[1:]))
    with h5py.File(tmp_path / "d.h5", "r") as f, warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        model = build_model("burgers", "pdmd", r=6, stats_mean=[0.5], stats_std=[0.8]).fit(f["fields"], TRAIN_MU)
    reference, _ = fitted(r=6)
    torch.testing.assert_close(model.basis, reference.basis)  # same seed, same data: same fit
    restored = build_model("burgers", "pdmd", r=6)
    restored.load_state_dict(model.state_dict())
    z = torch.randn(len(TEST_MU), 6, dtype=torch.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        torch.testing.assert_close(restored.forecast(z, TEST_MU), model.forecast(z, TEST_MU))
    torch.testing.assert_close(restored.stats_mean, torch.tensor([0.5]))


def test_bad_input_raises():
    model = build_model("burgers", "pdmd", r=6)
    data = travelling_waves(TRAIN_MU[:4])
    with pytest.raises(RuntimeError, match="not fitted"):
        model.encode(torch.as_tensor(data[0]), 0.1)
    with pytest.raises(ValueError, match="shape"):
        model.fit(data[:, :, 0], TRAIN_MU[:4])
    with pytest.raises(ValueError, match="one per trajectory"):
        model.fit(data, TRAIN_MU[:3])
    with pytest.raises(ValueError, match="distinct"):
        model.fit(data, np.ones(4))
    with pytest.raises(ValueError, match="n_t - 1 >= r"):
        build_model("burgers", "pdmd", r=60).fit(data, TRAIN_MU[:4])


def test_exact_decoder_jacobian_equals_autodiff_of_the_decoder():
    """pDMD's closed-form decoder Jacobian against the generic forward-mode one of the base class."""
    from dks_gym.models.latent_model import LatentModel

    model, _ = fitted()
    z = torch.randn(3, model.r, dtype=torch.float64)
    mu = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    exact = model.decoder_jacobian(z, mu)
    autodiff = LatentModel.decoder_jacobian(model, z, mu)
    assert exact.shape == autodiff.shape == (3, model.n_fields, int(np.prod(model.grid)), model.r)
    torch.testing.assert_close(exact, autodiff.to(exact), rtol=1e-10, atol=1e-12)


def test_fit_records_pydmds_condition_number_instead_of_warning():
    """The ill-conditioned stacked coefficients are a diagnostic of the fit, not a warning on every fit."""
    data = travelling_waves(TRAIN_MU)
    model = build_model("burgers", "pdmd", r=6, stats_mean=[0.5], stats_std=[0.8])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        model.fit(data, TRAIN_MU)
    assert model.dmd_condition_number is not None and model.dmd_condition_number > 1e5
    assert model.fit_info["dmd_condition_number"] == model.dmd_condition_number
