"""The models that ship with dks-gym: small inference-only files, used only on the data they were trained on,
without training, tuning or writing anything, and reproducing the committed Burgers table."""

from __future__ import annotations

import json
import os
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from safetensors import safe_open

import dks_gym  # noqa: F401  (registers the env ids)
from dks_gym.assimilation import AssimilationConfig, run_assimilation
from dks_gym.dataset import Dataset
from dks_gym.evaluation.results import load_results
from dks_gym.models import CheckpointMissing, load_model
from dks_gym.models.shipped import (
    MAX_TOTAL_BYTES,
    SHIPPED_BENCHMARKS,
    STATS_RTOL,
    WEIGHTS_DIR,
    data_fingerprint,
    export_model,
    find_shipped,
    fingerprint_differences,
    is_shipped,
    list_shipped,
    max_file_bytes,
    shipped_name,
)
from dks_gym.names import MODEL_KINDS
from dks_gym.wrappers import LatentFilter

ROOT = Path(__file__).resolve().parents[1]
BURGERS_TABLE = ROOT / "docs" / "results" / "burgers-lite-calibrated" / "results.json.gz"


def _snapshot(home: Path) -> dict[str, tuple[int, int]]:
    """Every file under ``home`` with its size and modification time."""
    return {str(p.relative_to(home)): (p.stat().st_size, p.stat().st_mtime_ns) for p in home.rglob("*") if p.is_file()}


def test_the_shipped_files_are_small_inference_only_and_portable() -> None:
    files = list_shipped()
    names = {item.path.name for item in files}
    assert {shipped_name("burgers", kind) for kind in MODEL_KINDS} <= names
    assert names <= {shipped_name(b, k) for b in SHIPPED_BENCHMARKS for k in MODEL_KINDS}
    assert sum(item.path.stat().st_size for item in files) <= MAX_TOTAL_BYTES
    for item in files:
        assert item.path.stat().st_size <= max_file_bytes(item.metadata["model"]) <= 6 * 2**20, item.path
        if item.metadata["model"] != "pdmd":
            assert item.path.stat().st_size <= 3 * 2**20, item.path
        with safe_open(str(item.path), framework="pt") as f:
            prefixes = {key.split(".", 1)[0] for key in f.keys()}  # noqa: SIM118
        assert prefixes == {"model", "calibration"}, (item.path, prefixes)  # no optimizer or training state
        meta = item.metadata
        assert meta["complete"] and meta["q_scale"] > 0 and meta["r"] == 32
        fp = meta["data"]
        assert fp["preset"] == "paper" and len(fp["train_params_sha256"]) == 64
        assert len(fp["stats_mean"]) == len(fp["stats_std"]) > 0 and fp["generator_version"]
        if meta["model"] != "pdmd":
            assert meta["schedule"]["batch_size"] > 0 and meta["best_validation_loss"] > 0
        text = json.dumps(meta)
        assert "/root" not in text and "/home" not in text and "/tmp" not in text, "a machine path in the metadata"


def test_fingerprint_tolerance_admits_round_off_and_refuses_other_data(burgers_paper: Path,
                                                                        burgers_small: Path) -> None:
    fp = data_fingerprint(Dataset(burgers_paper))
    assert fingerprint_differences(fp, fp) == []
    std = np.asarray(fp["stats_std"])
    close = dict(fp, stats_mean=list(np.asarray(fp["stats_mean"]) + 0.1 * STATS_RTOL * std))
    assert fingerprint_differences(fp, close) == []
    far = dict(fp, stats_std=list(std * (1 + 10 * STATS_RTOL)))
    assert any("standard deviations" in d for d in fingerprint_differences(fp, far))
    small = fingerprint_differences(fp, data_fingerprint(Dataset(burgers_small)))
    assert any("preset 'small'" in d for d in small) and "the train split's parameters" in small


def test_a_shipped_model_filters_the_paper_data_at_once_and_writes_nothing(burgers_paper: Path,
                                                                           data_home: Path) -> None:
    """An empty model cache: the wrapper takes the shipped model, runs an EKF episode, and no file under the
    data home is created or changed."""
    assert not list((data_home / "models").glob("*koopman-lite-r32-T1.safetensors"))
    before = _snapshot(data_home)
    env = LatentFilter(gym.make("DKS/Burgers-v0"), model="koopman", filter="ekf")
    assert is_shipped(env.model.checkpoint_path)
    env.reset(seed=0)
    done, steps = False, 0
    while not done:
        _, reward, terminated, truncated, info = env.step(None)
        done, steps = terminated or truncated, steps + 1
    assert steps == 99 and np.isfinite(reward) and 0.5 < info["coverage"] <= 1.0
    assert _snapshot(data_home) == before


def test_other_data_get_a_clear_error_and_nothing_is_written(burgers_small: Path, data_home: Path) -> None:
    before = _snapshot(data_home)
    with pytest.raises(CheckpointMissing) as err:
        LatentFilter(gym.make("DKS/Burgers-v0", preset="small"), model="mlp")
    message = str(err.value)
    assert "ships with dks-gym was trained on other data" in message and "preset 'small'" in message
    assert "dks-gym train burgers --model mlp" in message and "--data-preset small" in message
    assert _snapshot(data_home) == before


def test_the_users_own_checkpoint_comes_before_the_shipped_one(burgers_paper: Path, tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """A checkpoint in the data home wins; exporting it writes an inference file with the same outputs."""
    import torch

    shipped = find_shipped("burgers", "pdmd")
    home = tmp_path / "home"
    (home / "models").mkdir(parents=True)
    monkeypatch.setenv("DKS_GYM_HOME", str(home))
    ds = Dataset(burgers_paper)
    exported = export_model(shipped.path, ds, out_dir=home / "models")  # an inference file is a checkpoint too
    assert exported.read_bytes() == shipped.path.read_bytes()  # and exporting is reproducible byte for byte
    model = load_model("burgers", "pdmd", dataset=ds)
    assert model.checkpoint_path == home / "models" / shipped.path.name and not is_shipped(model.checkpoint_path)
    z = model.encode(torch.as_tensor(ds.frame("test", 0, 5))[None], torch.as_tensor(ds.params("test")[:1]))
    assert torch.isfinite(z).all()


@pytest.fixture(scope="module")
def shipped_demo(burgers_paper: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, str, Path]:
    """`dks-gym demo` with the shipped lite models on freshly generated Burgers paper data (about 35 s on one
    core: its twelve runs are both the committed table's and the expected scores' Burgers rows), what it printed
    and its folder."""
    import contextlib
    import io

    from dks_gym.evaluation.demo import run_demo

    out = tmp_path_factory.mktemp("demo")
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        doc = run_demo(out, progress=False)
    return doc, printed.getvalue(), out


def test_the_demo_with_the_shipped_burgers_models_reproduces_the_committed_table(
        shipped_demo: tuple[dict, str, Path]) -> None:
    """Published checkpoints against the published table: the demo gives the committed final-time MSE
    (docs/results/burgers-lite-calibrated, experiment `calibrated`: forward run, EKF and EnKF of every model,
    calibrated Q and P0) to 3 digits, and says that it used the shipped models."""
    doc, out, folder = shipped_demo
    committed = {(r["model"], r["filter"]): r["final_mse_mean"]
                 for r in load_results(BURGERS_TABLE)["records"] if r["experiment"] == "calibrated"}
    got = {(r["model"], r["filter"]): r["final_mse_mean"] for r in doc["records"]}
    assert set(got) == set(committed)
    for key, value in committed.items():
        assert got[key] == pytest.approx(value, rel=1e-3), (key, got[key], value)
    assert doc["config"]["shipped_models"] == list(MODEL_KINDS)
    assert "shipped with dks-gym" in out and "Koopman" in out
    assert (folder / "demo.png").exists() and (folder / "results.json.gz").exists()


def test_the_shipped_burgers_models_reproduce_the_expected_scores(shipped_demo: tuple[dict, str, Path]) -> None:
    """The package's expected-score table (dks_gym.evaluation.expected), Burgers rows: relative L2 error, its
    95 % interval and the 95 % coverage of each model and filter, recomputed from freshly generated data with
    the shipped files, agree to three significant digits (a perturbed shipped weight fails here)."""
    from dks_gym.evaluation.expected import compare_expected, scores_of

    doc, _, _ = shipped_demo
    assert compare_expected("burgers", scores_of(doc["records"])) == []


CFD_HOME = Path(os.environ.get("DKS_GYM_CFD_HOME", "/nonexistent"))


@pytest.mark.parametrize("benchmark", ["cylinder", "dambreak"])
def test_the_shipped_cfd_models_start_at_once_and_reproduce_the_committed_koopman_ekf(benchmark: str) -> None:
    """With a CFD benchmark's paper data (generated with OpenFOAM, 10-60 min: a data home named by
    DKS_GYM_CFD_HOME), each kind's LatentFilter starts on the shipped model, and the Koopman EKF with the
    paper's Q and P0 reproduces the committed final-time MSE (docs/results/BENCHMARK, experiment `main`)."""
    path = CFD_HOME / "data" / f"{benchmark}-paper.h5"
    if not path.exists():
        pytest.skip(f"set DKS_GYM_CFD_HOME to a data home holding data/{benchmark}-paper.h5")
    from dks_gym.assimilation.config import PAPER_P0, PAPER_Q

    ds = Dataset(path)
    for kind in MODEL_KINDS:
        shipped = find_shipped(benchmark, kind)
        assert shipped is not None and shipped.differences(ds) == [], (kind, shipped and shipped.differences(ds))
        env = LatentFilter(gym.make(f"DKS/{benchmark.capitalize()}-v0", data_path=path), model=kind)
        assert is_shipped(env.model.checkpoint_path)
    committed = next(r["final_mse_mean"] for r in load_results(ROOT / "docs" / "results" / benchmark /
                                                                "results.json.gz")["records"]
                     if (r["experiment"], r["model"], r["filter"], r["initial"], r["r"], r["T"])
                     == ("main", "koopman", "ekf", "approximate", 32, 1))
    config = AssimilationConfig().replace(kind="ekf", Q=PAPER_Q, P0=PAPER_P0)
    result = run_assimilation(load_model(benchmark, "koopman", dataset=ds), ds, config, uncertainty=False)
    assert float(np.mean(result.step_mse[:, -1])) == pytest.approx(committed, rel=1e-3)


def test_weights_folder_is_package_data() -> None:
    import tomllib

    data = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]["dks_gym"]
    assert any(Path(WEIGHTS_DIR.name, "x.safetensors").match(Path(p).relative_to("models").as_posix())
               for p in data if p.startswith("models/"))


def test_models_command_lists_the_shipped_files_and_whether_the_data_match(burgers_paper: Path) -> None:
    from click.testing import CliRunner

    from dks_gym.cli import main

    result = CliRunner().invoke(main, ["models"])
    assert result.exit_code == 0, result.output
    rows = {line.split()[0]: line for line in result.output.splitlines()[1:] if line.strip()}
    for kind in MODEL_KINDS:
        assert rows[shipped_name("burgers", kind)].rstrip().endswith("match")
    for name, line in rows.items():
        if not name.startswith("burgers"):
            assert "no data (`dks-gym data generate" in line or "match" in line


def test_calibrate_command_tunes_a_checkpoint_and_export_refuses_an_untuned_one(
        burgers_small: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A checkpoint fresh from train_model has no Q scale: exporting it is refused with the command to run;
    `dks-gym calibrate` tunes it into the checkpoint, and a filter on it then runs without the warning."""
    import shutil
    import warnings

    from click.testing import CliRunner

    from dks_gym.assimilation import tuning
    from dks_gym.cli import main
    from dks_gym.models import train_model, training_schedule
    from dks_gym.models.checkpoint import calibration_names

    home = tmp_path / "home"
    (home / "data").mkdir(parents=True)
    shutil.copy(burgers_small, home / "data" / burgers_small.name)
    monkeypatch.setenv("DKS_GYM_HOME", str(home))
    monkeypatch.setattr(tuning, "BISECTIONS", 1)
    ds = Dataset(home / "data" / burgers_small.name)
    path = train_model("burgers", "koopman", 32, "lite", 1, dataset=ds, progress=False,
                       schedule=training_schedule("burgers", "lite", steps=20)).path
    assert "Q_scale" not in calibration_names(path)
    with pytest.raises(ValueError, match="dks-gym calibrate burgers --model koopman"):
        export_model(path, ds, out_dir=tmp_path / "out")
    assert not (tmp_path / "out").exists() or not list((tmp_path / "out").iterdir())
    result = CliRunner().invoke(main, ["calibrate", "burgers", "--model", "koopman", "--data-preset", "small",
                                       "--no-progress"])
    assert result.exit_code == 0, result.output
    assert "process-noise scale" in result.output and "Q_scale" in calibration_names(path)
    model = load_model("burgers", "koopman", dataset=ds)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a tuned model runs without the "no tuned scale" warning
        env = LatentFilter(gym.make("DKS/Burgers-v0", preset="small"), model=model)
        env.reset(seed=0)
        env.step(None)
