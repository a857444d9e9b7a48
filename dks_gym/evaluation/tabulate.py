"""The one table builder of the reproduce tables: rows of variables, columns that turn a row into a cell.

Every experiment's table is ``tabulate(rows, columns)``: ``rows`` are small dicts of what varies down the
table (``{"model": "koopman", "n": 20}``), each :class:`Column` a header and a function of the row. The cells
look records up in a :class:`Records` view of a results document and print them with
:mod:`~dks_gym.evaluation.formatting` (DAPPER's ``tabulate_avrgs`` idea: experiments are data, one builder).

A column of a field that only newer records hold (the relative L2 error) is ``optional``: :func:`tabulate`
leaves it out when every one of its cells is missing or blank, so the tables of older records print as they did.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .figures import MODEL_LABELS
from .formatting import MISSING, interval, markdown_table, mean_std, relative_score, sci, sig
from .paper import PAPER_DERIVED, PAPER_FINAL_MSE
from .results import Record, ResultsDocument, select

Row = Mapping[str, Any]

#: The scenario every experiment varies one thing of: the paper's defaults (r = 32, T = 1, 20 % noise).
DEFAULT_SCENARIO = {"initial": "approximate", "noise": 0.2, "r": 32, "T": 1}
#: Experiments whose runs differ from other experiments' runs of the same key (the calibrated filters' own Q
#: and P0; timing's one trajectory; parameter's calibrated runs): :meth:`Records.find` looks into them only when
#: asked by ``experiment=``.
OWN_RUNS = ("calibrated", "timing", "parameter")


class Records:
    """A results document's records looked up by their fields (``find(model="mlp", filter="ekf")``)."""

    def __init__(self, doc: ResultsDocument) -> None:
        self.doc = doc
        self.benchmark: str = doc["benchmark"]
        self.config: dict[str, Any] = doc["config"]
        self.experiments = {r["experiment"] for r in doc["records"]}

    def select(self, **criteria: Any) -> list[Record]:
        """Every record whose fields equal ``criteria``."""
        return select(self.doc, **criteria)

    def find(self, **criteria: Any) -> Record | None:
        """The record matching ``criteria`` in any experiment but those of :data:`OWN_RUNS` unless ``criteria``
        name one (the others repeat identical runs): of several, the one with the most fields (a rerun's, whose
        newer fields an older copy lacks), else the first."""
        found = self.select(**criteria)
        if "experiment" not in criteria:
            found = [r for r in found if r["experiment"] not in OWN_RUNS]
        return max(found, key=len) if found else None

    def base(self, **criteria: Any) -> Record | None:
        """The MLP forward run of a scenario: what the paper's bar charts divide by."""
        return self.find(model="mlp", filter="forward", **criteria)


@dataclass(frozen=True)
class Column:
    """One column of a table: its header, the function that makes a row's cell and whether the table drops
    it when all its cells are missing (``optional``: a field older records lack)."""

    header: str
    cell: Callable[[Row], str]
    optional: bool = False


def tabulate(rows: Iterable[Row], columns: Sequence[Column]) -> str:
    """A markdown table with one line per row and one cell per column, less the optional columns without
    a value (every cell missing or blank)."""
    rows = list(rows)
    cells = [[c.cell(row) for row in rows] for c in columns]
    kept = [i for i, c in enumerate(columns) if not c.optional or any(cell not in (MISSING, "") for cell in cells[i])]
    return markdown_table([columns[i].header for i in kept], [[cells[i][j] for i in kept] for j in range(len(rows))])


def label(row: Row) -> str:
    """The row's model as the paper names it."""
    return MODEL_LABELS.get(row["model"], row["model"])


# Cells ---------------------------------------------------------------------------------------------------
def mse(rec: Record | None) -> str:
    """A record's final-time MSE, mean ± sample std over the test trajectories."""
    return MISSING if rec is None else mean_std(rec["final_mse_mean"], rec["final_mse_std"])


def mse_ci95(rec: Record | None) -> str:
    """A record's stored interquartile mean of the final MSE over the trajectories and the 95 % bootstrap
    interval of its mean, ``IQM [low, high]`` (never recomputed: another scipy may draw differently); ``-`` for
    a record without them."""
    rec = rec or {}
    bounds = rec.get("final_mse_ci95")
    return MISSING if bounds is None else f"{sci(rec.get('final_mse_iqm'))} {interval(*bounds)}"


def mse_ratio(num: Record | None, den: Record | None) -> str:
    """The ratio of two records' mean final MSE (``-`` when either is missing or the denominator is 0)."""
    if num is None or den is None or not den["final_mse_mean"] or num["final_mse_mean"] is None:
        return MISSING
    return sig(num["final_mse_mean"] / den["final_mse_mean"])


def rel_l2(rec: Record | None) -> str:
    """A record's final relative L2 error, mean over the test trajectories, and its score (``-`` without)."""
    rec = rec or {}
    return relative_score(rec.get("final_rel_l2_mean"), rec.get("final_score_mean"))


def rel_l2_columns(headers: Mapping[str, str]) -> list[Column]:
    """Optional columns ``"{header} rel. L2 (score)"`` of the records at the rows' keys (key: header)."""
    return [Column(f"{name} rel. L2 (score)", lambda r, k=key: rel_l2(r[k]), optional=True)
            for key, name in headers.items()]


def max_norm(rec: Record | None) -> float | None:
    """max_k ||F_k||_2 over a record's trajectories (None without one)."""
    values = [v for v in (rec or {}).get("max_forecast_norm") or [] if v is not None]
    return max(values) if values else None


def over_steps(rec: Record, name: str) -> float | None:
    """The mean over frames 1..n_t-1 of a per-step score (frame 0 is the initial estimate, before any step)."""
    values = [v for v in (rec.get(name) or [])[1:] if v is not None]
    return float(np.mean(values)) if values else None


def paper_mse(benchmark: str, model: str, filt: str) -> str:
    """The paper's final MSE of ``model`` under ``filt``, ``≈`` when only derived from its text."""
    value = PAPER_FINAL_MSE.get(benchmark, {}).get((model, filt))
    if value is not None:
        return sci(value)
    derived = PAPER_DERIVED.get(benchmark, {}).get((model, filt))
    return f"≈{sci(derived[0])}" if derived else MISSING


__all__ = [
    "DEFAULT_SCENARIO",
    "Column",
    "Records",
    "Row",
    "label",
    "max_norm",
    "mse",
    "mse_ci95",
    "mse_ratio",
    "over_steps",
    "paper_mse",
    "rel_l2",
    "rel_l2_columns",
    "tabulate",
]
