"""The HDF5 dataset layer: schema round trip, files written elsewhere, rejection of malformed files, atomicity."""

from __future__ import annotations

import json
import os
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from dks_gym.atomic import atomic_path, atomic_write_text
from dks_gym.benchmarks import GeneratedData
from dks_gym.cli import main
from dks_gym.dataset import DataError, Dataset, DatasetMissing, SchemaError, load_dataset, write_dataset
from dks_gym.home import DataHomeError, dataset_path
from dks_gym.locks import file_lock, lock_dir, lock_path

from .conftest import synthetic_data
from .damage import damage_chunk, put_nonfinite


@pytest.fixture(autouse=True)
def _private_home(data_home: Path) -> None:
    """Writers keep their locks in the data home: every test here uses the session's private one."""


def _arrays(data: GeneratedData) -> dict[tuple[str, int], np.ndarray]:
    return {(s, i): a for s, i, a in data.trajectories}


def test_round_trip_and_train_statistics(tmp_path: Path) -> None:
    data = synthetic_data("cylinder", n_train=3, n_test=2, n_t=5)
    arrays = _arrays(synthetic_data("cylinder", n_train=3, n_test=2, n_t=5))
    path = write_dataset(data, "cylinder", tmp_path / "c.h5")
    with Dataset(path) as ds:
        assert ds.benchmark.name == "cylinder"
        assert ds.channels == ("u", "v", "p") and ds.observed_channel == "p"
        assert ds.dt == 0.5 and ds.param_name == "Re"
        np.testing.assert_array_equal(ds.params("train"), data.params["train"])
        np.testing.assert_array_equal(ds.cell_type, data.cell_type)
        for (split, i), arr in arrays.items():
            np.testing.assert_array_equal(ds.trajectory(split, i), arr)
        np.testing.assert_array_equal(ds.frame("test", 1, 3), arrays[("test", 1)][3])
        # Statistics over the train split only, per channel, computed independently in one pass.
        train = np.stack([arrays[("train", i)] for i in range(3)]).astype(np.float64)
        per_channel = np.moveaxis(train, 2, 0).reshape(3, -1)
        np.testing.assert_allclose(ds.stats_mean, per_channel.mean(axis=1), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(ds.stats_std, per_channel.std(axis=1, ddof=1), rtol=1e-10)
        with h5py.File(path) as f:
            assert f["train/fields"].chunks[0] == 1  # chunked by trajectory
            assert f["train/fields"].compression == "gzip"


def _write_by_hand(path: Path, n_t: int = 3) -> None:
    """A Burgers file in the schema, written with bare h5py as another tool would."""
    rng = np.random.default_rng(1)
    with h5py.File(path, "w") as f:
        f.attrs.update(
            benchmark="burgers",
            channels=json.dumps(["u"]),
            observed_channel="u",
            scored_channels=["u"],
            param_name="nu",
            dt=0.005,
            generator=json.dumps({"name": "somebody else"}),
            schema_version=1,
            created="2026-01-01",
        )
        f["time"] = 0.005 * np.arange(n_t)
        f["coords/x"] = 2 * np.pi * np.arange(1024) / 1024
        for split, n in (("train", 2), ("test", 1)):
            f[f"{split}/fields"] = rng.standard_normal((n, n_t, 1, 1024)).astype(np.float32)
            f[f"{split}/params"] = rng.uniform(0.01, 1, n)
        f["stats/mean"] = np.zeros(1)
        f["stats/std"] = np.ones(1)


def test_file_written_elsewhere_loads_unchanged(tmp_path: Path) -> None:
    path = tmp_path / "foreign.h5"
    _write_by_hand(path)
    with h5py.File(path) as f:
        expected = f["test/fields"][0]
    with Dataset(path) as ds:
        assert ds.channels == ("u",) and ds.preset is None
        np.testing.assert_array_equal(ds.trajectory("test", 0), expected)
        assert ds.generator == {"name": "somebody else"}


@pytest.mark.parametrize(
    "mutate, item",
    [
        (lambda f: f.attrs.__delitem__("benchmark"), "benchmark"),
        (lambda f: f.attrs.__setitem__("benchmark", "Two words"), "benchmark"),  # no name of a custom one
        (lambda f: f.attrs.__setitem__("channels", ["v"]), "channels"),
        (lambda f: f.attrs.__setitem__("generator", "{not json"), "generator"),
        (lambda f: f.attrs.__setitem__("schema_version", 99), "schema_version"),
        (lambda f: f.attrs.__setitem__("dt", -1.0), "dt"),
        (lambda f: f.__delitem__("test"), "test"),
        (lambda f: f.__delitem__("train/params"), "train/params"),
        (lambda f: f.__delitem__("time"), "time"),
        (lambda f: f.__delitem__("coords/x"), "coords/x"),
        (lambda f: f.__delitem__("stats/std"), "stats/std"),
        (lambda f: (f.__delitem__("train/fields"),
                    f.create_dataset("train/fields", data=np.zeros((2, 3, 1, 512), "f4"))), "train/fields"),
        (lambda f: (f.__delitem__("test/params"), f.create_dataset("test/params", data=np.zeros(5))), "test/params"),
        (lambda f: f.attrs.__setitem__("observed_channel", "p"), "observed_channel"),
        (lambda f: f.attrs.__setitem__("scored_channels", ["u", "w"]), "scored_channels"),
        (lambda f: (f.__delitem__("train/fields"),
                    f.create_dataset("train/fields", data=np.zeros((2, 4, 1, 1024), "i4"))), "train/fields"),
    ],
)
def test_malformed_files_are_rejected_naming_the_item(tmp_path: Path, mutate, item: str) -> None:
    path = tmp_path / "bad.h5"
    _write_by_hand(path)
    with h5py.File(path, "a") as f:
        mutate(f)
    with pytest.raises(SchemaError, match=item.replace("/", "/")):
        Dataset(path)


def test_cfd_file_without_cell_type_is_rejected(make_synthetic) -> None:
    path = make_synthetic("dambreak")
    with h5py.File(path, "a") as f:
        del f["cell_type"]
    with pytest.raises(SchemaError, match="cell_type"):
        Dataset(path)


def test_cfd_file_with_a_wrong_cell_type_shape_is_rejected(make_synthetic) -> None:
    path = make_synthetic("cylinder")
    with h5py.File(path, "a") as f:
        del f["cell_type"]
        f.create_dataset("cell_type", data=np.zeros((64, 32), np.int8))
    with pytest.raises(SchemaError, match="cell_type"):
        Dataset(path)


def test_not_an_hdf5_file(tmp_path: Path) -> None:
    path = tmp_path / "junk.h5"
    path.write_bytes(b"this is not hdf5")
    with pytest.raises(SchemaError, match="not a readable HDF5 file"):
        Dataset(path)


def _failing(data: GeneratedData, exc: BaseException) -> GeneratedData:
    original = data.trajectories

    def trajectories():
        for n, item in enumerate(original):
            if n == 2:
                raise exc
            yield item

    data.trajectories = trajectories()
    return data


@pytest.mark.parametrize("exc", [RuntimeError("solver blew up"), KeyboardInterrupt()])
def test_failed_or_interrupted_write_leaves_nothing(tmp_path: Path, exc: BaseException) -> None:
    target = tmp_path / "out.h5"
    with pytest.raises(type(exc)):
        write_dataset(_failing(synthetic_data("burgers", n_train=3), exc), "burgers", target)
    assert not target.exists()
    assert [p.name for p in tmp_path.iterdir()] == []  # no temporary file, no lock file


@pytest.mark.parametrize("exc", [RuntimeError("writer failed"), KeyboardInterrupt()])
def test_atomic_path_keeps_the_old_file_until_the_new_one_is_complete(tmp_path: Path, exc: BaseException) -> None:
    """The helper every writer uses (datasets, results, checkpoints, OpenFOAM files): the target keeps its old
    content through a failed or interrupted write, the temporary file beside it goes, a success replaces it."""
    target = atomic_write_text(tmp_path / "run.npz", "old")
    with pytest.raises(type(exc)), atomic_path(target, suffix=".npz") as tmp:
        assert tmp.parent == tmp_path and tmp.name.startswith(".run.npz.tmp-") and tmp.suffix == ".npz"
        tmp.write_text("half")
        raise exc
    assert [p.name for p in tmp_path.iterdir()] == ["run.npz"] and target.read_text() == "old"
    with atomic_path(target, suffix=".npz") as tmp:
        np.savez(tmp, x=np.arange(3))  # np.savez appends .npz to a name without it: the suffix keeps the name
    assert [p.name for p in tmp_path.iterdir()] == ["run.npz"]
    np.testing.assert_array_equal(np.load(target)["x"], np.arange(3))


def test_damaged_file_raises_data_error_saying_how_to_regenerate_it(tmp_path: Path) -> None:
    """A file whose header is intact but whose data blocks are not: every read of the bad trajectory says so."""
    path = write_dataset(synthetic_data("burgers", n_train=2), "burgers", tmp_path / "b.h5",
                         extra_attrs={"preset": "small", "seed": 0})
    damage_chunk(path, "train", 1)
    with Dataset(path) as ds:  # opens and validates: only the data is damaged
        ds.trajectory("train", 0)
        for read in (lambda: ds.trajectory("train", 1), lambda: ds.frame("train", 1, 0),
                     lambda: ds.read("train", 1, slice(None), 0)):
            with pytest.raises(DataError, match="is damaged: trajectory 1 of split 'train'") as err:
                read()
            hint = f"dks-gym data generate burgers --preset small --out {path} --overwrite` or delete it"
            assert hint in str(err.value)
    # NaN or inf in stored data, from a writer other than ours (ours refuses it, see below).
    foreign = tmp_path / "foreign.h5"
    _write_by_hand(foreign)
    put_nonfinite(foreign, "train", 1, frame=2, channel=0, value=-np.inf)
    with Dataset(foreign) as ds:
        with pytest.raises(DataError, match=r"split 'train', trajectory 1, channel 'u' holds NaN or inf in 1 of 3 "
                                            r"frames \(first: frame 2\).*tool that wrote it"):
            ds.check_finite(ds.trajectory("train", 1), "train", 1)
        ds.check_finite(ds.trajectory("train", 0), "train", 0)


def test_bad_generator_output_is_refused(tmp_path: Path) -> None:
    data = synthetic_data("burgers")
    data.trajectories = iter([("train", 0, np.full((4, 1, 1024), np.nan, np.float32))])
    with pytest.raises(ValueError, match="non-finite"):
        write_dataset(data, "burgers", tmp_path / "nan.h5")
    data = synthetic_data("burgers")
    data.trajectories = iter([("train", 0, np.zeros((4, 1, 1000), np.float32))])
    with pytest.raises(ValueError, match="shape"):
        write_dataset(data, "burgers", tmp_path / "shape.h5")
    assert not (tmp_path / "nan.h5").exists() and not (tmp_path / "shape.h5").exists()


def test_lock_keeps_a_second_writer_out(tmp_path: Path) -> None:
    target = tmp_path / "locked.h5"
    with file_lock(target, "write") as lock:
        with pytest.raises(RuntimeError, match="another process is writing") as err:
            write_dataset(synthetic_data("burgers"), "burgers", target, lock_timeout=0.1)
    assert str(lock.lock_file) in str(err.value)  # the message names the lock file
    assert Path(lock.lock_file).parent == lock_dir()
    assert not target.exists() and list(tmp_path.iterdir()) == []


def test_locks_live_in_the_data_home_keyed_by_the_absolute_path(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                 data_home: Path) -> None:
    """One lock per (target, kind), the same whichever way the path is spelled, and none beside the target."""
    target = tmp_path / "sub" / "f.h5"
    target.parent.mkdir()
    (tmp_path / "link").symlink_to(target.parent)
    monkeypatch.chdir(tmp_path)
    lock = lock_path(target, "write")
    assert lock.parent == data_home / ".locks" and lock.name.startswith("f.h5-") and lock.name.endswith(".write.lock")
    assert lock_path(Path("sub/f.h5")) == lock_path(Path("sub/../sub/f.h5")) == lock_path(Path("link/f.h5")) == lock
    assert lock_path(target, "generate") != lock and lock_path(tmp_path / "g.h5") != lock
    with pytest.raises(ValueError, match="unknown lock kind"):
        lock_path(target, "read")
    # A data home that cannot be written: the lock goes to a hidden folder beside the target.
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    monkeypatch.setenv("DKS_GYM_HOME", str(blocker / "home"))
    assert lock_path(target) == target.parent / ".locks" / lock.name


def test_generate_write_and_train_leave_no_lock_file_beside_their_outputs(tmp_path: Path,
                                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    from dks_gym.benchmarks import get_benchmark
    from dks_gym.dataset import generate_dataset
    from dks_gym.models import train_model, training_schedule

    home = tmp_path / "home"
    monkeypatch.setenv("DKS_GYM_HOME", str(home))
    monkeypatch.setattr(type(get_benchmark("burgers")), "generate",
                        lambda self, preset, **kwargs: synthetic_data("burgers", n_train=3, n_test=1))
    out = tmp_path / "out"
    out.mkdir()
    write_dataset(synthetic_data("burgers"), "burgers", out / "written.h5")
    generated = generate_dataset("burgers", "small", progress=False)
    train_model("burgers", "koopman", 4, dataset=Dataset(generated),
                schedule=training_schedule("burgers", "lite", steps=2, batch_size=2), path=out / "m.safetensors",
                progress=False)
    assert sorted(p.name for p in out.iterdir()) == ["m.loss.png", "m.safetensors", "written.h5"]  # and its figure
    assert sorted(p.name for p in (home / "data").iterdir()) == ["burgers-small.h5"]
    kinds = sorted(p.name.rsplit(".", 2)[1] for p in (home / ".locks").iterdir())
    assert kinds == ["generate", "train", "write", "write"]
    assert not [p for p in tmp_path.rglob("*") if p.name.endswith(".lock") and p.parent.name != ".locks"]


def test_lock_held_by_another_process_keeps_the_writer_out(tmp_path: Path) -> None:
    """The lock is an OS file lock, so it also excludes a second process, not only a second thread."""
    import subprocess
    import sys

    target = tmp_path / "locked.h5"
    holder = subprocess.Popen(  # the other process finds the lock through the helper, from the data home
        [sys.executable, "-c", "import sys, time; from dks_gym.locks import file_lock; lock = file_lock(sys.argv[1]); "
         "lock.acquire(); print('held', flush=True); time.sleep(60)", str(target)],
        stdout=subprocess.PIPE, text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(RuntimeError, match="another process is writing"):
            write_dataset(synthetic_data("burgers"), "burgers", target, lock_timeout=0.2)
        assert not target.exists()
    finally:
        holder.kill()
        holder.wait()
    write_dataset(synthetic_data("burgers"), "burgers", target, lock_timeout=5)  # released with the process
    assert Dataset(target).n_trajectories("train") == 2
    assert [p.name for p in tmp_path.iterdir()] == ["locked.h5"]


def test_unwritable_data_home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    # A path below a regular file can never be created, even by root (permission bits would not stop root).
    monkeypatch.setenv("DKS_GYM_HOME", str(blocker / "home"))
    from dks_gym.dataset import generate_dataset

    with pytest.raises(DataHomeError, match="DKS_GYM_HOME"):
        generate_dataset("burgers", "small", progress=False)


def test_missing_dataset_names_the_command(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("DKS_GYM_HOME", str(tmp_path))
    with pytest.raises(DatasetMissing, match="dks-gym data generate burgers --preset small"):
        load_dataset("burgers", "small")
    assert dataset_path("burgers", "small") == tmp_path / "data" / "burgers-small.h5"
    with pytest.raises(ValueError, match="unknown preset"):
        load_dataset("burgers", "huge")
    with pytest.raises(ValueError, match="unknown benchmark"):
        load_dataset("pendulum")


def test_cli_data_info(tmp_path: Path) -> None:
    good = tmp_path / "good.h5"
    _write_by_hand(good)
    result = CliRunner().invoke(main, ["data", "info", str(good)])
    assert result.exit_code == 0, result.output
    assert "burgers" in result.output and "2 trajectories" in result.output
    bad = tmp_path / "bad.h5"
    _write_by_hand(bad)
    with h5py.File(bad, "a") as f:
        del f["stats"]
    result = CliRunner().invoke(main, ["data", "info", str(bad)])
    assert result.exit_code == 1 and "stats/mean" in result.output


def test_dataset_survives_fork_style_reopen(tmp_path: Path) -> None:
    import pickle

    path = tmp_path / "f.h5"
    _write_by_hand(path)
    ds = Dataset(path)
    clone = pickle.loads(pickle.dumps(ds))
    np.testing.assert_array_equal(clone.trajectory("train", 1), ds.trajectory("train", 1))
    assert os.fspath(clone.path) == os.fspath(path)


def test_generator_extras_round_trip_and_bad_shape_is_refused(tmp_path: Path) -> None:
    data = synthetic_data("cylinder", n_train=2, n_test=1)
    lift = np.arange(2 * 5, dtype=np.float64).reshape(2, 5)
    data.extras = {"train": {"lift": lift, "t_start": np.array([30.0, 31.5])}, "test": {"lift": lift[:1]}}
    path = write_dataset(data, "cylinder", tmp_path / "extras.h5")
    with Dataset(path) as ds:
        np.testing.assert_array_equal(ds.extras("train")["lift"], lift)
        np.testing.assert_array_equal(ds.extras("train")["t_start"], [30.0, 31.5])
        assert set(ds.extras("test")) == {"lift"}
    plain = write_dataset(synthetic_data("cylinder"), "cylinder", tmp_path / "plain.h5")
    with Dataset(plain) as ds:
        assert ds.extras("train") == {}
    data = synthetic_data("cylinder", n_train=2, n_test=1)
    data.extras = {"train": {"lift": lift[:1]}}
    with pytest.raises(ValueError, match="first axis must be the 2 trajectories"):
        write_dataset(data, "cylinder", tmp_path / "bad.h5")
    assert not (tmp_path / "bad.h5").exists()


def test_generate_dataset_removes_the_work_cache_only_after_success(tmp_path: Path) -> None:
    """The generator's `<stem>.work` cache (OpenFOAM runs) goes once the file is written, stays on failure."""
    import dataclasses

    from dks_gym.benchmarks import get_benchmark
    from dks_gym.benchmarks.cylinder import CylinderBenchmark
    from dks_gym.dataset import generate_dataset

    class Caching(CylinderBenchmark):
        fail = True

        def generate(self, preset="paper", *, seed=0, workdir=None, progress=True, **options):
            Path(workdir, "runs").mkdir(parents=True, exist_ok=True)
            Path(workdir, "runs", "train-000.npz").write_bytes(b"cached run")
            if Caching.fail:
                raise RuntimeError("solver failed")
            return synthetic_data("cylinder", n_train=2, n_test=1)

    bench = Caching(**{f.name: getattr(get_benchmark("cylinder"), f.name) for f in dataclasses.fields(Caching)})
    path = tmp_path / "cylinder-small.h5"
    work = tmp_path / "cylinder-small.work"
    with pytest.raises(RuntimeError, match="solver failed"):
        generate_dataset(bench, "small", path=path, progress=False)
    assert (work / "runs" / "train-000.npz").exists() and not path.exists()  # kept so a rerun resumes
    Caching.fail = False
    generate_dataset(bench, "small", path=path, progress=False, keep_workdir=True)
    assert path.exists() and work.exists()
    generate_dataset(bench, "small", path=path, progress=False, overwrite=True)
    assert path.exists() and not work.exists()


def test_cli_device_and_workers_options_go_to_the_right_generators(tmp_path: Path) -> None:
    runner = CliRunner()
    result = runner.invoke(main, ["data", "generate", "burgers", "--preset", "small", "--device", "cpu",
                                  "--out", str(tmp_path / "b.h5")])
    assert result.exit_code == 0, result.output
    with Dataset(tmp_path / "b.h5") as ds:
        assert ds.n_trajectories("train") == 6
    result = runner.invoke(main, ["data", "generate", "cylinder", "--device", "cuda", "--out", str(tmp_path / "c.h5")])
    assert result.exit_code == 2 and "--device is for the torch solvers" in result.output
    result = runner.invoke(main, ["data", "generate", "sphere", "--workers", "2", "--out", str(tmp_path / "s.h5")])
    assert result.exit_code == 2 and "--workers is for the OpenFOAM benchmarks" in result.output
    result = runner.invoke(main, ["data", "generate", "burgers", "--scheduler", "tcp://127.0.0.1:1", "--out",
                                  str(tmp_path / "s.h5")])
    assert result.exit_code == 2 and "--scheduler is for the OpenFOAM benchmarks" in result.output
    result = runner.invoke(main, ["data", "generate", "cylinder", "--workers", "2", "--scheduler", "tcp://127.0.0.1:1",
                                  "--out", str(tmp_path / "c.h5")])
    assert result.exit_code == 2 and "not both" in result.output
    assert not (tmp_path / "c.h5").exists() and not (tmp_path / "s.h5").exists()


def test_cli_scheduler_hands_the_clusters_executor_to_the_openfoam_generator(tmp_path: Path, monkeypatch) -> None:
    """`data generate cylinder --scheduler ADDRESS` gives the generator the executor of a client of that scheduler
    (the generator's run on a real LocalCluster: tests/test_openfoam.py), and closes the client after."""
    import concurrent.futures as cf
    import contextlib

    import dks_gym.dataset
    import dks_gym.parallel

    seen: dict = {}

    class Client:  # what open_executor asks of distributed.Client
        def get_executor(self, pure: bool) -> cf.Executor:
            seen["executor"] = cf.ThreadPoolExecutor(1)
            return seen["executor"]

    @contextlib.contextmanager
    def client(address: str):
        seen["address"] = address
        try:
            yield Client()
        finally:
            seen["closed"] = True

    def generate(benchmark: str, preset: str, **options):
        seen["options"] = options
        raise ValueError("stop here: the options are what this test checks")

    monkeypatch.setattr(dks_gym.parallel, "_dask_client", client)
    monkeypatch.setattr(dks_gym.dataset, "generate_dataset", generate)
    result = CliRunner().invoke(main, ["data", "generate", "cylinder", "--scheduler", "tcp://10.0.0.1:8786", "--out",
                                       str(tmp_path / "c.h5")])
    assert result.exit_code == 1 and "stop here" in result.output
    assert seen["address"] == "tcp://10.0.0.1:8786" and seen["closed"]
    assert seen["options"]["executor"] is seen["executor"] and "workers" not in seen["options"]


def test_cli_states_the_cost_first_and_refuses_a_gpu_preset_on_the_cpu(tmp_path: Path) -> None:
    runner = CliRunner()
    result = runner.invoke(main, ["data", "generate", "burgers", "--preset", "small", "--out", str(tmp_path / "b.h5")])
    assert result.exit_code == 0, result.output
    assert result.output.index("expect about") < result.output.index("done in")
    result = runner.invoke(main, ["data", "generate", "sphere", "--out", str(tmp_path / "s.h5")])
    assert result.exit_code == 2
    for hint in ("--device cuda", "--preset small", "--force", "40 h on a CPU"):
        assert hint in result.output
    assert not (tmp_path / "s.h5").exists()


def test_missing_dataset_names_both_presets_with_their_cost(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from dks_gym.benchmarks import BENCHMARKS

    monkeypatch.setenv("DKS_GYM_HOME", str(tmp_path))
    for bench in BENCHMARKS.values():
        with pytest.raises(DatasetMissing) as err:
            load_dataset(bench.name, "paper")
        message = str(err.value)
        for preset in ("paper", "small"):
            assert f"dks-gym data generate {bench.name} --preset {preset}` ({bench.generation_costs[preset].time}" \
                in message
        assert ("needs OpenFOAM" in message) == (bench.name in ("cylinder", "dambreak"))
        assert ("needs a CUDA GPU" in message) == (bench.name == "sphere")
