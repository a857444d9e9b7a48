"""The OpenFOAM runner and the cylinder / dambreak `small` presets, run end to end through the real solvers.

Both presets go through the user-facing paths (`dks-gym data generate cylinder --preset small` and
`generate_dataset("dambreak", "small")`), then Gymnasium's `check_env`. Independent references: scipy's
LinearNDInterpolator (resampling weights), exactness of linear interpolation on linear fields,
conservation of water volume (volume inside + outflow through the top), continuity (the volume flux
through every grid column equals the inflow), the exact initial water volume of the column, and a rerun /
an interrupted run / a Dask run reproducing an uninterrupted one bit for bit.

Runtime: about 45-60 s on 2 cores (each small preset is generated once per module).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import gymnasium as gym
import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from gymnasium.utils.env_checker import check_env

import dks_gym  # noqa: F401  (registers the env ids)
from dks_gym.benchmarks import get_benchmark
from dks_gym.cli import main
from dks_gym.dataset import Dataset, generate_dataset, write_dataset
from dks_gym.solvers import openfoam as of

HAVE_OPENFOAM = all(path is not None for path in of.find_tools().values())
needs_openfoam = pytest.mark.skipif(not HAVE_OPENFOAM, reason=f"OpenFOAM missing: {of.INSTALL_HINT}")


def _datasets(path: Path) -> dict[str, np.ndarray]:
    """Every dataset of an HDF5 file, by name (attributes such as `created` excluded)."""
    out: dict[str, np.ndarray] = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return out


def _assert_same_file(a: Path, b: Path) -> None:
    da, db = _datasets(a), _datasets(b)
    assert sorted(da) == sorted(db)
    for name in da:
        np.testing.assert_array_equal(da[name], db[name], err_msg=name)


# Fixtures: each small preset generated once per module -------------------------------------------------------


@pytest.fixture(scope="module")
def dambreak_small(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """`generate_dataset("dambreak", "small", workers=2)`, keeping its run cache for the rerun test."""
    if not HAVE_OPENFOAM:
        pytest.skip(f"OpenFOAM missing: {of.INSTALL_HINT}")
    root = tmp_path_factory.mktemp("dambreak")
    path = generate_dataset("dambreak", "small", path=root / "dambreak-small.h5", progress=False, workers=2,
                            keep_workdir=True)  # fmt: skip
    return path, root / "dambreak-small.work"


@pytest.fixture(scope="module")
def cylinder_small(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """`dks-gym data generate cylinder --preset small --workers 2`, exactly as a user runs it."""
    if not HAVE_OPENFOAM:
        pytest.skip(f"OpenFOAM missing: {of.INSTALL_HINT}")
    path = tmp_path_factory.mktemp("cylinder") / "cylinder-small.h5"
    result = CliRunner().invoke(
        main, ["data", "generate", "cylinder", "--preset", "small", "--workers", "2", "--out", str(path)]
    )
    assert result.exit_code == 0, result.output
    assert "done in" in result.output and path.exists()
    assert not path.with_name("cylinder-small.work").exists()  # the run cache goes once the file is written
    return path


# Checks without the solver ----------------------------------------------------------------------------------


def test_missing_openfoam_says_how_to_install(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from dks_gym.benchmarks import GeneratorUnavailable
    from dks_gym.solvers.dambreak_case import generate_dambreak

    monkeypatch.setenv("PATH", "")
    with pytest.raises(of.OpenFOAMMissing, match=r"apt-get install -y openfoam") as err:
        generate_dambreak(get_benchmark("dambreak"), "small", progress=False)
    assert isinstance(err.value, GeneratorUnavailable)  # the CLI reports it as a clean error
    assert "interFoam" in str(err.value)
    out = tmp_path / "cylinder-small.h5"
    result = CliRunner().invoke(main, ["data", "generate", "cylinder", "--preset", "small", "--out", str(out)])
    assert result.exit_code == 1 and "apt-get install -y openfoam" in result.output
    assert "Traceback" not in result.output and not out.exists()


def test_generators_are_wired_into_the_benchmarks(tmp_path: Path) -> None:
    for name in ("cylinder", "dambreak"):
        bench = get_benchmark(name)
        assert bench.generator_available
        with pytest.raises(ValueError, match=f"unknown option.*{name} generator: bogus"):
            bench.generate("small", bogus=1)
    args = ["data", "generate", "burgers", "--workers", "2", "--out", str(tmp_path / "b.h5")]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 2 and "--workers is for the OpenFOAM benchmarks" in result.output


def test_doctor_reports_tools_and_packages(monkeypatch: pytest.MonkeyPatch) -> None:
    result = CliRunner().invoke(main, ["doctor"])
    assert result.exit_code == 0, result.output
    for item in ("OpenFOAM", "blockMesh", "interFoam", "pimpleFoam", "CUDA", "fluidfoam", "dask", "distributed",
                 "xlstm", "pydmd", "stable-baselines3"):  # fmt: skip
        assert item in result.output, item
    if HAVE_OPENFOAM:
        assert "OpenFOAM v" in result.output and "MISSING" not in result.output.split("torch")[0]
    import torch

    monkeypatch.setenv("PATH", "")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)  # the GPU branch, without a GPU
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda i: "Test GPU")
    result = CliRunner().invoke(main, ["doctor"])
    assert result.exit_code == 0, result.output
    assert "blockMesh       MISSING" in result.output and "apt-get install -y openfoam" in result.output
    assert "CUDA available" in result.output and "Test GPU" in result.output


def test_bad_pool_arguments_are_rejected(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="workers must be a positive integer"):
        of.run_all(_never_called, [], name="x", settings={}, resampler=None, workdir=tmp_path, workers=0)
    with pytest.raises(TypeError, match="get_executor"):
        of.run_all(_never_called, [], name="x", settings={}, resampler=None, workdir=tmp_path, executor=object())


def test_cache_key_tracks_settings_and_exact_parameter() -> None:
    base = of.run_key("dambreak", {"cell_size": 0.025}, 0.01)
    assert base == of.run_key("dambreak", {"cell_size": 0.025}, 0.01)
    assert base != of.run_key("dambreak", {"cell_size": 0.0125}, 0.01)
    assert base != of.run_key("dambreak", {"cell_size": 0.025}, np.nextafter(0.01, 1.0))


def _never_called(*args):  # pragma: no cover - the argument checks fire first
    raise AssertionError("the pool must validate its arguments before running anything")


def test_spin_up_detection_on_known_lift_signals() -> None:
    from dks_gym.solvers.cylinder_case import PRESETS, lift_saturated, strouhal

    settings = PRESETS["paper"]
    t = np.arange(0.0, 100.0, 0.01)
    wave = np.sin(2 * np.pi * t / 8.0)  # period 8 R/U, i.e. St = D / (U T) = 0.25
    assert lift_saturated(t, 0.7 * wave, 100.0, settings)
    assert not lift_saturated(t, np.exp(0.01 * t) * wave, 100.0, settings)  # still growing 20 % per 20 R/U
    assert not lift_saturated(t, np.exp(-0.01 * t) * wave, 100.0, settings)  # decaying towards a steady wake
    assert lift_saturated(t, 1e-4 * wave, 100.0, settings)  # steady wake: no shedding to wait for
    assert strouhal(0.7 * wave[::10], 0.1) == pytest.approx(0.25, rel=1e-3)


# Resampling -------------------------------------------------------------------------------------------------


@needs_openfoam
@pytest.mark.parametrize("name", ["dambreak", "cylinder"])
def test_resampler_weights_match_scipy_and_reproduce_linear_fields(name: str, tmp_path: Path) -> None:
    from scipy.interpolate import LinearNDInterpolator

    case = __import__(f"dks_gym.solvers.{name}_case", fromlist=["build_resampler"])
    bench = get_benchmark(name)
    resampler = case.build_resampler(case.preset_settings("small"), tmp_path, bench)
    mesh = resampler.mesh
    fluid = bench.fluid_mask()
    x, y = np.meshgrid(*bench.coords(), indexing="ij")
    c = bench.channels.index("p")  # the observed pressure: boundary faces copy their cell or are fixed

    # 1. Random cell values: our sparse weights equal scipy's barycentric interpolation on the same nodes.
    rng = np.random.default_rng(0)
    cell_values = rng.normal(size=mesh.n_cells)
    nodes = np.concatenate([mesh.cell_centres, *[mesh.boundary[p][0] for p in mesh.boundary]])
    node_values = [cell_values]
    for patch, (_, owner) in mesh.boundary.items():
        fixed = case.BOUNDARY_VALUES[patch].get("p", of.OWNER)
        node_values.append(cell_values[owner] if fixed is of.OWNER else np.full(len(owner), fixed))
    values = np.zeros((1, len(bench.channels), mesh.n_cells))
    values[0, c] = cell_values
    ours = resampler(values)[0, c]
    node_values = np.concatenate(node_values)
    reference = LinearNDInterpolator(nodes, node_values)(x, y)
    outside = np.isnan(reference)
    # Only the four corner cells can lie outside the hull of the face centres; they take the nearest node.
    corners = np.zeros_like(outside)
    corners[[0, 0, -1, -1], [0, -1, 0, -1]] = True
    assert not np.any(outside & ~corners)
    from scipy.spatial import cKDTree

    _, nearest = cKDTree(nodes).query(np.stack([x[outside], y[outside]], axis=1))
    reference[outside] = node_values[nearest]
    np.testing.assert_allclose(ours[fluid], reference[fluid], rtol=0, atol=1e-10)
    assert np.all(ours[~fluid] == 0.0)

    # 2. A linear field is reproduced exactly wherever the triangle uses cell centres only (away from walls).
    def lin(px, py):
        return 2.0 + 3.0 * px - 5.0 * py

    values[0, c] = lin(mesh.cell_centres[:, 0], mesh.cell_centres[:, 1])
    out = resampler(values)[0, c]
    from scipy.spatial import Delaunay

    tri = Delaunay(nodes)
    simplex = tri.find_simplex(np.stack([x.ravel(), y.ravel()], axis=1))
    cells_only = (simplex >= 0) & np.all(tri.simplices[simplex] < mesh.n_cells, axis=1)
    interior = cells_only & fluid.ravel()
    assert interior.sum() > 0.5 * fluid.sum()
    np.testing.assert_allclose(out.ravel()[interior], lin(x, y).ravel()[interior], rtol=0, atol=1e-9)

    # 3. Constants are kept everywhere in the fluid (weights form a partition of unity) when no patch fixes them.
    if name == "dambreak":
        values[0, c] = 7.5
        np.testing.assert_allclose(resampler(values)[0, c][fluid], 7.5, rtol=1e-12)


# Dambreak small preset, end to end --------------------------------------------------------------------------


def test_dambreak_small_file_and_physics(dambreak_small) -> None:
    path, _ = dambreak_small
    bench = get_benchmark("dambreak")
    with Dataset(path) as ds:
        assert tuple(ds.channels) == bench.channels
        np.testing.assert_allclose(ds.time, 0.01 * np.arange(1, 101))
        fields = ds.fields("train")[()]
        assert fields.shape == (3, 100, 5, 64, 64) and fields.dtype == np.float32
        np.testing.assert_array_equal(ds.cell_type, bench.cell_type())
        extras = {split: ds.extras(split) for split in ("train", "test")}
        generator = ds.generator
    assert generator["name"] == "dks_gym.solvers.dambreak_case" and "OPENFOAM" in generator["openfoam_build"]
    alpha = fields[:, :, 4]
    assert alpha.min() > -1e-3 and alpha.max() < 1 + 1e-3  # VOF stays bounded after resampling
    from dks_gym.solvers.dambreak_case import DEPTH, WATER_COLUMN

    for split, n in (("train", 3), ("test", 2)):
        assert set(extras[split]) == {"water_volume", "water_outflow", "surge_front"}
        volume, outflow = extras[split]["water_volume"], extras[split]["water_outflow"]
        assert volume.shape == (n, 101) and outflow.shape == extras[split]["surge_front"].shape == (n, 100)
        # The column fills whole cells: initial volume = width x height x depth exactly.
        np.testing.assert_allclose(volume[:, 0], WATER_COLUMN[0] * WATER_COLUMN[1] * DEPTH, rtol=1e-9)
        # Mass conservation: what is inside plus what left through the open top is the initial volume.
        balance = (volume[:, 1:] + outflow) / volume[:, :1] - 1.0
        assert np.abs(balance).max() < 1e-5
        assert np.abs(volume / volume[:, :1] - 1.0).max() < 5e-3  # the 0.5 % criterion
        front = extras[split]["surge_front"]
        assert np.all(front[:, 0] >= WATER_COLUMN[0] - 0.02) and np.all(front[:, 10] > front[:, 0])


def test_dambreak_env_passes_check_env(dambreak_small) -> None:
    path, _ = dambreak_small
    env = gym.make("DKS/Dambreak-v0", data_path=str(path))
    check_env(env.unwrapped, skip_render_check=True)


@pytest.mark.slow
def test_rerun_skips_finished_runs_and_reproduces_the_file(dambreak_small, tmp_path: Path) -> None:
    from dks_gym.solvers.dambreak_case import generate_dambreak

    path, work = dambreak_small
    cached = sorted((work / "runs").glob("*.npz"))
    assert len(cached) == 5
    removed, kept = cached[:2], cached[2:]
    stamps = {p: p.stat().st_mtime_ns for p in kept}
    for p in removed:
        p.unlink()
    data = generate_dambreak(get_benchmark("dambreak"), "small", seed=0, workdir=work, progress=False, workers=1)
    again = write_dataset(data, "dambreak", tmp_path / "again.h5")
    assert all(p.exists() for p in removed)
    assert {p: p.stat().st_mtime_ns for p in kept} == stamps  # finished runs were not redone
    _assert_same_file(path, again)  # OpenFOAM is deterministic and the cache is exact


# Cylinder small preset, end to end --------------------------------------------------------------------------


def test_cylinder_small_file_and_physics(cylinder_small) -> None:
    path = cylinder_small
    bench = get_benchmark("cylinder")
    with Dataset(path) as ds:
        fields = np.concatenate([ds.fields("train")[()], ds.fields("test")[()]])
        x, y = ds.coords
        assert fields.shape == (5, 20, 3, 64, 64)
        np.testing.assert_allclose(np.diff(ds.time), 0.5)
        extras = {split: ds.extras(split) for split in ("train", "test")}
        params = {split: ds.params(split) for split in ("train", "test")}
        generator = ds.generator
    assert generator["name"] == "dks_gym.solvers.cylinder_case" and generator["force_dt"] == 0.1
    body = ~bench.fluid_mask()
    assert np.all(fields[:, :, :, body] == 0)
    # Continuity: the volume flux through every grid column equals the inflow U * 8R (walls: u = 0 at y = +-4).
    u = fields[:, :, 0]
    dy = y[1] - y[0]
    flux = u.sum(axis=-1) * dy  # midpoint rule over the 64 cells of each column
    columns = np.abs(x) > 1.5  # columns that do not cut the body (midpoint rule is poor across it)
    np.testing.assert_allclose(flux[..., columns], 8.0, rtol=0.03)
    for split in ("train", "test"):
        assert set(extras[split]) == {"lift", "drag", "t_start"}
        lift, drag = extras[split]["lift"], extras[split]["drag"]
        assert lift.shape == drag.shape == (len(params[split]), 96)  # 9.5 R/U every 0.1 R/U
        assert np.all(drag > 0.5) and np.all(np.abs(lift) < 5)
        np.testing.assert_allclose(extras[split]["t_start"], 40.0)  # the small preset's fixed spin-up


def test_cylinder_small_round_trips_through_the_well(cylinder_small, tmp_path: Path) -> None:
    """The real cylinder data, obstacle cell types included, exported to The Well's layout and imported back:
    the same fields and the same EKF results (tests/test_importers.py checks the layout itself)."""
    from dks_gym.dataset.the_well import export_the_well, import_the_well

    from .round_trip import assert_round_trip

    export_the_well(cylinder_small, tmp_path / "well")
    assert_round_trip(cylinder_small, import_the_well(tmp_path / "well", tmp_path / "cylinder.h5"))


def test_cylinder_env_passes_check_env(cylinder_small) -> None:
    env = gym.make("DKS/Cylinder-v0", data_path=str(cylinder_small))
    check_env(env.unwrapped, skip_render_check=True)


@pytest.mark.slow
def test_killed_generation_resumes_to_the_same_file(cylinder_small, tmp_path: Path) -> None:
    """SIGKILL `dks-gym data generate` half-way, rerun it: the rest is done and the file equals the
    uninterrupted one (which ran with 2 workers; this one with 1)."""
    out = tmp_path / "resumed.h5"
    args = ["data", "generate", "cylinder", "--preset", "small", "--workers", "1", "--out", str(out)]
    runs = tmp_path / "resumed.work" / "runs"
    proc = subprocess.Popen([sys.executable, "-m", "dks_gym.cli", *args], start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    try:
        deadline = time.monotonic() + 120
        while len(list(runs.glob("*.npz"))) < 2 and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.2)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the generator and its running OpenFOAM solver
        proc.wait()
    done = {p.name for p in runs.glob("*.npz")}
    assert 2 <= len(done) < 5, "the generation should have been killed half-way"
    assert not out.exists() and not list(tmp_path.glob(".resumed.h5.tmp-*"))  # no file until complete
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    _assert_same_file(cylinder_small, out)
    assert not (tmp_path / "resumed.work").exists()


# The pool ---------------------------------------------------------------------------------------------------


def _fails_in_openfoam(param, case_dir, settings, resampler):
    """A run whose solver fails: interFoam on a case with no files."""
    if param > 0.5:
        of.run_tool(case_dir, "interFoam")
    return {"fields": np.full((1, 1), param)}


@needs_openfoam
def test_failed_run_keeps_its_logs_and_others_are_cached(tmp_path: Path) -> None:
    runs = [of.Run("train", 0, 0.25), of.Run("train", 1, 0.75), of.Run("test", 0, 0.5)]
    with ThreadPoolExecutor(2) as pool, pytest.raises(of.OpenFOAMError, match=r"1 of 3 demo runs failed") as err:
        of.run_all(_fails_in_openfoam, runs, name="demo", settings={}, resampler=None,
                   workdir=tmp_path, executor=pool, progress=False)  # fmt: skip
    case = tmp_path / "cases" / "train-001"
    assert str(case) in str(err.value)
    assert "FOAM FATAL" in (case / "log.interFoam").read_text()
    cached = sorted(p.name.split("-")[0] + p.name.split("-")[1] for p in (tmp_path / "runs").glob("*.npz"))
    assert cached == ["test000", "train000"]
    assert not (tmp_path / "cases" / "train-000").exists()  # successful cases are cleaned up


@needs_openfoam
def test_dask_local_cluster_runs_real_cases(tmp_path: Path) -> None:
    """A reduced dambreak sweep (2 runs, 0.05 s) on a Dask LocalCluster of worker processes gives exactly
    the file of the same sweep run in this process."""
    distributed = pytest.importorskip(
        "distributed", reason="dask distributed is optional (pip install 'dks-gym[cluster]')"
    )
    from dks_gym.solvers.dambreak_case import generate_dambreak

    settings = {"n_train": 1, "n_test": 1, "n_frames": 5}
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None)
    with cluster, distributed.Client(cluster) as client:
        data = generate_dambreak(get_benchmark("dambreak"), "small", workdir=tmp_path / "dask", progress=False,
                                 settings=settings, executor=client.get_executor())  # fmt: skip
        on_dask = write_dataset(data, "dambreak", tmp_path / "dask.h5")
    data = generate_dambreak(get_benchmark("dambreak"), "small", workdir=tmp_path / "local", progress=False,
                             settings=settings, workers=1)  # fmt: skip
    _assert_same_file(on_dask, write_dataset(data, "dambreak", tmp_path / "local.h5"))
    with Dataset(on_dask) as ds:
        assert ds.fields("train").shape == (1, 5, 5, 64, 64) and ds.extras("test")["water_volume"].shape == (1, 6)
