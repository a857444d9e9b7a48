"""End to end on a flow none of the four benchmarks is (examples/any_flow.py, its small version): Kuramoto-Sivashinsky
trajectories written in The Well's layout, imported, the four models trained, placements ranked with the EKF."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from dks_gym.benchmarks import CustomBenchmark
from dks_gym.cli import main as cli
from dks_gym.dataset import Dataset, import_the_well
from dks_gym.dataset.kuramoto_sivashinsky import DATA_LENGTH, split_values, write_well_folder
from dks_gym.names import MODEL_KINDS
from dks_gym.solvers.kuramoto_sivashinsky import NU_RANGE, small_dataset

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "any_flow.py"


def test_split_values_put_each_test_viscosity_between_two_training_ones() -> None:
    train, test = split_values(32, 12)
    assert train[0] == NU_RANGE[0] and train[-1] == NU_RANGE[1] and len(test) == 12
    gaps = np.searchsorted(train, test)  # the training value above each test value
    np.testing.assert_allclose(test, (train[gaps - 1] + train[gaps]) / 2)
    with pytest.raises(ValueError, match="one per gap"):
        split_values(3, 3)


def test_the_well_folder_imports_as_the_solver_wrote_it(tmp_path: Path) -> None:
    data = small_dataset()
    files = write_well_folder(data, [1, 2], tmp_path / "well")
    assert [len(files[s]) for s in ("train", "test")] == [2, 2]  # one file per viscosity, as The Well
    with pytest.raises(ValueError, match="some, not all"):
        write_well_folder(data, [0, 1, 2, 3], tmp_path / "none")
    ds = Dataset(import_the_well(tmp_path / "well", tmp_path / "ks.h5"))
    assert isinstance(ds.benchmark, CustomBenchmark) and ds.benchmark.name == "kuramoto_sivashinsky"
    assert ds.channels == ("u",) and ds.param_name == "nu" and ds.benchmark.dt == pytest.approx(0.5)
    np.testing.assert_allclose(ds.params("test"), data.nu[[1, 2]])
    np.testing.assert_allclose(ds.trajectory("test", 1)[:, 0], data.u[2], rtol=1e-6, atol=1e-6)
    # The equation conserves the spatial mean (zero here: zero-mean initial conditions), which nothing in the
    # writer or the importer enforces: every imported frame keeps it, to float32 storage and the modes the stored
    # subgrid aliases onto k = 0 (below 1e-6 of the peak, the solver's resolution check). A field of this size
    # without the property has a mean near max|u| / sqrt(64).
    u = np.stack([ds.trajectory("train", i)[:, 0] for i in range(2)]).astype(np.float64)
    assert np.abs(u.mean(axis=-1)).max() < 1e-5 * np.abs(u).max()


def test_the_command_writes_the_l22_data_on_64_points_by_default(tmp_path: Path) -> None:
    import h5py

    def written(*options: str) -> tuple[np.ndarray, np.ndarray]:
        out = tmp_path / "-".join(("well",) + options)
        result = CliRunner().invoke(cli, ["data", "kuramoto-sivashinsky", str(out), "--n-train", "2", "--n-test", "1",
                                          "--frames", "2", *options])
        assert result.exit_code == 0, result.output
        with h5py.File(sorted((out / "data" / "train").iterdir())[0]) as f:
            return f["dimensions/x"][:], f["t0_fields/u"][:]

    # The default domain (DATA_LENGTH = 22, 64 points) and the option: x_j = L j / n on [0, L).
    x, u = written()
    np.testing.assert_allclose(x, DATA_LENGTH * np.arange(64) / 64)
    assert DATA_LENGTH == 22.0 and u.shape[-1] == 64
    x, _ = written("--length", "11", "--points", "32")
    np.testing.assert_allclose(x, 11 * np.arange(32) / 32)


def test_the_example_runs_end_to_end_and_the_command_ranks_its_file(tmp_path: Path, monkeypatch) -> None:
    import dks_gym.assimilation.tuning as tuning
    import dks_gym.models.training as training
    import dks_gym_agents.evaluate as evaluate

    # The figures (loss curves, layouts) and the depth of the Q-scale bisection cost seconds and are tested
    # elsewhere; the chain is what runs here.
    monkeypatch.setattr(training, "write_loss_curves", lambda *args: None)
    monkeypatch.setattr(evaluate, "layout_figure", lambda *args: None)
    monkeypatch.setattr(tuning, "BISECTIONS", 1)
    spec = importlib.util.spec_from_file_location("any_flow", EXAMPLE)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    rankings = example.main(tmp_path, small=True)
    assert list(rankings) == list(MODEL_KINDS)
    for kind, doc in rankings.items():
        assert doc["benchmark"] == "kuramoto_sivashinsky" and "protocol" not in doc  # no protocol: a custom flow
        rows = {rec["policy"]: rec for rec in doc["records"]}
        assert set(rows) == {"paper", "qr", "forward"}, kind
        assert all(np.isfinite(rec["time_mean_mse_mean"]) for rec in rows.values())
        # the lattice rule: the centres of 4 equal intervals of the 64 cells, each to a nearest cell
        np.testing.assert_allclose(rows["paper"]["sensors"], 16 * np.arange(4) + 7.5, atol=0.5)
        assert (tmp_path / kind / "placement.md").read_text().count("| paper") == 1
    result = CliRunner().invoke(cli, ["evaluate-placement", "--data", str(tmp_path / "ks.h5"), "--model", "pdmd",
                                      "--r", "4", "--n-sensors", "4", "--policies", "qr",
                                      "--out", str(tmp_path / "cli")])
    assert result.exit_code == 0, result.output
    ranked = {rec["policy"]: rec["time_mean_mse_mean"] for rec in rankings["pdmd"]["records"]}
    assert f"{ranked['qr']:.3e}" in result.output  # the command ranks the file as the example's Python does

