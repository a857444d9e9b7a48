"""The check of a round trip through another collection's layout: the same data, the same filter results."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dks_gym.dataset import Dataset


def ekf_run(path: Path, kind: str = "koopman") -> tuple[np.ndarray, np.ndarray]:
    """A short EKF run of one test trajectory, the paper's Q and P0: per-frame MSE and the final estimate.

    The model is built from the file: ``koopman``, an untrained lite model taking the file's statistics and
    cell types (an input channel); ``pdmd``, POD + parametric DMD fitted on the file's train split and
    parameters (the cheaper run on a long grid)."""
    from dks_gym.assimilation import run_assimilation
    from dks_gym.models import build_model

    with Dataset(path) as ds:
        model = build_model(ds.benchmark, kind, r=8, preset="lite", dataset=ds, seed=0)
        if kind == "pdmd":
            model.fit_dataset(ds)
        result = run_assimilation(model, ds, Q="paper", P0="paper", uncertainty=False, trajectories=[0])
    return result.step_mse, result.final_estimate


def assert_same_dataset(a: Path, b: Path) -> None:
    """Same benchmark, channels, dt, fields, parameters, statistics and cell types; times to float32 round-off."""
    with Dataset(a) as x, Dataset(b) as y:
        assert x.benchmark.name == y.benchmark.name and x.channels == y.channels and x.dt == y.dt
        for split in ("train", "test"):
            np.testing.assert_array_equal(x.fields(split)[()], y.fields(split)[()])
            np.testing.assert_array_equal(x.params(split), y.params(split))
        np.testing.assert_allclose(x.time, y.time, rtol=1e-6, atol=1e-7)  # The Well and PDEBench store float32
        np.testing.assert_allclose(x.stats_mean, y.stats_mean, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(x.stats_std, y.stats_std, rtol=1e-12)
        assert (x.cell_type is None and y.cell_type is None) or np.array_equal(x.cell_type, y.cell_type)


def assert_round_trip(original: Path, imported: Path, reference: tuple[np.ndarray, np.ndarray] | None = None,
                      kind: str = "koopman") -> None:
    """Same fields, parameters, statistics and cell types, and the same EKF results to round-off (``reference``:
    the original's :func:`ekf_run`, when already run)."""
    assert_same_dataset(original, imported)
    for want, got in zip(reference or ekf_run(original, kind), ekf_run(imported, kind)):
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-9)
