"""The committed placement results: every table regenerates byte for byte from its committed records, and
docs/results stays light enough to clone (at most 15 MB: gzip-compressed records, palette PNGs).

The reproduce tables are checked the same way in ``tests/test_evaluation.py``
(``test_committed_tables_regenerate_byte_for_byte``).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from dks_gym_agents.records import PLACEMENT_FILE
from dks_gym_agents.summary import summary_page
from dks_gym_agents.tables import budget_table, ranked_table

from dks_gym.evaluation.results import load_results

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results"
PLACEMENT = RESULTS / "placement"
MAX_RESULTS_BYTES = 15_000_000


def _runs() -> list[Path]:
    return sorted(PLACEMENT.rglob(PLACEMENT_FILE))


def test_every_committed_ranking_regenerates_from_its_records() -> None:
    runs = _runs()
    assert len(runs) >= 100  # the placement benchmark's budgets and the single runs
    stale = [p.parent.relative_to(RESULTS).as_posix() for p in runs
             if ranked_table(load_results(p)) != (p.parent / "placement.md").read_text()]
    assert not stale, f"placement.md differs from its records in {stale}"


def test_every_committed_budget_table_and_the_summary_regenerate_from_their_records(
        monkeypatch: pytest.MonkeyPatch) -> None:
    tables = sorted(PLACEMENT.rglob("budgets.md"))
    assert tables
    for table in tables:
        docs = {int(p.parent.name[1:]): load_results(p) for p in table.parent.glob(f"m*/{PLACEMENT_FILE}")}
        assert budget_table(docs) == table.read_text(), table.relative_to(RESULTS).as_posix()
    # the page names its own command and links its figures relative to itself: made from the repository root
    monkeypatch.chdir(RESULTS.parents[1])
    page = summary_page("docs/results/placement/benchmark", "docs/results/placement/benchmark.md")
    assert page == (PLACEMENT / "benchmark.md").read_text()


def test_no_uncompressed_results_files_are_committed() -> None:
    plain = [p.relative_to(RESULTS).as_posix() for p in RESULTS.rglob("*.json")
             if p.name in ("results.json", "placement.json")]
    assert not plain, f"commit results gzip-compressed (save_results(doc, '...json.gz')): {plain}"


def test_the_committed_results_weigh_at_most_15_mb() -> None:
    total = sum(p.stat().st_size for p in RESULTS.rglob("*") if p.is_file())
    assert total <= MAX_RESULTS_BYTES, f"docs/results holds {total / 1e6:.1f} MB (at most 15 MB)"


#: The results READMEs that lead with the relative L2 error: their first table, rebuilt from the records here.
LEAD_TABLES = ("burgers", "burgers-lite", "burgers-lite-calibrated", "cylinder", "dambreak")
#: The lead tables' columns: the records each quotes (experiment, filter, further criteria), approximate IC.
LEAD_COLUMNS = {"forward run": ("main", "forward", {"initial": "approximate"}),
                "EKF": ("main", "ekf", {"initial": "approximate"}), "EnKF n = 20": ("enkf", "enkf", {}),
                "calibrated EKF": ("calibrated", "ekf", {}), "calibrated EnKF": ("calibrated", "enkf", {})}


@pytest.mark.parametrize("name", LEAD_TABLES)
def test_the_results_readmes_lead_with_the_records_relative_errors(name: str) -> None:
    """Each README's first table is its relative-L2 table and equals the committed records' final relative L2
    (approximate IC) printed as the tables print it, so the prose cannot drift from the results."""
    from dks_gym.evaluation.figures import MODEL_LABELS
    from dks_gym.evaluation.formatting import percent

    doc = load_results(RESULTS / name / "results.json.gz")
    lines = (RESULTS / name / "README.md").read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("| "))
    header, *rows = [[c.strip() for c in line.strip("|").split("|")] for line in lines[start:start + 6]]
    assert header[:3] == ["model", "forward run", "EKF"] and set(header[1:]) <= set(LEAD_COLUMNS), header
    for row, model in zip(rows[1:], ("koopman", "pdmd", "mlp", "xlstm"), strict=True):
        expected = [percent(_lead_record(doc, model, h)["final_rel_l2_mean"]) for h in header[1:]]
        assert row == [MODEL_LABELS[model], *expected], (name, model)


def _lead_record(doc: dict, model: str, column: str) -> dict:
    """The record a lead-table column quotes for ``model``, checked to be the paper's scenario (m = 16)."""
    experiment, filt, criteria = LEAD_COLUMNS[column]
    rec = next(r for r in doc["records"] if r["experiment"] == experiment and r["model"] == model
               and r["filter"] == filt and all(r[k] == v for k, v in criteria.items()))
    scenario = (rec["initial"], rec["noise"], rec["r"], rec["T"], rec["n_members"])
    assert scenario == ("approximate", 0.2, 32, 1, 20 if filt == "enkf" else None), (column, scenario)
    return rec


def test_the_results_index_quotes_burgers_at_paper_scale_from_the_records() -> None:
    """docs/results/README.md's Burgers-at-paper-scale table: each error cell is the record's relative L2 with
    its MSE and the paper's MSE in brackets, printed by the tables' formatters."""
    from dks_gym.evaluation.figures import MODEL_LABELS
    from dks_gym.evaluation.formatting import percent, sci
    from dks_gym.evaluation.tabulate import paper_mse

    doc = load_results(RESULTS / "burgers" / "results.json.gz")
    lines = (RESULTS / "README.md").read_text().splitlines()
    start = lines.index("| model | rollout (MSE; paper) | EKF (MSE; paper) | EnKF n = 20 (MSE; paper) "
                        "| max_k ‖F_k‖ (paper) |")
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in lines[start + 2:start + 6]]
    for row, model in zip(rows, ("koopman", "pdmd", "mlp", "xlstm"), strict=True):
        expected = []
        for column in ("forward run", "EKF", "EnKF n = 20"):
            rec = _lead_record(doc, model, column)
            paper = paper_mse("burgers", model, rec["filter"])
            expected.append(f"{percent(rec['final_rel_l2_mean'])} ({sci(rec['final_mse_mean'])}; paper {paper})")
        assert row[:4] == [MODEL_LABELS[model], *expected], model


def test_every_committed_record_holds_its_relative_error() -> None:
    """Every record under docs/results holds its final relative L2 error: from its run, or derived from its MSEs
    and the data by ``python -m dks_gym.evaluation.migrate --relative docs/results`` where the run predates it
    (the derivation is checked against the runs' own in tests/test_relative_errors.py)."""
    from dks_gym.evaluation.migrate import results_files

    lacking = [f"{p.relative_to(RESULTS).as_posix()}: {r['experiment']}" for p in results_files([RESULTS])
               for r in load_results(p)["records"] if "final_rel_l2_mean" not in r]
    assert not lacking, lacking[:5]
