"""A user's estimator under the protocol (dks_gym.evaluation.estimators) and the leaderboard page.

The harness is checked against closed forms (an estimate off the truth by a constant c has Eq. 18 MSE c^2, NEES 1
with std c, coverage 1) and against a second reader of the readings (SHRED's read_episodes); the example runs end
to end, beats the training mean field (computed here with numpy) and reproduces its committed results file, which
``compare`` accepts beside ours; the committed leaderboard regenerates byte for byte from the files it names.
"""

from __future__ import annotations

import importlib.util
import json
import re
import shlex
from pathlib import Path

import numpy as np
import pytest

from dks_gym.dataset import Dataset
from dks_gym.evaluation.comparison import compare
from dks_gym.evaluation.conformance import protocol_differences
from dks_gym.evaluation.estimators import score_estimator
from dks_gym.evaluation.leaderboard import collect, leaderboard_page
from dks_gym.evaluation.results import RESULTS_FILE, load_results, save_results
from dks_gym.models.shred import read_episodes

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "docs" / "results"
OURS = RESULTS / "burgers-lite-calibrated" / RESULTS_FILE
RIDGE = RESULTS / "estimators" / "burgers-ridge" / RESULTS_FILE
LEADERBOARD = RESULTS / "leaderboard.md"


def _example():
    spec = importlib.util.spec_from_file_location("ridge_estimator", REPO / "examples" / "ridge_estimator.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_example_runs_end_to_end_beats_the_mean_field_and_compares_with_ours(burgers_paper: Path,
                                                                                  tmp_path: Path, capsys) -> None:
    doc = _example().main(str(tmp_path))
    assert "ridge" in capsys.readouterr().out
    written = load_results(tmp_path / RESULTS_FILE)
    (record,) = written["records"]
    assert written["protocol"]["name"] == "dks-v1" and written["protocol"]["deviations"] == {}
    assert "protocol_deviations" not in record and record["batch"] == 10
    ours = load_results(OURS)
    assert protocol_differences(ours, written) == []
    rows = compare(ours, written)  # refuses files of other protocol settings
    assert any(r["only"] == "b" and r["model"] == "ridge" for r in rows)
    # independent baseline: the training mean field of the estimated frames, scored with numpy
    ds = Dataset(burgers_paper)
    train, test = np.asarray(ds.fields("train"), np.float64), np.asarray(ds.fields("test"), np.float64)
    mean = train[:, 1:].mean(axis=(0, 1))
    final = test[:, -1]
    baseline = np.mean(np.linalg.norm((mean - final).reshape(len(final), -1), axis=1)
                       / np.linalg.norm(final.reshape(len(final), -1), axis=1))
    assert np.isfinite(record["final_rel_l2_mean"]) and record["final_rel_l2_mean"] < 0.6 * baseline
    # the committed file is this run's (same data, same seeds): its numbers reproduce
    committed = load_results(RIDGE)
    assert doc["dataset"]["fingerprint"] == committed["dataset"]["fingerprint"]
    for name in ("final_mse_mean", "final_rel_l2_mean"):
        assert record[name] == pytest.approx(committed["records"][0][name], rel=1e-6), name


class _Offset:
    """The truth plus ``c`` everywhere, with std ``c``; records what it was shown."""

    def __init__(self, ds: Dataset, c: float) -> None:
        self.ds, self.c, self.seen = ds, c, []
        self.mus = ds.params("test")

    def estimate(self, readings, sensors, mu):
        t = int(np.argmin(np.abs(self.mus - mu)))
        self.seen.append((t, readings.copy(), sensors.copy()))
        truth = self.ds.frame("test", t, len(readings)).astype(np.float64)
        return truth + self.c, np.full(truth.shape, self.c)


def test_the_harness_scores_each_frame_against_its_truth_with_the_filters_readings(burgers_paper: Path) -> None:
    ds, c = Dataset(burgers_paper), 0.5
    offset = _Offset(ds, c)
    doc = score_estimator(offset, "burgers", name="offset", dataset=ds, trajectories=[1, 4])
    (record,) = doc["records"]
    assert record["protocol_deviations"] == ["trajectories"] and doc["protocol"]["deviations"] == {}
    assert protocol_differences(load_results(OURS), doc) == []  # a subset is marked per record, as timing's is
    assert record["per_step_mse_mean"][0] is None  # frame 0 is not estimated
    np.testing.assert_allclose(record["per_step_mse_mean"][1:], c**2, rtol=1e-12)
    assert record["final_nees_mean"] == pytest.approx(1.0) and record["final_coverage_mean"] == 1.0
    final = np.stack([ds.frame("test", t, ds.n_frames - 1) for t in (1, 4)]).reshape(2, -1).astype(np.float64)
    expected = np.mean(c * np.sqrt(final.shape[1]) / np.linalg.norm(final, axis=1))
    assert record["final_rel_l2_mean"] == pytest.approx(expected, rel=1e-12)
    # the readings: frames 1..k of what SensingEnv serves the filters, at the paper layout
    layout = ds.benchmark.paper_layout(16)
    served = read_episodes(ds, layout, [1, 4], [0, 0], split="test", noise_level=0.2, faults=None)
    assert len(offset.seen) == 2 * (ds.n_frames - 1)
    for t, readings, sensors in offset.seen:
        np.testing.assert_array_equal(sensors, layout)
        np.testing.assert_array_equal(readings, served[[1, 4].index(t), 1:len(readings) + 1])


def test_bad_estimators_get_clear_errors(burgers_paper: Path) -> None:
    ds = Dataset(burgers_paper)
    with pytest.raises(TypeError, match="estimate"):
        score_estimator(42, "burgers", name="x", dataset=ds)
    with pytest.raises(ValueError, match=r"shape \(1024,\).*\(1, 1024\)"):
        score_estimator(lambda r, s, mu: np.zeros(1024), "burgers", name="x", dataset=ds, trajectories=[0])
    flaky = lambda r, s, mu: (np.zeros((1, 1024)), np.ones((1, 1024))) if len(r) % 2 else np.zeros((1, 1024))  # noqa: E731
    with pytest.raises(ValueError, match="std at some frames"):
        score_estimator(flaky, "burgers", name="x", dataset=ds, trajectories=[0])
    with pytest.raises(ValueError, match="non-empty"):
        score_estimator(lambda r, s, mu: np.zeros((1, 1024)), "burgers", name=" ", dataset=ds)


def _page_command() -> list[str]:
    text = LEADERBOARD.read_text()
    command = re.search(r"```bash\n(dks-gym leaderboard .*)\n```", text).group(1)
    return shlex.split(command)


def test_the_committed_leaderboard_regenerates_byte_for_byte(monkeypatch: pytest.MonkeyPatch) -> None:
    args = _page_command()
    out = args[args.index("--out") + 1]
    sources = args[2:args.index("--out")]
    monkeypatch.chdir(REPO)
    assert leaderboard_page(sources, out) == LEADERBOARD.read_text()


def test_the_leaderboard_ranks_only_runs_under_the_protocol(tmp_path: Path) -> None:
    doc = load_results(RIDGE)
    other = json.loads(json.dumps(doc))
    other["protocol"]["version"] = 2
    marked = json.loads(json.dumps(doc))
    marked["records"][0]["protocol_deviations"] = ["trajectories"]
    save_results(other, tmp_path / "v2" / RESULTS_FILE)
    save_results(marked, tmp_path / "marked" / RESULTS_FILE)
    entries, _, skipped = collect([RIDGE, tmp_path / "v2", tmp_path / "marked"])
    assert [e.method for e in entries["burgers"]] == ["ridge"]
    assert "protocol dks-v1 v2; this dks-gym ranks dks-v1 v1" in skipped[0]
    assert "1 run(s) leave the protocol (trajectories: 1)" in skipped[1]
    (paper,) = collect([RESULTS / "burgers"])[2]
    assert paper.endswith("burgers/results.json.gz` (burgers): its runs leave the protocol: model_preset = 'paper' "
                          "(the protocol's: 'lite').")


def test_the_leaderboard_sorts_by_final_relative_error() -> None:
    entries, notes, _ = collect([OURS, RIDGE])
    errors = [e.record["final_rel_l2_mean"] for e in entries["burgers"]]
    assert errors == sorted(errors) and len(errors) == 13
    assert {e.method for e in entries["burgers"]} >= {"Koopman, calibrated EKF", "pDMD, forward run", "ridge"}
    assert len(notes) == 2


def test_the_schema_takes_any_estimator_name_and_only_latent_models_under_a_filter() -> None:
    from dks_gym.evaluation.results import ResultsError, validate

    doc = load_results(RIDGE)
    for model, filt in (("ridge", "ekf"), (" ", "none")):
        bad = json.loads(json.dumps(doc))
        bad["records"][0].update(model=model, filter=filt)
        with pytest.raises(ResultsError, match="is none of"):
            validate(bad)
