"""Importers of The Well's and PDEBench's layouts (`dks-gym data import the-well | pdebench`), and the exporters.

Neither collection can be downloaded in a test, so each layout is exercised on tiny files written here from
the collections' documented layouts (The Well: docs/data_format.md and its WellDataset reader; PDEBench: its
1D Burgers files and FNODataset reader), with values drawn at random and kept: the expected channels,
splits, parameters and statistics are rebuilt from them with numpy, independently of the importer. The
round trips (the project's Burgers `small` data through both layouts, cylinder-shaped data with its cell
types through The Well's) must give back the same fields and the same EKF results. Files that break a
layout must fail with an error naming what is missing, and leave nothing written.

Runtime: a few seconds (three short Burgers EKF runs of one trajectory dominate).
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from dks_gym.cli import main
from dks_gym.dataset import Dataset, LayoutError, export_pdebench, export_the_well, import_pdebench, import_the_well

from .round_trip import assert_round_trip, ekf_run

GRID, N_T, T0, DT = (6, 4), 5, 1.0, 0.25
#: The tiny dataset: split -> [(file stem, Re, number of trajectories)]; Pr is listed but the same everywhere.
WELL_FILES = {"train": [("tiny_Re_100", 100.0, 2), ("tiny_Re_200", 200.0, 2)], "valid": [("tiny_Re_150", 150.0, 1)],
              "test": [("tiny_Re_250", 250.0, 2)]}
WELL_CHANNELS = ("pressure", "tracer", "velocity_x", "velocity_y", "stress_xx", "stress_xy", "stress_yx", "stress_yy")


def _flags(ds: h5py.Dataset, sample: bool, time: bool, dims: list[bool]) -> None:
    ds.attrs.update({"sample_varying": sample, "time_varying": time, "dim_varying": dims})


def _write_well_file(path: Path, re: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """One file of The Well's layout; returns the channels it should import as, (n, N_T, 8, *GRID)."""
    nx, ny = GRID
    pressure = rng.normal(size=(n, N_T, nx, ny)).astype(np.float32)
    tracer = rng.normal(size=(n, N_T, nx)).astype(np.float32)  # constant along y: dim_varying [True, False]
    velocity = rng.normal(size=(n, N_T, nx, ny, 2)).astype(np.float32)
    stress = rng.normal(size=(N_T, nx, ny, 2, 2)).astype(np.float32)  # the same for every trajectory
    with h5py.File(path, "w") as f:
        f.attrs.update({"dataset_name": "Tiny-Flow 2D", "grid_type": "cartesian", "n_spatial_dims": 2,
                        "n_trajectories": n, "simulation_parameters": ["Re", "Pr"], "Re": re, "Pr": 0.7})
        dims = f.create_group("dimensions")
        dims.attrs["spatial_dims"] = ["x", "y"]
        dims.create_dataset("time", data=(T0 + DT * np.arange(N_T)).astype(np.float32)).attrs["sample_varying"] = False
        for axis, size in zip("xy", GRID):
            dims.create_dataset(axis, data=np.linspace(0, 1, size, dtype=np.float32)).attrs.update(
                {"sample_varying": False, "time_varying": False})
        bc = f.create_group("boundary_conditions").create_group("x_periodic")
        bc.attrs.update({"associated_dims": ["x"], "associated_fields": [], "bc_type": "periodic",
                         "sample_varying": False, "time_varying": False})
        bc.create_dataset("mask", data=np.array([True, False, False, False, False, True]))
        scalars = f.create_group("scalars")
        scalars.attrs["field_names"] = ["Re"]
        scalars.create_dataset("Re", data=np.float32(re)).attrs.update({"sample_varying": False, "time_varying": False})
        t0 = f.create_group("t0_fields")
        t0.attrs["field_names"] = ["pressure", "density", "tracer"]
        _flags(t0.create_dataset("pressure", data=pressure), True, True, [True, True])
        _flags(t0.create_dataset("density", data=rng.normal(size=(n, nx, ny)).astype(np.float32)), True, False,
               [True, True])
        _flags(t0.create_dataset("tracer", data=tracer), True, True, [True, False])
        t1 = f.create_group("t1_fields")
        t1.attrs["field_names"] = ["velocity"]
        _flags(t1.create_dataset("velocity", data=velocity), True, True, [True, True])
        t2 = f.create_group("t2_fields")
        t2.attrs["field_names"] = ["stress"]
        _flags(t2.create_dataset("stress", data=stress), False, True, [True, True])
    channels = [pressure, np.repeat(tracer[..., None], ny, axis=-1), velocity[..., 0], velocity[..., 1]]
    channels += [np.broadcast_to(stress[..., a, b], (n, N_T, nx, ny)) for a in range(2) for b in range(2)]
    return np.stack(channels, axis=2)


@pytest.fixture
def well(tmp_path: Path) -> tuple[Path, dict[str, np.ndarray]]:
    """A tiny dataset folder of The Well (root/data/{train,valid,test}) and the fields of each source split."""
    rng = np.random.default_rng(7)
    root, expected = tmp_path / "tiny_flow", {}
    for split, files in WELL_FILES.items():
        (root / "data" / split).mkdir(parents=True)
        expected[split] = np.concatenate([_write_well_file(root / "data" / split / f"{stem}.hdf5", re, n, rng)
                                          for stem, re, n in files])
    return root, expected


def _datasets(path: Path) -> dict[str, np.ndarray]:
    with h5py.File(path, "r") as f:
        return {name: f[name][()] for name in ("train/fields", "train/params", "test/fields", "test/params", "time",
                                               "stats/mean", "stats/std")}


def _expected_params(splits: tuple[str, ...]) -> np.ndarray:
    return np.concatenate([np.full(n, re) for split in splits for _, re, n in WELL_FILES[split]])


def _assert_stats(got: dict[str, np.ndarray], train: np.ndarray) -> None:
    x = np.moveaxis(train.astype(np.float64), 2, 0).reshape(train.shape[2], -1)
    np.testing.assert_allclose(got["stats/mean"], x.mean(axis=1), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(got["stats/std"], x.std(axis=1, ddof=1), rtol=1e-9)


def test_the_well_layout_imports_channels_splits_parameter_and_stats(well, tmp_path: Path) -> None:
    root, expected = well
    out = import_the_well(root, tmp_path / "tiny.h5")
    got = _datasets(out)
    train = np.concatenate([expected["train"], expected["valid"]])  # valid appended to train, by default
    np.testing.assert_array_equal(got["train/fields"], train)
    np.testing.assert_array_equal(got["test/fields"], expected["test"])
    np.testing.assert_array_equal(got["train/params"], _expected_params(("train", "valid")))
    np.testing.assert_array_equal(got["test/params"], _expected_params(("test",)))
    np.testing.assert_allclose(got["time"], T0 + DT * np.arange(N_T))
    _assert_stats(got, train)
    with h5py.File(out, "r") as f:
        assert f.attrs["benchmark"] == "tiny_flow_2d" and f.attrs["param_name"] == "Re"  # the varying one of Re, Pr
        assert tuple(f.attrs["channels"]) == WELL_CHANNELS and f.attrs["observed_channel"] == "pressure"
        assert f.attrs["dt"] == DT and "cell_type" not in f
        generator = __import__("json").loads(f.attrs["generator"])
    assert generator["skipped"] == ["scalars/Re", "t0_fields/density"]
    assert generator["boundary_conditions"] == {"x_periodic": "PERIODIC"}
    bench = Dataset(out).benchmark  # a custom benchmark the package opens as it is
    assert (bench.name, bench.env_id, bench.grid, bench.param_name) == ("tiny_flow_2d", "DKS/Custom-v0",
                                                                        got["train/fields"].shape[3:], "Re")

    dropped = _datasets(import_the_well(root, tmp_path / "drop.h5", valid="drop", observed="velocity_x", name="mine"))
    np.testing.assert_array_equal(dropped["train/fields"], expected["train"])
    _assert_stats(dropped, expected["train"])  # the statistics are the written train split's
    with h5py.File(tmp_path / "drop.h5", "r") as f:
        assert f.attrs["benchmark"] == "mine" and f.attrs["observed_channel"] == "velocity_x"


def _mutate(root: Path, split: str, change) -> None:
    stem = WELL_FILES[split][0][0]
    with h5py.File(root / "data" / split / f"{stem}.hdf5", "r+") as f:
        change(f)


def _replace(f: h5py.File, name: str, data: np.ndarray) -> None:
    attrs = dict(f[name].attrs)
    del f[name]
    f.create_dataset(name, data=data).attrs.update(attrs)


WELL_BREAKS = {
    "root attribute": (lambda f: f.attrs.__delitem__("simulation_parameters"),
                       "missing root attribute 'simulation_parameters'"),
    "t1 group": (lambda f: f.__delitem__("t1_fields"), "missing group 't1_fields'"),
    "time": (lambda f: f.__delitem__("dimensions/time"), "missing dataset 'dimensions/time'"),
    "axis": (lambda f: f.__delitem__("dimensions/y"), "missing dataset 'dimensions/y'"),
    "boundaries": (lambda f: f.__delitem__("boundary_conditions"), "missing group 'boundary_conditions'"),
    "listed field": (lambda f: f.__delitem__("t0_fields/pressure"), "missing dataset 't0_fields/pressure'"),
    "field flag": (lambda f: f["t1_fields/velocity"].attrs.__delitem__("dim_varying"),
                   "missing attribute 'dim_varying' of 't1_fields/velocity'"),
    "field shape": (lambda f: _replace(f, "t0_fields/pressure", np.zeros((2, N_T, 6, 3), np.float32)),
                    r"'t0_fields/pressure' has shape \(2, 5, 6, 3\).*give \(2, 5, 6, 4\)"),
    "uneven time": (lambda f: _replace(f, "dimensions/time", np.array([0, .25, .5, 1, 1.25], np.float32)),
                    "not evenly spaced in time"),
    "other dataset": (lambda f: f.attrs.__setitem__("dataset_name", "other"), "dataset_name other differ"),
}


@pytest.mark.parametrize("case", list(WELL_BREAKS))
def test_a_file_breaking_the_well_layout_names_what_is_missing_and_writes_nothing(well, tmp_path, case) -> None:
    root, _ = well
    change, message = WELL_BREAKS[case]
    _mutate(root, "test", change)
    out = tmp_path / "out" / "x.h5"
    out.parent.mkdir()
    with pytest.raises(LayoutError, match=message) as err:
        import_the_well(root, out)
    assert "tiny_Re_250.hdf5" in str(err.value)  # the offending file is named
    assert not any(out.parent.iterdir())


def test_the_well_folder_errors(well, tmp_path: Path) -> None:
    root, _ = well
    with pytest.raises(LayoutError, match="no folder 'data/train'"):
        import_the_well(tmp_path, tmp_path / "x.h5")
    with pytest.raises(ValueError, match="channels .* not the cylinder benchmark's.*another name"):
        import_the_well(root, tmp_path / "x.h5", name="cylinder")
    _mutate(root, "train", lambda f: f.attrs.__setitem__("Pr", 0.9))  # now Re and Pr both vary
    with pytest.raises(ValueError, match=r"\['Re', 'Pr'\], and 2 of them"):
        import_the_well(root, tmp_path / "x.h5")
    assert import_the_well(root, tmp_path / "x.h5", param="Re").exists()
    for path in (root / "data" / "test").iterdir():
        path.unlink()
    with pytest.raises(LayoutError, match="no .hdf5 or .h5 files .*'test' split"):
        import_the_well(root, tmp_path / "y.h5")


def test_nan_found_late_leaves_no_file(well, tmp_path: Path) -> None:
    root, _ = well
    _mutate(root, "test", lambda f: f["t0_fields/pressure"].__setitem__((1, 3, 0, 0), np.nan))
    out = tmp_path / "out" / "x.h5"
    out.parent.mkdir()
    with pytest.raises(LayoutError, match="tiny_Re_250.hdf5: trajectory 1 holds NaN or inf"):
        import_the_well(root, out)  # the train split was already written when the NaN was read
    assert not any(out.parent.iterdir())


# PDEBench -----------------------------------------------------------------------------------------------------
def _write_pdebench(path: Path, n: int, rng: np.random.Generator, n_t: int = 4, n_x: int = 8) -> np.ndarray:
    u = rng.normal(size=(n, n_t, n_x)).astype(np.float32)
    with h5py.File(path, "w") as f:
        f.create_dataset("tensor", data=u)
        f.create_dataset("x-coordinate", data=((np.arange(n_x) + 0.5) / n_x).astype(np.float32))
        f.create_dataset("t-coordinate", data=(0.01 * np.arange(n_t + 1)).astype(np.float32))  # one more, as PDEBench
    return u


@pytest.fixture
def pdebench(tmp_path: Path) -> tuple[list[Path], list[np.ndarray]]:
    rng = np.random.default_rng(3)
    paths = [tmp_path / "1D_Burgers_Sols_Nu0.001.hdf5", tmp_path / "1D_Burgers_Sols_Nu0.01.hdf5"]
    return paths, [_write_pdebench(p, 10, rng) for p in paths]


def test_pdebench_layout_splits_like_pdebench_or_by_file(pdebench, tmp_path: Path) -> None:
    paths, u = pdebench
    got = _datasets(import_pdebench(paths, tmp_path / "a.h5"))  # PDEBench's rule: the first 10 % of each file
    np.testing.assert_array_equal(got["test/fields"][:, :, 0], np.stack([u[0][0], u[1][0]]))
    np.testing.assert_array_equal(got["train/fields"][:, :, 0], np.concatenate([u[0][1:], u[1][1:]]))
    np.testing.assert_array_equal(got["train/params"], np.repeat([0.001, 0.01], 9))
    np.testing.assert_allclose(got["time"], 0.01 * np.arange(4), rtol=1e-6)
    with h5py.File(tmp_path / "a.h5", "r") as f:
        assert f.attrs["benchmark"] == "pdebench_burgers" and f.attrs["param_name"] == "nu"
        assert np.isclose(f.attrs["dt"], 0.01, rtol=1e-6) and tuple(f.attrs["channels"]) == ("u",)
    bench = Dataset(tmp_path / "a.h5").benchmark
    assert (bench.name, bench.param_range, bench.grid) == ("pdebench_burgers", (0.001, 0.01), (8,))
    _assert_stats(got, got["train/fields"])

    got = _datasets(import_pdebench(paths, tmp_path / "b.h5", test=paths[1:], max_per_file=3))  # each file once
    np.testing.assert_array_equal(got["train/fields"][:, :, 0], u[0][:3])
    np.testing.assert_array_equal(got["test/fields"][:, :, 0], u[1][:3])
    np.testing.assert_array_equal(got["test/params"], [0.01] * 3)


def _pdebench_break(path: Path, change) -> None:
    with h5py.File(path, "r+") as f:
        change(f)


PDEBENCH_BREAKS = {
    "tensor": (lambda f: f.__delitem__("tensor"), "missing dataset 'tensor'"),
    "t-coordinate": (lambda f: f.__delitem__("t-coordinate"), "missing dataset 't-coordinate'"),
    "time length": (lambda f: _replace(f, "t-coordinate", np.arange(7, dtype=np.float32)),
                    r"'t-coordinate' has shape \(7,\); 'tensor' needs \(4,\) or \(5,\)"),
    "2D": (lambda f: _replace(f, "tensor", np.zeros((10, 4, 8, 8), np.float32)), "a 1D file holds"),
    "other grid": (lambda f: _replace(f, "x-coordinate", np.linspace(0, 2, 8, dtype=np.float32)),
                   "'x-coordinate' differs from"),
}


@pytest.mark.parametrize("case", list(PDEBENCH_BREAKS))
def test_a_file_breaking_the_pdebench_layout_names_what_is_missing(pdebench, tmp_path: Path, case) -> None:
    paths, _ = pdebench
    change, message = PDEBENCH_BREAKS[case]
    _pdebench_break(paths[1], change)
    with pytest.raises(LayoutError, match=message) as err:
        import_pdebench(paths, tmp_path / "x.h5")
    assert "Nu0.01.hdf5" in str(err.value) and not (tmp_path / "x.h5").exists()


def test_a_source_that_is_not_hdf5_names_itself_and_writes_nothing(well, pdebench, tmp_path: Path) -> None:
    root, _ = well
    stem = WELL_FILES["train"][0][0]
    (root / "data" / "train" / f"{stem}.hdf5").write_text("not HDF5")
    with pytest.raises(LayoutError, match=rf"{stem}.hdf5 is not a readable HDF5 file"):
        import_the_well(root, tmp_path / "w.h5")
    paths, _ = pdebench
    paths[0].write_bytes(b"\x00" * 64)
    with pytest.raises(LayoutError, match=rf"{paths[0].name} is not a readable HDF5 file"):
        import_pdebench(paths, tmp_path / "p.h5")
    assert not (tmp_path / "w.h5").exists() and not (tmp_path / "p.h5").exists()


def test_pdebench_name_and_split_errors(pdebench, tmp_path: Path) -> None:
    paths, _ = pdebench
    renamed = paths[1].rename(tmp_path / "burgers.hdf5")
    with pytest.raises(LayoutError, match="burgers.hdf5: the file name carries no viscosity.*Nu<value>"):
        import_pdebench([paths[0], renamed], tmp_path / "x.h5")
    with pytest.raises(LayoutError, match="no test trajectories"):
        import_pdebench(paths[:1], tmp_path / "x.h5", max_per_file=5)  # int(5 * 0.1) = 0
    from dks_gym.dataset.importing import parameter_range

    assert parameter_range({"train": np.array([0.001, 0.001]), "test": np.array([0.001])}) == (0.0005, 0.0015)
    assert parameter_range({"train": np.array([0.0]), "test": np.array([0.0])}) == (-0.5, 0.5)
    assert parameter_range({"train": np.array([2.0, 1.0]), "test": np.array([3.0])}) == (1.0, 3.0)
    with pytest.raises(ValueError, match="either whole files"):
        import_pdebench(paths[:1], tmp_path / "x.h5", test=[renamed], test_fraction=0.2)
    assert not (tmp_path / "x.h5").exists()


# Round trips of the project's own data ---------------------------------------------------------------------------
@pytest.fixture(scope="module")
def burgers_ekf(burgers_small: Path) -> tuple[np.ndarray, np.ndarray]:
    return ekf_run(burgers_small, "pdmd")


def test_burgers_small_round_trips_through_the_well(burgers_small, burgers_ekf, tmp_path: Path) -> None:
    files = export_the_well(burgers_small, tmp_path / "well")
    assert len(files["train"]) == 6 and all(p.exists() for p in files["train"] + files["test"])
    assert_round_trip(burgers_small, import_the_well(tmp_path / "well", tmp_path / "b.h5"), burgers_ekf, "pdmd")


def test_burgers_small_round_trips_through_pdebench(burgers_small, burgers_ekf, tmp_path: Path) -> None:
    files = export_pdebench(burgers_small, tmp_path / "pde")
    assert all(p.name.startswith("1D_Burgers_Sols_Nu") for p in files["train"])
    with h5py.File(files["test"][0], "r") as f:
        assert f["tensor"].shape == (1, 100, 1024) and f["t-coordinate"].shape == (101,)
    out = import_pdebench(files["train"], tmp_path / "b.h5", test=files["test"], name="burgers")
    assert_round_trip(burgers_small, out, burgers_ekf, "pdmd")


def test_cylinder_data_and_cell_types_round_trip_through_the_well(make_synthetic, tmp_path: Path) -> None:
    original = make_synthetic("cylinder", n_train=2, n_test=2, n_t=4)
    export_the_well(original, tmp_path / "well")
    with h5py.File(next((tmp_path / "well" / "data" / "test").iterdir()), "r") as f:
        assert list(f["t0_fields"].attrs["field_names"]) == ["p", "cell_type"]
        assert f["t1_fields/velocity"].shape == (1, 4, 64, 64, 2)
        assert f["t0_fields/cell_type"].attrs["time_varying"] == np.False_
    assert_round_trip(original, import_the_well(tmp_path / "well", tmp_path / "c.h5"))


def test_an_interrupted_export_leaves_nothing(burgers_small, tmp_path: Path, monkeypatch) -> None:
    import dks_gym.dataset.the_well as the_well

    calls = []

    def failing(*args):
        calls.append(args)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*args)

    real = the_well._export_file
    monkeypatch.setattr(the_well, "_export_file", failing)
    with pytest.raises(KeyboardInterrupt):
        export_the_well(burgers_small, tmp_path / "well")
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").touch()
    with pytest.raises(FileExistsError, match="not an empty folder"):
        export_pdebench(burgers_small, tmp_path / "full")


def test_cli_imports_both_layouts(well, pdebench, tmp_path: Path) -> None:
    root, _ = well
    runner = CliRunner()
    out = tmp_path / "well.h5"
    result = runner.invoke(main, ["data", "import", "the-well", str(root), "--out", str(out), "--valid", "drop"])
    assert result.exit_code == 0, result.output
    assert "imported 4 train, 2 test trajectories of tiny_flow_2d" in result.output and out.exists()
    result = runner.invoke(main, ["data", "import", "the-well", str(root), "--out", str(out)])
    assert result.exit_code == 1 and "exists" in result.output and "Traceback" not in result.output
    paths, _ = pdebench
    out = tmp_path / "pde.h5"
    result = runner.invoke(main, ["data", "import", "pdebench", str(paths[0]), "--test", str(paths[1]),
                                  "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "imported 10 train, 10 test trajectories of pdebench_burgers (channels u, grid 8" in result.output
    _pdebench_break(paths[0], lambda f: f.__delitem__("tensor"))
    result = runner.invoke(main, ["data", "import", "pdebench", *map(str, paths), "--out", str(tmp_path / "y.h5")])
    assert result.exit_code == 1 and "missing dataset 'tensor'" in result.output and "Traceback" not in result.output
