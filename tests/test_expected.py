"""The expected-score table that ships in the package (dks_gym.evaluation.expected): equal to the committed
records it was read from, published as docs/results/expected.md, and strict about what a rerun must match.
The rerun itself (Burgers, freshly generated data, the shipped files) is in tests/test_shipped.py."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from dks_gym.dataset import Dataset
from dks_gym.evaluation.conformance import PROTOCOL_KEY
from dks_gym.evaluation.expected import (
    EXPECTED_PROTOCOL,
    EXPECTED_SCORES,
    compare_expected,
    expected_markdown,
    expected_scores,
    scores_of,
    shipped_models,
)
from dks_gym.evaluation.results import load_results
from dks_gym.names import MODEL_KINDS

ROOT = Path(__file__).resolve().parents[1]
FOLDERS = {"burgers": "burgers-lite-calibrated", "cylinder": "cylinder", "dambreak": "dambreak"}


@pytest.mark.parametrize("benchmark", list(FOLDERS))
def test_the_table_is_the_committed_calibrated_runs_under_the_protocol(benchmark: str) -> None:
    """Every row equals the committed `calibrated` record of that model and filter (to the table's four digits),
    made under the protocol the table names, with no deviation; every model and filter has a row."""
    doc = load_results(ROOT / "docs" / "results" / FOLDERS[benchmark] / "results.json.gz")
    assert (doc[PROTOCOL_KEY]["name"], doc[PROTOCOL_KEY]["version"]) == EXPECTED_PROTOCOL
    assert doc[PROTOCOL_KEY]["deviations"] == {}
    records = [r for r in doc["records"] if r["experiment"] == "calibrated"]
    assert not any(r.get("protocol_deviations") for r in records)
    assert set(expected_scores(benchmark)) == {(m, f) for m in MODEL_KINDS for f in ("forward", "ekf", "enkf")}
    assert compare_expected(benchmark, scores_of(records), rtol=0.0) == []


def test_a_rerun_must_match_to_three_digits() -> None:
    """A number 2e-3 off is a mismatch, one 2e-4 off is not; a missing run or a missing coverage is a mismatch."""
    table = expected_scores("burgers")
    exact = dict(table)
    assert compare_expected("burgers", exact) == []
    key = ("koopman", "ekf")
    near = dict(exact)
    near[key] = dataclasses.replace(table[key], relative_l2=table[key].relative_l2 * (1 + 2e-4))
    assert compare_expected("burgers", near) == []
    far = dict(exact)
    far[key] = dataclasses.replace(table[key], coverage=table[key].coverage * (1 + 2e-3))
    [mismatch] = compare_expected("burgers", far)
    assert (mismatch.model, mismatch.filter, mismatch.field) == ("koopman", "ekf", "coverage")
    no_std = dict(exact)
    no_std[key] = dataclasses.replace(table[key], coverage=None)
    assert [m.field for m in compare_expected("burgers", no_std)] == ["coverage"]
    missing = {k: v for k, v in exact.items() if k != key}
    assert len(compare_expected("burgers", missing)) == 4
    with pytest.raises(ValueError, match="sphere"):
        expected_scores("sphere")


def test_the_docs_page_is_the_package_table() -> None:
    """docs/results/expected.md is `dks-gym expected --markdown`, byte for byte, and lists every benchmark."""
    page = (ROOT / "docs" / "results" / "expected.md").read_text()
    assert page == expected_markdown()
    assert all(f"## {b.capitalize()}" in page for b in EXPECTED_SCORES)


def test_the_shipped_models_refuse_other_data(burgers_small: Path) -> None:
    """Expected scores hold for the data the shipped models were trained on: other data are refused, naming
    what differs and the command that makes the protocol's data."""
    with pytest.raises(ValueError, match="data generate burgers --preset paper"):
        shipped_models("burgers", Dataset(burgers_small))
