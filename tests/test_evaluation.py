"""Evaluation: the batched assimilation runs, the results schema, reproduce end to end (Burgers `small`)."""

from __future__ import annotations

import json
import math
import os
import shutil
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from click.testing import CliRunner

import dks_gym  # noqa: F401
from dks_gym.dataset import Dataset
from dks_gym.assimilation import AssimilationConfig, FilterConfig, approximate_initial_latent, run_assimilation
from dks_gym.evaluation.commands import compare_command, reproduce_command
from dks_gym.evaluation.comparison import compare
from dks_gym.evaluation.results import (
    ResultsError,
    load_results,
    make_record,
    merge,
    new_results,
    save_results,
    validate,
)
from dks_gym.models import train_model, training_schedule
from dks_gym.wrappers import LatentFilter

# Short trainings: enough for the models to leave their initialization, small enough for a test (~25 s).
TRAIN_STEPS = {"koopman": 150, "mlp": 60, "xlstm": 40}


@pytest.fixture(scope="module")
def home(burgers_small: Path, tmp_path_factory: pytest.TempPathFactory):
    """A data home of this module only (its checkpoints never meet other modules'), with the small data."""
    root = tmp_path_factory.mktemp("eval_home")
    (root / "data").mkdir()
    shutil.copy(burgers_small, root / "data" / "burgers-small.h5")
    previous = os.environ.get("DKS_GYM_HOME")
    os.environ["DKS_GYM_HOME"] = str(root)
    yield root
    if previous is None:
        os.environ.pop("DKS_GYM_HOME")
    else:
        os.environ["DKS_GYM_HOME"] = previous


@pytest.fixture(scope="module")
def dataset(home: Path) -> Dataset:
    return Dataset(home / "data" / "burgers-small.h5")


@pytest.fixture(scope="module")
def models(dataset: Dataset) -> dict:
    """Lite r = 32 models briefly trained into the module's data home (the checkpoints reproduce reuses).

    The module's one long setup (about 25 s on one core): reproduce, its resumption and the batched runs are
    checked on models that left their initialization, trained once for the whole module."""
    out = {}
    for kind in ("koopman", "mlp", "xlstm", "pdmd"):
        out[kind] = train_model("burgers", kind, 32, "lite", 1, dataset=dataset, progress=False,
                                schedule=training_schedule("burgers", "lite", steps=TRAIN_STEPS.get(kind))).model.eval()
    return out


def _single_wrapper_run(model, filt: str, initial: str, trajectory: int) -> tuple[np.ndarray, np.ndarray]:
    """The same run through the LatentFilter wrapper, one trajectory: per-frame MSE and ||F_k|| per step."""
    env = LatentFilter(gym.make("DKS/Burgers-v0", preset="small"), model=model,
                       filter=filt, config=FilterConfig(initial=initial))
    _, info = env.reset(options={"trajectory": trajectory, "noise_seed": 0})
    mse, norms, done = [info["mse"]], [], False
    while not done:
        _, _, terminated, truncated, info = env.step(None)
        mse.append(info["mse"])
        norms.append(info["forecast_norm"])
        done = terminated or truncated
    env.close()
    return np.array(mse), np.array(norms)


@pytest.mark.parametrize("kind, filt, initial", [("koopman", "ekf", "approximate"), ("mlp", "ekf", "exact"),
                                                 ("xlstm", "forward", "approximate"), ("pdmd", "ekf", "approximate")])
def test_batched_run_equals_wrappers_one_trajectory_at_a_time(models, dataset, kind, filt, initial) -> None:
    result = run_assimilation(models[kind], dataset, kind=filt, initial=initial)
    n_test = dataset.n_trajectories("test")
    assert result.step_mse.shape == (n_test, dataset.n_frames)
    for i in range(n_test):
        mse, norms = _single_wrapper_run(models[kind], filt, initial, i)
        # float32 decoding: a relative 2e-4, or 1e-7 absolute (field variance ~0.5) for the tiny pDMD errors
        np.testing.assert_allclose(result.step_mse[i], mse, rtol=2e-4, atol=1e-7)
        np.testing.assert_allclose(result.forecast_norm[:, i], norms, rtol=1e-4)
    assert result.final_mse_mean == pytest.approx(np.mean(result.step_mse[:, -1]))
    assert result.final_mse_std == pytest.approx(np.std(result.step_mse[:, -1], ddof=1))


def test_forward_run_is_the_decoded_rollout_scored_against_the_data(models, dataset) -> None:
    """Eq. 18 recomputed from the model's rollout and the stored fields, and ||F_k|| from the Jacobians."""
    model = models["mlp"]
    result = run_assimilation(model, dataset, kind="forward")
    mu = torch.as_tensor(dataset.params("test"), dtype=torch.float32)
    z0 = approximate_initial_latent(model, dataset)[None].expand(len(mu), -1)
    n_steps = dataset.n_frames - 1
    with torch.no_grad():
        path = model.rollout(z0, mu, n_steps)  # (B, n_t, r)
        final = model.decode(path[:, -1], mu).numpy()
    truth = np.asarray(dataset.fields("test")[:, -1], dtype=np.float64)
    expected = ((final - truth) ** 2).mean(axis=(1, 2))
    np.testing.assert_allclose(result.final_mse, expected, rtol=1e-4)
    norms = torch.stack([torch.linalg.matrix_norm(model.forecast_jacobian(path[:, k], mu), ord=2)
                         for k in range(n_steps)]).amax(0).detach().numpy()
    np.testing.assert_allclose(result.max_forecast_norm, norms, rtol=1e-4)
    koopman = run_assimilation(models["koopman"], dataset, kind="forward")
    with torch.no_grad():
        k_norm = torch.linalg.matrix_norm(models["koopman"].koopman_operator(mu), ord=2).detach().numpy()
    np.testing.assert_allclose(koopman.max_forecast_norm, k_norm, rtol=1e-5)
    assert np.all(k_norm <= 1 + 1e-5)  # ||K(mu; dt)|| <= 1 by construction (paper Cor. 1)


def test_enkf_run_is_reproducible_from_its_seed(models, dataset) -> None:
    model = models["koopman"]
    a = run_assimilation(model, dataset, kind="enkf", n_members=8, seed=3)
    b = run_assimilation(model, dataset, kind="enkf", n_members=8, seed=3)
    c = run_assimilation(model, dataset, kind="enkf", n_members=8, seed=4)
    np.testing.assert_array_equal(a.step_mse, b.step_mse)
    assert not np.array_equal(a.step_mse, c.step_mse)
    assert a.forecast_norm is None and a.max_forecast_norm is None


def test_bad_configuration_is_refused(models, dataset) -> None:
    with pytest.raises(ValueError, match="unknown filter"):
        FilterConfig(kind="ukf")
    with pytest.raises(ValueError, match="noise_level"):
        AssimilationConfig(noise_level=0.0)
    with pytest.raises(ValueError, match="trajectories"):
        run_assimilation(models["koopman"], dataset, trajectories=[0, 99])
    from dks_gym.models import build_model

    with pytest.raises(ValueError, match="cylinder"):
        run_assimilation(build_model("cylinder", "koopman", r=8, preset="lite"), dataset)


# Results schema ----------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small_doc(models, dataset) -> dict:
    from dks_gym.models.checkpoint import dataset_identity

    records = []
    for kind in ("koopman", "mlp"):
        for filt in ("forward", "ekf", "enkf"):
            res = run_assimilation(models[kind], dataset, kind=filt, n_members=8)
            records.append(make_record(res, experiment="main"))
    return new_results("burgers", "lite", dataset_identity(dataset), {"n_sensors": 16}, records)


def test_results_round_trip_and_validation(small_doc, tmp_path: Path) -> None:
    path = save_results(small_doc, tmp_path / "results.json")
    assert load_results(path) == json.loads(json.dumps(small_doc))
    rec = small_doc["records"][0]
    assert rec["final_mse_mean"] == pytest.approx(np.mean(rec["per_trajectory_final_mse"]))
    assert rec["per_step_mse_mean"][-1] == pytest.approx(rec["final_mse_mean"])
    bad = json.loads(json.dumps(small_doc))
    del bad["records"][1]["final_mse_mean"]
    with pytest.raises(ResultsError, match=r"records\[1\] lacks final_mse_mean"):
        validate(bad)
    bad = json.loads(json.dumps(small_doc))
    bad["records"][0]["per_trajectory_final_mse"].append(1.0)
    with pytest.raises(ResultsError, match="batch"):
        validate(bad)
    bad = json.loads(json.dumps(small_doc))
    bad["records"].append(bad["records"][0])
    with pytest.raises(ResultsError, match="repeats"):
        validate(bad)
    bad = dict(small_doc, schema_version=99)
    with pytest.raises(ResultsError, match="schema_version"):
        validate(bad)
    (tmp_path / "broken.json").write_text("{not json")
    with pytest.raises(ResultsError, match="not valid JSON"):
        load_results(tmp_path / "broken.json")


def test_nonfinite_numbers_are_stored_as_null(small_doc) -> None:
    from dks_gym.evaluation.results import _numbers

    assert _numbers([1.0, math.nan, math.inf]) == [1.0, None, None]
    doc = json.loads(json.dumps(small_doc))
    doc["records"][0]["final_mse_std"] = None
    validate(doc)
    doc["records"][0]["final_mse_std"] = math.nan
    with pytest.raises(ResultsError, match="final_mse_std"):
        validate(doc)


def test_compare_gives_ratios_of_matching_records(small_doc) -> None:
    other = json.loads(json.dumps(small_doc))
    other["records"][0]["final_mse_mean"] *= 2.0
    other["records"][1]["da_step_seconds"] *= 0.5
    dropped = other["records"].pop()
    rows = compare(small_doc, other)
    paired = [r for r in rows if r["only"] is None]
    assert len(paired) == len(small_doc["records"]) - 1
    assert paired[0]["mse_ratio"] == pytest.approx(2.0)
    assert paired[1]["time_ratio"] == pytest.approx(0.5)
    assert all(r["mse_ratio"] == pytest.approx(1.0) for r in paired[1:])
    only = [r for r in rows if r["only"] == "a"]
    assert len(only) == 1 and only[0]["filter"] == dropped["filter"] and only[0]["model"] == dropped["model"]


def test_merge_keeps_the_experiments_not_rerun(small_doc) -> None:
    other = json.loads(json.dumps(small_doc))
    for rec in other["records"]:
        rec["experiment"] = "enkf"
    merged = merge(small_doc, other)
    assert {r["experiment"] for r in merged["records"]} == {"main", "enkf"}
    foreign = dict(other, dataset=dict(other["dataset"], fingerprint="0" * 64))
    with pytest.raises(ResultsError, match="different datasets"):
        merge(small_doc, foreign)


# Figures ------------------------------------------------------------------------------------------------------
def test_bar_values_are_normalized_by_the_mlp_forward_run() -> None:
    from dks_gym.evaluation.figures import normalized_values

    base = {"model": "mlp", "final_mse_mean": 2.0, "final_mse_std": 1.0}
    recs = [{"model": "xlstm", "final_mse_mean": 6.0, "final_mse_std": 0.5},
            {"model": "koopman", "final_mse_mean": 1.0, "final_mse_std": None}, base]
    assert normalized_values(recs, base) == [("koopman", 0.5, 0.0), ("mlp", 1.0, 0.5), ("xlstm", 3.0, 0.25)]
    with pytest.raises(ValueError, match="baseline"):
        normalized_values(recs, dict(base, final_mse_mean=None))


@pytest.mark.parametrize("name", ["cylinder", "sphere"])
def test_reconstruction_figure_of_2d_and_3d_fields(name: str, tmp_path: Path) -> None:
    from dks_gym.benchmarks import get_benchmark
    from dks_gym.evaluation.figures import _field_slice, reconstruction_figure

    bench = get_benchmark(name)
    mesh = np.meshgrid(*bench.coords(), indexing="ij")
    truth = np.stack([np.sin(mesh[0]) * np.cos(mesh[1]) + c for c in range(len(bench.channels))])
    np.testing.assert_array_equal(_field_slice(truth[1]), truth[1][..., 32] if bench.ndim == 3 else truth[1])
    path = reconstruction_figure({"koopman": truth + 0.1, "mlp": truth - 0.1}, truth, bench.coords(),
                                 tmp_path / "r.png", channel=1, fluid_mask=bench.fluid_mask(), title=name)
    assert path.stat().st_size > 10_000


# Reproduce end to end ------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def reproduced(models, home: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, float]:
    out = tmp_path_factory.mktemp("reproduce")
    start = time.perf_counter()
    result = CliRunner().invoke(reproduce_command, ["burgers", "--preset", "lite", "--data-preset", "small",
                                                    "--only", "main", "--out", str(out), "--no-train"])
    assert result.exit_code == 0, result.output + repr(result.exception)
    return out, time.perf_counter() - start


def test_reproduce_main_writes_results_tables_and_figures(reproduced) -> None:
    out, seconds = reproduced
    assert seconds < 180
    doc = load_results(out / "results.json.gz")
    assert doc["benchmark"] == "burgers" and doc["config"]["experiments"] == ["main"]
    runs = {(r["model"], r["filter"], r["initial"]) for r in doc["records"]}
    assert runs == {(m, f, i) for m in ("koopman", "pdmd", "mlp", "xlstm") for f in ("forward", "ekf")
                    for i in ("approximate", "exact")}
    assert all(r["batch"] == 3 and len(r["per_trajectory_step_mse"]) == 3 for r in doc["records"])
    tables = (out / "tables.md").read_text()
    assert "## Main comparison, approximate initial condition" in tables
    assert "3.17e-03" in tables  # the paper's Koopman rollout beside ours
    for name in ("main_approximate", "main_exact", "temporal_approximate", "reconstruction"):
        assert (out / "figures" / f"{name}.png").stat().st_size > 10_000


def test_reproduce_reruns_merge_and_compare_prints_ratios(reproduced, models) -> None:
    out, _ = reproduced
    result = CliRunner().invoke(reproduce_command, ["burgers", "--data-preset", "small", "--only", "operator_norm",
                                                    "--out", str(out), "--no-train"])
    assert result.exit_code == 0, result.output
    doc = load_results(out / "results.json.gz")
    assert {r["experiment"] for r in doc["records"]} == {"main", "operator_norm"}
    # The same run asked for by two experiments gives the same record.
    a = next(r for r in doc["records"] if r["experiment"] == "main" and r["model"] == "mlp" and r["filter"] == "ekf"
             and r["initial"] == "approximate")
    b = next(r for r in doc["records"] if r["experiment"] == "operator_norm" and r["model"] == "mlp"
             and r["filter"] == "ekf")
    assert a["per_trajectory_final_mse"] == pytest.approx(b["per_trajectory_final_mse"], rel=1e-5)
    assert "Table IX" in (out / "tables.md").read_text()
    result = CliRunner().invoke(reproduce_command, ["burgers", "--data-preset", "small", "--only", "main",
                                                    "--only", "operator_norm", "--out", str(out), "--no-train",
                                                    "--skip-done"])
    assert result.exit_code == 0 and "skipping experiments already in" in result.output
    assert load_results(out / "results.json.gz")["records"] == doc["records"]
    result = CliRunner().invoke(compare_command, [str(out / "results.json.gz"), str(out / "results.json.gz"),
                                                  "--experiment", "main"])
    assert result.exit_code == 0 and result.output.count(" 1 ") >= 16


def test_reproduce_names_its_protocol_and_marks_the_records_that_leave_it(reproduced) -> None:
    doc = load_results(reproduced[0] / "results.json.gz")
    assert (doc["protocol"]["name"], doc["protocol"]["version"]) == ("dks-v1", 1)
    assert doc["protocol"]["deviations"] == {"data_preset": "small"}  # the small data; the rest as prescribed
    exact = [r for r in doc["records"] if r["initial"] == "exact"]
    assert exact and all(r["protocol_deviations"] == ["initial"] for r in exact)
    assert all("protocol_deviations" not in r for r in doc["records"] if r["initial"] == "approximate")


def test_koopman_ekf_beats_its_forward_run_after_short_training(reproduced) -> None:
    """Paper Section IV: assimilation lowers the error of the linear Koopman model (here 150 lite steps)."""
    doc = load_results(reproduced[0] / "results.json.gz")

    def mse(filt: str, initial: str) -> float:
        return next(r["final_mse_mean"] for r in doc["records"] if r["experiment"] == "main"
                    and r["model"] == "koopman" and r["filter"] == filt and r["initial"] == initial)

    for initial in ("approximate", "exact"):
        assert mse("ekf", initial) < mse("forward", initial)


def test_reproduce_on_a_dask_cluster_writes_what_the_serial_run_writes(models, home: Path, dask_client,
                                                                      tmp_path: Path) -> None:
    """--scheduler loads the models and makes the runs on a two-worker LocalCluster: the results but for their
    measured times, and the tables but for their date, are those of a serial run."""
    import re

    from dks_gym.evaluation.reproduce import reproduce
    from tests.conftest import without_times

    reproduce("burgers", data_preset="small", only=["operator_norm"], models=["koopman", "pdmd"],
              out=tmp_path / "serial", train=False, progress=False, log=lambda _: None)
    result = CliRunner().invoke(reproduce_command, ["burgers", "--data-preset", "small", "--only", "operator_norm",
                                                    "--model", "koopman", "--model", "pdmd", "--no-train",
                                                    "--out", str(tmp_path / "dask"),
                                                    "--scheduler", dask_client.scheduler.address])
    assert result.exit_code == 0, result.output + repr(result.exception)
    serial, spread = (load_results(tmp_path / name / "results.json.gz") for name in ("serial", "dask"))
    assert len(serial["records"]) == 4 and len(serial["models"]) == 2
    assert without_times(spread) == without_times(serial)
    tables = [re.sub(r"Created \S+", "", (tmp_path / name / "tables.md").read_text()) for name in ("serial", "dask")]
    assert tables[0] == tables[1]


def test_missing_model_without_training_fails_clearly(home: Path, tmp_path: Path, models) -> None:
    result = CliRunner().invoke(reproduce_command, ["burgers", "--data-preset", "small", "--only", "latent",
                                                    "--out", str(tmp_path), "--no-train"])
    assert result.exit_code != 0
    assert "dks-gym train" in result.output and "r=16" in result.output


# ------------------------------------------------------------------ the committed reproduce results

RESULTS = Path(__file__).parents[1] / "docs" / "results"


def _num(x: float | None) -> str:
    """The tables' number format, written out here independently: 3 significant digits, e-notation outside
    [1e-2, 1e3)."""
    if x is None or not math.isfinite(x):
        return "-"
    return f"{x:.3g}" if 1e-2 <= abs(x) < 1e3 else f"{x:.2e}"


def _cell(rec: dict | None) -> str:
    if rec is None:
        return "-"
    if rec["final_mse_std"] is None:
        return _num(rec["final_mse_mean"])
    return f"{_num(rec['final_mse_mean'])} ± {_num(rec['final_mse_std'])}"


def _section(tables: str, heading: str) -> list[list[str]]:
    """Body rows (cells) of the markdown table under the '## heading...' line."""
    lines = tables.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(f"## {heading}"))
    rows = []
    for line in lines[start + 1:]:
        if line.startswith("## "):
            break
        if line.startswith("|") and not line.startswith("|---"):
            rows.append([c.strip() for c in line.strip("|").split("|")])
    return rows[1:]  # drop the header


def _rec(doc: dict, **criteria) -> dict | None:
    return next((r for r in doc["records"] if all(r.get(k) == v for k, v in criteria.items())), None)


@pytest.mark.parametrize("name", ["burgers-lite", "burgers", "burgers-lite-calibrated", "dambreak", "cylinder"])
def test_committed_tables_regenerate_byte_for_byte(name: str) -> None:
    from dks_gym.evaluation.reproduce import tables_markdown

    doc = load_results(RESULTS / name / "results.json.gz")
    assert tables_markdown(doc) == (RESULTS / name / "tables.md").read_text()


def test_committed_lite_results_every_experiment_in_tables_and_figures(tmp_path: Path) -> None:
    """docs/results/burgers-lite: each ablation's table holds the numbers of its JSON records, and
    write_figures draws one figure per experiment (the reconstruction needs the run's cache: not here)."""
    from dks_gym.evaluation.reproduce import tables_markdown, write_figures

    doc = load_results(RESULTS / "burgers-lite" / "results.json.gz")
    assert set(doc["config"]["experiments"]) == {"main", "enkf", "ensemble", "noise", "latent", "multistep",
                                                 "operator_norm", "timing"}
    (tmp_path / "tables.md").write_text(tables_markdown(doc))
    tables = (tmp_path / "tables.md").read_text()
    labels = {"koopman": "Koopman", "pdmd": "pDMD", "mlp": "MLP", "xlstm": "xLSTM"}
    base = {"initial": "approximate", "noise": 0.2, "r": 32, "T": 1}

    rows = _section(tables, "EnKF, n = 20 (Table VII)")
    assert len(rows) == 5 and rows[4][:2] == ["Koopman", "EKF (reference)"]
    for row, m in zip(rows, labels):
        assert row[:4] == [labels[m], "rollout / EnKF", _cell(_rec(doc, experiment="enkf", model=m, filter="forward")),
                           _cell(_rec(doc, experiment="enkf", model=m, filter="enkf", n_members=20))]
    rows = _section(tables, "EnKF ensemble size (Table VIII)")
    assert [r[0] for r in rows] == ["Koopman", "MLP", "xLSTM"]
    for row, m in zip(rows, ("koopman", "mlp", "xlstm")):
        assert row[1:4] == [_cell(_rec(doc, experiment="ensemble", model=m, filter="enkf", n_members=n))
                            for n in (20, 40, 64)]
    rows = _section(tables, "Measurement noise (Fig. 10)")
    assert [r[0] for r in rows] == list(labels.values())
    for row, m in zip(rows, labels):
        for cell, s in zip(row[1:], (0.1, 0.2, 0.3)):
            rec = _rec(doc, model=m, filter="ekf", **{**base, "noise": s})
            ref = _rec(doc, model="mlp", filter="forward", **{**base, "noise": s})
            assert cell == f"{_cell(rec)} ({rec['final_mse_mean'] / ref['final_mse_mean']:.3g})"
    rows = _section(tables, "Latent dimension (Fig. 11)")
    assert [(r[0], r[1]) for r in rows] == [(str(r), labels[m]) for r in (16, 32, 64) for m in labels]
    for row in rows:
        m = next(k for k, v in labels.items() if v == row[1])
        crit = {**base, "r": int(row[0])}
        assert row[2:4] == [_cell(_rec(doc, model=m, filter=f, **crit)) for f in ("forward", "ekf")]
    rows = _section(tables, "Multi-step training (Fig. 13)")
    assert [(r[0], r[1]) for r in rows] == [(str(t), labels[m]) for t in (1, 2, 4, 8) for m in ("koopman", "mlp")]
    for row in rows:
        m = "koopman" if row[1] == "Koopman" else "mlp"
        crit = {**base, "T": int(row[0])}
        assert row[2:4] == [_cell(_rec(doc, model=m, filter=f, **crit)) for f in ("forward", "ekf")]
    rows = _section(tables, "Operator norm max_k ||F_k||_2")
    assert [r[0] for r in rows] == list(labels.values())
    for row, m in zip(rows, labels):
        norms = [v for v in _rec(doc, model=m, filter="ekf", **base)["max_forecast_norm"] if v is not None]
        assert row[:2] == [labels[m], f"{max(norms):.4f}"]
    rows = _section(tables, "Wall time per DA step in ms")
    assert [(r[0], r[1]) for r in rows] == [(i, labels[m]) for i in ("approximate", "exact") for m in labels]
    for row in rows:
        m = next(k for k, v in labels.items() if v == row[1])
        for cell, f in zip(row[2:5], ("forward", "ekf", "enkf")):
            rec = _rec(doc, experiment="timing", model=m, filter=f, initial=row[0])
            assert cell == f"{1e3 * rec['da_step_seconds']:.3g}"
        for cell, f in zip(row[6:9], ("forward", "ekf", "enkf")):  # the timed trajectory's final relative error
            rel = _rec(doc, experiment="timing", model=m, filter=f, initial=row[0])["final_rel_l2_mean"]
            assert cell == f"{format(100 * rel, '#.3g').rstrip('.')} % ({100 * (1 - rel):.1f})"

    written = write_figures(doc, tmp_path / "figures")
    names = {p.stem for p in written}
    committed = {p.stem for p in (RESULTS / "burgers-lite" / "figures").glob("*.png")}
    assert names == committed - {"reconstruction"}
    assert names >= {"enkf", "ensemble", "noise", "latent", "multistep", "timing_approximate", "timing_exact"}
    assert all(p.stat().st_size > 10_000 for p in written)


def test_records_hold_per_channel_errors_and_the_filter_spread(make_synthetic) -> None:
    """Per scored channel: the final-time MSE (its mean over channels is Eq. 18) and the MSE over the
    channel standardized by its data std, against a direct numpy computation; the gain norm and spread per
    step; and the reproduce tables' per-channel section showing them."""
    from dks_gym.evaluation.reproduce import tables_markdown
    from dks_gym.models import build_model
    from dks_gym.models.calibration import calibrate

    ds = Dataset(make_synthetic("dambreak", n_t=5))
    model = build_model("dambreak", "koopman", r=8, preset="lite", dataset=ds, seed=0)
    model.calibration = calibrate(model, ds, [0, 1])
    model.calibration["Q_scale"] = torch.tensor(1.0, dtype=torch.float64)
    records = []
    for kind in ("forward", "ekf"):
        config = AssimilationConfig().replace(kind=kind, Q="paper", P0="paper")
        result = run_assimilation(model, ds, config, uncertainty=False)
        est, truth = result.final_estimate.astype(np.float64), result.final_truth.astype(np.float64)
        scored = list(ds.benchmark.scored_indices)
        direct = ((est - truth) ** 2)[:, scored].reshape(len(est), len(scored), -1).mean(-1)
        np.testing.assert_allclose(result.final_channel_mse, direct, rtol=1e-5)
        np.testing.assert_allclose(result.final_channel_mse.mean(1), result.final_mse, rtol=1e-5)
        std = np.asarray(ds.stats_std, dtype=np.float64)[scored]
        np.testing.assert_allclose(result.final_channel_nmse, direct / std**2, rtol=1e-5)
        assert result.gain_norm.shape == result.spread.shape == (ds.n_frames - 1, len(est))
        assert (result.gain_norm == 0).all() if kind == "forward" else (result.gain_norm > 0).all()
        rec = make_record(result, experiment="main")
        assert list(rec["final_channel_nmse_mean"]) == list(ds.scored_channels)
        assert rec["final_channel_nmse_mean"]["p"] == pytest.approx(
            float(result.final_channel_nmse[:, ds.scored_channels.index("p")].mean()))
        assert len(rec["per_step_spread_mean"]) == ds.n_frames - 1
        records.append(rec)
    doc = new_results("dambreak", "lite", {"path": "x.h5", "fingerprint": "0"},
                      {"scored_channels": list(ds.scored_channels), "n_test": 2}, records)
    rows = [r for r in _section(tables_markdown(doc), "Per channel") if r[0] == "Koopman"]
    assert [r[1] for r in rows] == ["forward run", "EKF"]
    n = len(ds.scored_channels)  # then, as the records hold them, each channel's relative L2 error
    for row, rec in zip(rows, records):
        assert row[2:2 + n] == [_num(rec["final_channel_nmse_mean"][c]) for c in ds.scored_channels]
    bad = dict(records[0], final_channel_nmse_mean={"p": "x"})
    with pytest.raises(ResultsError, match="final_channel_nmse_mean"):
        validate(dict(doc, records=[bad]))


def test_an_interrupted_reproduce_continues_with_the_runs_already_written(models, home: Path,
                                                                          tmp_path: Path) -> None:
    """Records are saved after every run; --skip-done keeps them and runs only the missing ones."""
    import importlib

    rp = importlib.import_module("dks_gym.evaluation.reproduce")  # the module, not the function it exports

    calls: list[str] = []
    real = rp.run_assimilation

    def stop_after_two(*args, **kwargs):
        if len(calls) == 2:
            raise KeyboardInterrupt
        calls.append(kwargs.get("description"))
        return real(*args, **kwargs)

    out = tmp_path / "resume"
    rp.run_assimilation = stop_after_two
    try:
        with pytest.raises(KeyboardInterrupt):
            rp.reproduce("burgers", data_preset="small", only=["enkf"], out=out, train=False, progress=False,
                         log=lambda *_: None)
    finally:
        rp.run_assimilation = real
    partial = load_results(out / "results.json.gz")
    assert len(partial["records"]) == 2  # the two finished runs survived the interruption
    said: list[str] = []
    ran: list[str] = []

    def counting(*args, **kwargs):
        ran.append(kwargs.get("description"))
        return real(*args, **kwargs)

    rp.run_assimilation = counting
    try:
        rp.reproduce("burgers", data_preset="small", only=["enkf"], out=out, train=False, progress=False,
                     skip_done=True, log=said.append)
    finally:
        rp.run_assimilation = real
    assert len(ran) == 8 - 2 and "2 of 8 runs kept" in " ".join(said) and "6 runs to do" in " ".join(said)
    doc = load_results(out / "results.json.gz")
    assert len(doc["records"]) == 8
    assert doc["records"][:2] == partial["records"]  # kept as written, not recomputed
