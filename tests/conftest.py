"""Shared fixtures: a private data home, a generated Burgers `small` dataset, synthetic CFD-shaped files."""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MPLBACKEND", "Agg")

from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(1)


@pytest.fixture(scope="session", autouse=True)
def data_home(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A data home private to the test session, for every test (the user's cache, its lock folder included,
    is never touched)."""
    home = tmp_path_factory.mktemp("dks_home")
    os.environ["DKS_GYM_HOME"] = str(home)
    return home


@pytest.fixture(scope="session")
def burgers_small(data_home: Path) -> Path:
    """The real Burgers `small` preset, generated once per session."""
    from dks_gym.dataset import generate_dataset

    return generate_dataset("burgers", "small", progress=False)


@pytest.fixture(scope="session")
def burgers_paper(data_home: Path) -> Path:
    """The real Burgers `paper` preset (the data the shipped models were trained on), generated once per
    session (about 5 s)."""
    from dks_gym.dataset import generate_dataset

    return generate_dataset("burgers", "paper", progress=False)


def synthetic_data(benchmark: str, n_train: int = 2, n_test: int = 2, n_t: int = 4, seed: int = 0):
    """GeneratedData in a benchmark's exact shapes, filled with smooth random travelling waves.

    Used to exercise the dataset layer and the environments on benchmarks whose generators need
    external solvers; values are arbitrary but finite and trajectory-dependent.
    """
    from dks_gym.benchmarks import GeneratedData, get_benchmark

    bench = get_benchmark(benchmark)
    rng = np.random.default_rng(seed)
    coords = bench.coords()
    mesh = np.meshgrid(*coords, indexing="ij")
    params = {
        "train": np.sort(rng.uniform(*bench.param_range, size=n_train)),
        "test": np.sort(rng.uniform(*bench.param_range, size=n_test)),
    }
    time = bench.dt * np.arange(n_t)
    store: dict[tuple[str, int], np.ndarray] = {}
    for split, values in params.items():
        for i, mu in enumerate(values):
            phase = rng.uniform(0, 2 * np.pi, size=len(bench.channels))
            traj = np.empty((n_t, len(bench.channels), *bench.grid), dtype=np.float32)
            for k in range(n_t):
                for c in range(len(bench.channels)):
                    arg = sum(m / (np.ptp(x) + 1e-12) for m, x in zip(mesh, coords)) * 2 * np.pi
                    traj[k, c] = (1.0 + c) * np.sin(arg + phase[c] + 0.3 * k) + 1e-3 * mu
            store[(split, i)] = traj
    return GeneratedData(
        time=time,
        params=params,
        trajectories=iter((s, i, a) for (s, i), a in store.items()),
        generator={"name": "tests.synthetic", "seed": seed},
        coords=coords,
        cell_type=bench.cell_type(),
    )


@pytest.fixture
def make_synthetic(tmp_path: Path):
    """Write a synthetic dataset for a benchmark and return its path."""
    from dks_gym.dataset import write_dataset

    def make(benchmark: str, **kwargs) -> Path:
        path = tmp_path / f"{benchmark}-synthetic.h5"
        write_dataset(synthetic_data(benchmark, **kwargs), benchmark, path)
        return path

    return make


@pytest.fixture(scope="session")
def dask_client():
    """A client of a Dask LocalCluster of two single-threaded workers in this process (started in about a
    second; dks_gym.parallel pickles every task and result itself, so they travel as to a real cluster)."""
    distributed = pytest.importorskip("distributed", reason="dask distributed is optional (pip install "
                                                            "'dks-gym[cluster]')")
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None)
    client = distributed.Client(cluster)
    yield client
    client.close()
    cluster.close()


#: What a run measures rather than computes (wall times, when it ran): the only fields that differ between two
#: runs of the same thing.
MEASURED = frozenset({"da_step_seconds", "wall_time", "wall_time_s", "created", "fit_seconds", "offline_seconds",
                      "decision_seconds", "train_seconds"})


def without_times(doc):
    """A results document with the measured fields (:data:`MEASURED`) taken out, everywhere in it."""
    if isinstance(doc, dict):
        return {k: without_times(v) for k, v in doc.items() if k not in MEASURED}
    if isinstance(doc, list):
        return [without_times(v) for v in doc]
    return doc
