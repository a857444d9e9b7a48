"""The predictive std of the decoded estimate (``estimate_std``) and its scores, each against something independent.

* the decoder-Jacobian variance diag(G P G^T) against the Monte-Carlo variance of decoded latent draws;
* on a problem where the model is exact (linear latent dynamics with the true process noise, a linear
  decoder, the env's own measurement noise), the 95 % coverage is 0.95, the NEES and the spread-skill ratio 1
  within sampling error and the EnKF's rank histograms flat, and a filter told a too-small process noise fails
  the same check;
* the closed-form Gaussian CRPS against a numerical integral of its definition;
* the EnKF's std against the spread of its members decoded here; the reconstruction variance against a
  direct numpy computation; the wrappers' infos, the results records and the figure.
"""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from scipy import integrate, stats

import dks_gym  # noqa: F401  (registers the env ids)
from dks_gym.assimilation import (
    AssimilationConfig,
    FilterConfig,
    calibrate_process_noise,
    process_noise_scale,
    gaussian_crps,
    gaussian_scores,
    jacobian_variance,
    reconstruction_variance,
    run_assimilation,
    tune_process_noise,
)
from dks_gym.benchmarks import GeneratedData, get_benchmark
from dks_gym.dataset import Dataset, write_dataset
from dks_gym.evaluation.figures import uncertainty_figure
from dks_gym.evaluation.results import make_record, new_results, validate_record
from dks_gym.models import LatentModel, benchmark_shape, build_model
from dks_gym.models.checkpoint import read_checkpoint, save_checkpoint, update_calibration
from dks_gym.models.calibration import calibrate
from dks_gym.wrappers import LatentFilter, Uncertainty
from dks_gym.wrappers.vector import LatentFilterVectorEnv

KINDS = ("koopman", "mlp", "xlstm", "pdmd")


@pytest.fixture(scope="module")
def models(burgers_small: Path) -> dict:
    """Untrained lite models (pDMD fitted), as in test_wrappers: the plumbing does not depend on training."""
    ds = Dataset(burgers_small)
    out = {kind: build_model("burgers", kind, r=8, preset="lite", dataset=ds, seed=0) for kind in KINDS}
    out["pdmd"].fit_dataset(ds)
    for model in out.values():  # what training stores, for the default calibrated Q and P0
        model.calibration = calibrate(model, ds, [0, 1])
    return out


# (a) diag(G P G^T) against Monte Carlo ------------------------------------------------------------------
def _monte_carlo_variance(model, z: torch.Tensor, mu: torch.Tensor, P: torch.Tensor, n: int, seed: int):
    """Sample variance over n draws z_i ~ N(z, P) of decode(z_i), per element, (B, C * n_cells)."""
    g = torch.Generator().manual_seed(seed)
    L = torch.linalg.cholesky(P)
    out = []
    with torch.no_grad():
        for b in range(z.shape[0]):
            draws = z[b] + torch.randn(n, z.shape[1], generator=g, dtype=z.dtype) @ L[b].T
            fields = model.decode(draws, mu[b].expand(n)).flatten(1)
            out.append(fields.var(0))
    return torch.stack(out)


@pytest.mark.parametrize("kind", ["mlp", "pdmd"])  # autodiff JVPs through a conv decoder; pDMD's exact G
def test_decoder_jacobian_variance_equals_monte_carlo(models: dict, kind: str) -> None:
    model = copy.deepcopy(models["pdmd"]) if kind == "pdmd" else build_model("burgers", "mlp", 8, "lite")
    model = model.double()
    torch.manual_seed(0)
    B, r, n = 2, model.r, 16000
    z = 0.5 * torch.randn(B, r, dtype=torch.float64)
    mu = torch.tensor([0.05, 0.5], dtype=torch.float64)
    M = torch.randn(B, r, r, dtype=torch.float64)
    P = 1e-4 * (M @ M.mT / r + 0.1 * torch.eye(r, dtype=torch.float64))  # small: the decoder is ~linear
    mc = _monte_carlo_variance(model, z, mu, P, n, seed=1)
    cells = mc > 1e-3 * mc.max(dim=1, keepdim=True).values  # cells with non-negligible variance
    assert cells.float().mean() > 0.5
    sd = math.sqrt(2 / n)  # the relative std of a sample variance from n Gaussian draws

    def relative_errors(P: torch.Tensor) -> torch.Tensor:
        return ((jacobian_variance(model, z, mu, P).flatten(1) - mc).abs() / mc)[cells]

    # Every cell within 5 sampling stds (max over ~2000 correlated cells), the average within 2.
    rel = relative_errors(P)
    assert float(rel.max()) < 5 * sd and float(rel.mean()) < 2 * sd, (float(rel.max()), float(rel.mean()), sd)
    # The check can fail: a covariance 15 % too large is caught.
    wrong = relative_errors(1.15 * P)
    assert float(wrong.mean()) > 5 * sd


# (b) calibration where the model is exact --------------------------------------------------------------
N_CELLS, R_LIN, Q_TRUE = 1024, 4, 0.01


class LinearLatentModel(LatentModel):
    """z_{k+1} = A z_k, x = D z on the Burgers grid: a model the Kalman filter is exact for."""

    kind = "linear"

    def __init__(self, D: np.ndarray, A: np.ndarray) -> None:
        super().__init__(benchmark_shape("burgers"), D.shape[1])
        self.register_buffer("D", torch.as_tensor(D, dtype=torch.float64))
        self.register_buffer("A", torch.as_tensor(A, dtype=torch.float64))

    def encode(self, x, mu):
        x = self._fields(x).flatten(1).double()
        return torch.linalg.lstsq(self.D, x.T).solution.T

    def decode(self, z, mu):
        z = self._latent(z)
        return (z @ self.D.to(z).T).view(z.shape[0], 1, N_CELLS)

    def forecast(self, z, mu):
        z = self._latent(z)
        return z @ self.A.to(z).T

    def forecast_jacobian(self, z, mu):
        z = self._latent(z)
        return self.A.to(z).expand(z.shape[0], -1, -1)


def _linear_problem(tmp_path: Path, n_test: int = 16, n_t: int = 40,
                    n_train: int = 2) -> tuple[LinearLatentModel, Path]:
    """A Burgers-shaped dataset drawn from the linear model with process noise N(0, Q_TRUE I)."""
    bench = get_benchmark("burgers")
    x = bench.coords()[0]
    D = np.stack([np.sin(2 * np.pi * x), np.cos(2 * np.pi * x), np.sin(4 * np.pi * x), np.cos(6 * np.pi * x)], 1)
    rot = lambda a: np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])  # noqa: E731
    A = 0.97 * np.block([[rot(0.2), np.zeros((2, 2))], [np.zeros((2, 2)), rot(-0.35)]])
    rng = np.random.default_rng(0)
    params = {"train": np.linspace(0.1, 0.2, n_train), "test": np.linspace(0.05, 0.9, n_test)}

    def trajectories():
        for split, values in params.items():
            for i in range(len(values)):
                z = rng.normal(size=R_LIN)
                frames = []
                for _ in range(n_t):
                    frames.append((D @ z)[None])
                    z = A @ z + math.sqrt(Q_TRUE) * rng.normal(size=R_LIN)
                yield split, i, np.stack(frames).astype(np.float32)

    data = GeneratedData(time=bench.dt * np.arange(n_t), params=params, trajectories=trajectories(),
                         generator={"name": "tests.linear"}, coords=bench.coords(), cell_type=bench.cell_type())
    return LinearLatentModel(D, A), write_dataset(data, "burgers", tmp_path / "linear.h5")


def _calibration(result) -> tuple[float, float, float, float]:
    """Coverage and NEES averaged over frames 1.. and trajectories, with their standard errors across trajectories."""
    cov = result.step_coverage[:, 1:].mean(1)
    nees = result.step_nees[:, 1:].mean(1)
    se = lambda v: float(v.std(ddof=1) / math.sqrt(len(v)))  # noqa: E731
    return float(cov.mean()), se(cov), float(nees.mean()), se(nees)


def _spread_skill(result) -> tuple[float, float]:
    """The spread-skill ratio over frames 1.. and trajectories (squares averaged first), and its standard
    error across trajectories."""
    predicted, mse = result.step_predicted_mse[:, 1:], result.step_mse[:, 1:]
    per_trajectory = np.sqrt(predicted.sum(1) / mse.sum(1))
    return math.sqrt(predicted.sum() / mse.sum()), float(per_trajectory.std(ddof=1) / math.sqrt(len(mse)))


def test_coverage_and_nees_are_calibrated_where_the_model_is_exact(tmp_path: Path) -> None:
    model, path = _linear_problem(tmp_path)
    config = AssimilationConfig(filter=FilterConfig(kind="ekf", initial="exact", P0=1e-6, Q=Q_TRUE),
                                noise_level=0.1, split="test")
    result = run_assimilation(model, path, config, dtype=torch.float64)
    cov, cov_se, nees, nees_se = _calibration(result)
    assert abs(cov - 0.95) < max(4 * cov_se, 0.01), (cov, cov_se)
    assert abs(nees - 1.0) < max(4 * nees_se, 0.05), (nees, nees_se)
    ratio, ratio_se = _spread_skill(result)  # measured 1.012 (0.018)
    assert abs(ratio - 1.0) < max(4 * ratio_se, 0.03), (ratio, ratio_se)
    # One trajectory's ratio at one frame is biased high (E[1/RMSE] > 1/sqrt(E[MSE]); 4 latent dimensions):
    # why the records average the squares over the trajectories before dividing. Measured 1.27.
    assert np.mean(np.sqrt(result.step_predicted_mse / result.step_mse)[:, 1:]) > ratio + 0.15
    # The record's ratio at the final frame, from the final fields directly.
    err2 = ((result.final_estimate - result.final_truth).astype(np.float64) ** 2).mean(axis=(1, 2))
    var = (result.final_estimate_std.astype(np.float64) ** 2).mean(axis=(1, 2))
    assert result.spread_skill[-1] == pytest.approx(math.sqrt(var.mean() / err2.mean()), rel=1e-5)
    # The check can fail: a filter that assumes 100x less process noise is overconfident.
    wrong = run_assimilation(model, path, config.replace(Q=Q_TRUE / 100), dtype=torch.float64)
    cov_w, _, nees_w, _ = _calibration(wrong)
    assert cov_w < cov - 0.1 and nees_w > 2 * nees, (cov_w, nees_w)
    assert _spread_skill(wrong)[0] < 0.5  # measured 0.13
    # The EnKF's decoded spread is calibrated too, within its sampling error at 200 members, and the truth is
    # one more member: its rank among the 200 is uniform (measured p = 0.40 at the sensors, 0.44 at the cells).
    enkf = run_assimilation(model, path, config.replace(kind="enkf", n_members=200), dtype=torch.float64)
    cov_e, cov_e_se, nees_e, nees_e_se = _calibration(enkf)
    assert abs(cov_e - 0.95) < max(4 * cov_e_se, 0.02), (cov_e, cov_e_se)
    assert abs(nees_e - 1.0) < max(4 * nees_e_se, 0.1), (nees_e, nees_e_se)
    ratio_e, ratio_e_se = _spread_skill(enkf)
    assert abs(ratio_e - 1.0) < max(4 * ratio_e_se, 0.03), (ratio_e, ratio_e_se)
    steps, sensors = enkf.step_mse.shape[1] - 1, config.n_sensors
    for counts, cells in ((enkf.rank_histogram_sensors, sensors), (enkf.rank_histogram_cells, 8)):
        assert counts.shape == (201,) and counts.sum() == len(enkf.trajectories) * steps * cells
        assert stats.chisquare(counts).pvalue > 0.01, counts


def test_tuned_q_scale_recovers_the_true_process_noise(tmp_path: Path) -> None:
    """Told 1/100 of the true process noise, the tuning finds the factor back from held-out coverage alone."""
    model, path = _linear_problem(tmp_path, n_test=2, n_train=12)
    ds = Dataset(path)
    eye = torch.eye(R_LIN, dtype=torch.float64)
    model.calibration = {"Q": eye * Q_TRUE / 100, "P0": eye, "P0_exact": eye * Q_TRUE,
                         "trajectories": torch.arange(12)}
    tuned = tune_process_noise(model, ds)
    # Coverage grows with the scale, and bisection brackets 0.95 ever tighter.
    scales, coverages = zip(*sorted(tuned["evaluations"]))
    assert all(np.diff(coverages) >= -0.01), tuned["evaluations"]
    assert abs(tuned["coverage"] - 0.95) < 0.01, tuned
    assert 100 / 2 < tuned["scale"] < 100 * 2, tuned  # the true Q is 100 x the calibrated one
    # Before tuning, Q="calibrated" runs unscaled and says so once; the explicit call stores the scale, and
    # Q="calibrated" resolves to the scaled Q.
    with pytest.warns(UserWarning, match="dks-gym calibrate"):
        torch.testing.assert_close(FilterConfig().process_noise(model), eye * Q_TRUE / 100)
    scale = calibrate_process_noise(model, ds)
    assert float(model.calibration["Q_scale"]) == scale == tuned["scale"]
    assert process_noise_scale(model) == scale
    torch.testing.assert_close(FilterConfig().process_noise(model), eye * Q_TRUE / 100 * scale)


def test_tuning_refuses_bad_input_clearly(models: dict, burgers_small: Path) -> None:
    ds = Dataset(burgers_small)
    model = copy.deepcopy(models["koopman"])
    with pytest.raises(ValueError, match="target coverage must lie in"):
        tune_process_noise(model, ds, target=1.5)
    model.calibration = {k: v for k, v in model.calibration.items() if k != "trajectories"}
    with pytest.raises(ValueError, match="calibrate it first"):
        tune_process_noise(model, ds)
    model.calibration.pop("Q_scale", None)
    assert calibrate_process_noise(model, ds, write=False) == 1.0  # an older checkpoint: scale 1


def test_q_scale_is_written_into_the_checkpoint(models: dict, tmp_path: Path) -> None:
    model = copy.deepcopy(models["koopman"])
    path = save_checkpoint(tmp_path / "m.safetensors", model, {"note": "kept"}, training_tensors={"x": torch.ones(2)})
    update_calibration(path, {**model.calibration, "Q_scale": torch.tensor(7.0, dtype=torch.float64)})
    back = read_checkpoint(path)
    assert back.metadata["note"] == "kept" and torch.equal(back.training["x"], torch.ones(2))
    for name, value in model.state_dict().items():
        assert torch.equal(back.model_state[name], value), name
    assert float(back.calibration["Q_scale"]) == 7.0
    torch.testing.assert_close(back.calibration["Q"], model.calibration["Q"])


# (c) CRPS ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("mu, sigma, x", [(0.0, 1.0, 0.0), (1.5, 0.3, 0.2), (-2.0, 4.0, 5.0), (0.1, 1e-2, 0.1003)])
def test_gaussian_crps_equals_the_integral_of_its_definition(mu: float, sigma: float, x: float) -> None:
    F = lambda y: 0.5 * (1.0 + math.erf((y - mu) / (sigma * math.sqrt(2.0))))  # noqa: E731
    below = integrate.quad(lambda y: F(y) ** 2, mu - 40 * sigma, x, limit=200, epsabs=1e-13)[0]
    above = integrate.quad(lambda y: (1.0 - F(y)) ** 2, x, mu + 40 * sigma, limit=200, epsabs=1e-13)[0]
    assert gaussian_crps(x, mu, sigma) == pytest.approx(below + above, rel=1e-7, abs=1e-12)


def test_gaussian_scores_match_a_direct_numpy_computation() -> None:
    rng = np.random.default_rng(3)
    est = rng.normal(size=(3, 2, 50))
    std = rng.uniform(0.1, 2.0, size=est.shape)
    truth = est + std * rng.normal(size=est.shape) * 1.5
    scores = gaussian_scores(torch.from_numpy(est), torch.from_numpy(std), torch.from_numpy(truth), (1,))
    e, s, t = est[:, 1], std[:, 1], truth[:, 1]
    np.testing.assert_allclose(scores["coverage"], np.mean(np.abs(t - e) <= 1.959963984540054 * s, axis=1))
    np.testing.assert_allclose(scores["nees"], np.mean(((t - e) / s) ** 2, axis=1))
    np.testing.assert_allclose(scores["crps"], np.mean(gaussian_crps(t, e, s), axis=1))


def test_gaussian_scores_of_an_overconfident_float32_filter_match_float64() -> None:
    # |z| from 0 to 40: past 13.2 exp(-z^2 / 2) leaves the normal float32 numbers (floored in gaussian_scores)
    z = np.linspace(-40.0, 40.0, 2001).reshape(1, 1, -1)
    std = np.full_like(z, 0.3)
    est, truth = np.zeros_like(z), z * std
    as32 = [torch.from_numpy(a.astype(np.float32)) for a in (est, std, truth)]
    scores = gaussian_scores(*as32, (0,))
    np.testing.assert_allclose(scores["crps"], np.mean(gaussian_crps(truth, est, std), axis=(1, 2)), rtol=2e-6)
    np.testing.assert_allclose(scores["nees"], np.mean(z**2, axis=(1, 2)), rtol=2e-6)


# (d) the wrappers --------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("filt", ["ekf", "enkf", "forward"])
def test_latent_filter_info_has_estimate_std(models: dict, kind: str, filt: str) -> None:
    env = LatentFilter(gym.make("DKS/Burgers-v0", preset="small"), model=models[kind], filter=filt,
                       config=FilterConfig(n_members=8))
    _, info = env.reset(seed=0)
    for _ in range(2):
        _, _, _, _, info = env.step(None)
        std = info["estimate_std"]
        assert std.shape == info["estimate"].shape == (1, 1024) and std.dtype == np.float32
        assert np.all(np.isfinite(std)) and np.all(std >= 0) and np.any(std > 0)
        assert 0.0 <= info["coverage"] <= 1.0 and info["nees"] >= 0 and info["crps"] >= 0
        # spread over skill: sqrt(mean std^2 / MSE) over the scored cells
        assert info["spread_skill"] == pytest.approx(math.sqrt(np.mean(std.astype(np.float64) ** 2) / info["mse"]),
                                                     rel=1e-4)
    env.close()


def test_enkf_std_is_the_spread_of_its_decoded_members(models: dict) -> None:
    model = models["koopman"]
    recon = np.full((1, 1024), 1e-3)
    env = LatentFilter(gym.make("DKS/Burgers-v0", preset="small"), model=model, filter="enkf",
                       config=FilterConfig(n_members=6), uncertainty=Uncertainty(reconstruction_var=recon))
    env.reset(seed=1)
    _, _, _, _, info = env.step(None)
    E = env.filter.ensemble[0]
    with torch.no_grad():
        members = model.decode(E, torch.full((len(E),), info["mu"])).double().numpy()
    expected = np.sqrt(members.var(axis=0, ddof=1) + recon)
    np.testing.assert_allclose(info["estimate_std"], expected, rtol=1e-4, atol=1e-7)
    env.close()


def test_reconstruction_variance_adds_to_the_filter_variance(models: dict, burgers_small: Path) -> None:
    model = models["pdmd"]
    ds = Dataset(burgers_small)
    recon = reconstruction_variance(model, ds, [0, 1], split="train")
    # Directly: the POD projection error of every frame, in numpy.
    U = model.basis.double().numpy()
    mean, sd = ds.stats_mean[0], ds.stats_std[0]
    errs = []
    for t in (0, 1):
        x = ds.trajectory("train", t)[:, 0].astype(np.float64)
        xn = (x - mean) / sd
        errs.append(((xn @ U @ U.T - xn) * sd) ** 2)
    np.testing.assert_allclose(recon, np.concatenate(errs).mean(0)[None], rtol=1e-3, atol=1e-9)
    # Added to the filter's variance: given explicitly, or by default the model's calibrated one.
    calibrated = copy.deepcopy(model)
    calibrated.calibration = dict(model.calibration,
                                  reconstruction_variance=torch.as_tensor(recon, dtype=torch.float32))
    stds = []
    for m, rv in ((model, 0.0), (model, recon), (calibrated, None)):
        env = LatentFilter(gym.make("DKS/Burgers-v0", preset="small"), model=m, filter="ekf",
                           uncertainty=Uncertainty(reconstruction_var=rv))
        env.reset(seed=0)
        stds.append(env.step(None)[4]["estimate_std"].astype(np.float64))
        env.close()
    np.testing.assert_allclose(stds[1] ** 2, stds[0] ** 2 + recon, rtol=1e-4, atol=1e-10)
    np.testing.assert_allclose(stds[2], stds[1], rtol=1e-5)
    with pytest.raises(ValueError, match="shape"):
        LatentFilter(gym.make("DKS/Burgers-v0", preset="small"), model=model,
                     uncertainty=Uncertainty(reconstruction_var=np.ones(1024)))


def test_vector_env_infos_and_switching_uncertainty_off(models: dict) -> None:
    venv = LatentFilterVectorEnv("burgers", 3, model=models["mlp"], filter="ekf", preset="small")
    _, infos = venv.reset(seed=0)
    _, _, _, _, infos = venv.step(np.zeros(3, dtype=np.int64))
    assert infos["estimate_std"].shape == infos["estimate"].shape == (3, 1, 1024)
    assert np.all(infos["estimate_std"] >= 0) and np.all(np.isfinite(infos["estimate_std"]))
    for name in ("coverage", "nees", "crps", "spread_skill"):
        assert infos[name].shape == (3,)
    venv.close()
    off = LatentFilterVectorEnv("burgers", 2, model=models["mlp"], filter="ekf", preset="small", uncertainty=False)
    off.reset(seed=0)
    infos = off.step(np.zeros(2, dtype=np.int64))[4]
    assert not {"estimate_std", "coverage", "nees", "crps", "spread_skill"} & set(infos)
    off.close()
    env = LatentFilter(gym.make("DKS/Burgers-v0", preset="small"), model=models["mlp"], uncertainty=False)
    env.reset(seed=0)
    assert "estimate_std" not in env.step(None)[4]
    env.close()


def test_results_records_hold_the_scores(models: dict, burgers_small: Path) -> None:
    result = run_assimilation(models["koopman"], burgers_small, AssimilationConfig(), trajectories=[0, 1])
    assert result.step_coverage.shape == result.step_mse.shape
    assert result.final_estimate_std.shape == result.final_estimate.shape
    rec = make_record(result, experiment="main")
    validate_record(rec)
    assert rec["final_coverage_mean"] == pytest.approx(float(result.step_coverage[:, -1].mean()))
    assert len(rec["per_step_nees_mean"]) == len(rec["per_step_mse_mean"])
    json.dumps(new_results("burgers", "lite", {"path": "x.h5"}, {}, [rec]), allow_nan=False)
    off = run_assimilation(models["koopman"], burgers_small, AssimilationConfig(), trajectories=[0],
                           uncertainty=False)
    rec_off = make_record(off, experiment="main")
    validate_record(rec_off)
    assert off.step_crps is None and rec_off["final_crps_mean"] is None and rec_off["per_step_crps_mean"] is None


# Figures -----------------------------------------------------------------------------------------------
def _is_png(path: Path) -> bool:
    return path.exists() and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_uncertainty_figure_writes_pngs(models: dict, tmp_path: Path) -> None:
    env = LatentFilter(gym.make("DKS/Burgers-v0", preset="small"), model=models["pdmd"], filter="ekf")
    env.reset(seed=0)
    chosen, est, std, truth = (1, 5, 20), [], [], []
    for k in range(1, max(chosen) + 1):
        info = env.step(None)[4]
        if k in chosen:
            est.append(info["estimate"]), std.append(info["estimate_std"]), truth.append(env.unwrapped.true_state)
    coords = env.unwrapped.dataset.coords
    env.close()
    assert _is_png(uncertainty_figure(np.stack(est), np.stack(std), np.stack(truth), coords, tmp_path / "a.png",
                                      steps=chosen, channel_name="u", title="Burgers"))
    rng = np.random.default_rng(0)
    for grid in ((16, 12), (8, 8, 6)):
        fields = rng.normal(size=(2, 3, *grid))
        coords = tuple(np.linspace(0, 1, n) for n in grid)
        mask = np.ones(grid, dtype=bool)
        path = uncertainty_figure(fields, np.abs(fields), fields + 0.1, coords, tmp_path / f"{len(grid)}d.png",
                                  channel=2, fluid_mask=mask, title="synthetic")
        assert _is_png(path)
    with pytest.raises(ValueError, match="shape"):
        uncertainty_figure(fields, fields[:1], fields, coords, tmp_path / "bad.png")
