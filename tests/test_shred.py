"""SHRED, the non-Bayesian baseline (dks_gym.models.shred): its POD output against numpy's SVD, causality,
reproducibility, that it learns (against the no-sensor estimate), and its bad input."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from dks_gym.dataset import Dataset
from dks_gym.models.shred import Shred, ShredConfig, read_episodes
from dks_gym_agents.shred_baseline import frame_errors

QUICK = ShredConfig(epochs=40, patience=40, noise_seeds=1, rank=8)


@pytest.fixture(scope="module")
def fitted(burgers_small: Path) -> tuple[Shred, Dataset, np.ndarray, np.ndarray]:
    ds = Dataset(burgers_small)
    layout = ds.benchmark.paper_layout(8)
    shred = Shred(ds, layout, noise_level=0.2, config=QUICK).fit()
    n = ds.n_trajectories("test")
    readings = read_episodes(ds, layout, np.arange(n), np.zeros(n, dtype=int), split="test", noise_level=0.2,
                             faults=None)
    return shred, ds, layout, readings


def test_pod_projection_is_numpy_svd_projection(fitted) -> None:
    """The decoder's output space: the leading POD modes of the standardized training snapshots. The floor
    (projection error of the test truth) equals that of numpy's SVD projection onto the same number of modes."""
    shred, ds, _, _ = fitted
    train = np.asarray(ds.fields("train"), dtype=np.float64)
    test = np.asarray(ds.fields("test"), dtype=np.float64)
    mean = train.reshape(-1, *train.shape[2:]).mean(0)
    std = np.asarray(ds.stats_std, dtype=np.float64).reshape(-1, *([1] * (train.ndim - 3)))
    X = ((train - mean) / std).reshape(-1, np.prod(train.shape[2:]))
    V = np.linalg.svd(X, full_matrices=False)[2][: QUICK.rank].T
    Y = ((test - mean) / std).reshape(-1, X.shape[1])
    projected = ((Y @ V @ V.T).reshape(test.shape) * std + mean)
    expected = frame_errors(projected, test, ds.benchmark.scored_indices)
    floor = frame_errors(shred.project(test), test, ds.benchmark.scored_indices)
    np.testing.assert_allclose(floor, expected, rtol=1e-4, atol=1e-12)


def test_reconstruction_is_causal_reproducible_and_learns(fitted, burgers_small: Path) -> None:
    shred, ds, layout, readings = fitted
    mu = ds.params("test")
    estimate = shred.reconstruct(readings, mu)
    assert estimate.shape == (len(readings), ds.n_frames, *ds.fields("test").shape[2:])
    # Causal: readings after frame k do not change the estimate at frames <= k.
    later = readings.copy()
    later[:, 40:] += 1.0
    np.testing.assert_array_equal(shred.reconstruct(later, mu)[:, :40], estimate[:, :40])
    # Missing readings (NaN) are inputs like any other.
    holes = readings.copy()
    holes[:, ::3, ::2] = np.nan
    assert np.isfinite(shred.reconstruct(holes, mu)).all()
    # The same seed gives the same network.
    again = Shred(ds, layout, noise_level=0.2, config=QUICK).fit()
    np.testing.assert_array_equal(again.reconstruct(readings, mu), estimate)
    # It learns: far below the no-sensor estimate (the training mean field, its frame-0 output) on the test split.
    truth = np.asarray(ds.fields("test"))
    mse = frame_errors(estimate, truth, ds.benchmark.scored_indices)[:, 1:].mean()
    mean_field = frame_errors(np.broadcast_to(estimate[:, :1], truth.shape), truth, ds.benchmark.scored_indices)
    assert mse < 0.2 * mean_field[:, 1:].mean()


def test_bad_input_is_refused(fitted, make_synthetic) -> None:
    shred, ds, _, readings = fitted
    with pytest.raises(ValueError, match="readings must be"):
        shred.reconstruct(readings[:, :, :3], ds.params("test"))
    with pytest.raises(RuntimeError, match="fit"):
        Shred(ds, [1, 2]).reconstruct(readings[:, :, :2], ds.params("test"))
    one = Dataset(make_synthetic("burgers", n_train=1))
    with pytest.raises(ValueError, match="at least 2 training trajectories"):
        Shred(one, [1, 2], config=QUICK).fit()


def test_as_an_estimator_it_reconstructs_each_frame_from_its_past(fitted) -> None:
    """The leaderboard's SHRED (dks_gym.evaluation.shred_estimator) estimates frame k from frames 1..k as the
    whole-episode reconstruction does, and the harness scores it as frame_errors scores that reconstruction."""
    from dks_gym.benchmarks.protocol import get_protocol
    from dks_gym.evaluation.estimators import score_estimator
    from dks_gym.evaluation.shred_estimator import ShredEstimator

    shred, ds, layout, readings = fitted
    mu = ds.params("test")
    whole = shred.reconstruct(readings, mu)
    adapter = ShredEstimator(QUICK)
    adapter.shred = shred  # trained by the fixture
    assert adapter.rank == QUICK.rank
    for e in (0, len(readings) - 1):
        for k in (1, 7, ds.n_frames - 1):
            np.testing.assert_allclose(adapter.estimate(readings[e, 1:k + 1], layout, mu[e]), whole[e, k],
                                       rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="layout it was trained on"):
        adapter.estimate(readings[0, 1:3], layout + 1, mu[0])
    protocol = dataclasses.replace(get_protocol("burgers"), default_n_sensors=len(layout), data_preset="small")
    doc = score_estimator(adapter.estimate, "burgers", name="shred", dataset=ds, protocol=protocol)
    truth = np.asarray(ds.fields("test"))
    expected = frame_errors(whole, truth, ds.benchmark.scored_indices)[:, -1]
    np.testing.assert_allclose(doc["records"][0]["per_trajectory_final_mse"], expected, rtol=1e-4)
    assert doc["protocol"]["deviations"] == {"data_preset": "small"}
