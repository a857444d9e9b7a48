"""``reproduce --only parameter``: when the physical parameter is unknown (not in the paper).

Each model under the EKF and the EnKF (n = 20), calibrated Q and P0, three ways: told the true mu
(``known``, the other experiments' setting), estimating it with the state (``estimate``, prior: a uniform over
the training range, :mod:`dks_gym.filters.parameter`), and assuming the prior's mean (``prior``, what a filter
without the value would do). The tables give the field's relative L2 error of the three, the estimated-mu
filter's error over the known-mu one's, and how well mu itself was found: the median relative error at the
final frame, how many test trajectories hold the true mu in the 95 % interval, and the final std over the
prior's (near 1: the sensors do not identify mu); one figure shows the parameter's error over time.
"""

from __future__ import annotations

from pathlib import Path


from ..assimilation import AssimilationResult
from ..assimilation.config import PARAMETER_CHOICES
from ..dataset import Dataset
from .experiment import Experiment, Run, Section, register
from .figures import FILTER_LABELS, MODEL_ORDER, parameter_figure
from .formatting import MISSING, fixed, percent, sig
from .tabulate import Column, Records, label, mse_ratio, rel_l2, tabulate

PARAMETER_FILTERS = ("ekf", "enkf")


def _scores(rec: dict | None) -> dict:
    return (rec or {}).get("parameter_scores") or {}


def _in_interval(rec: dict | None) -> str:
    scores = _scores(rec)
    if "final_in_interval_fraction" not in scores:
        return MISSING
    n = len(scores["per_trajectory_final_estimate"])
    return f"{round(scores['final_in_interval_fraction'] * n)}/{n}"


@register
class Parameter(Experiment):
    name = "parameter"
    description = "EKF and EnKF told mu, estimating it with the state, or assuming the prior's mean"

    def runs(self) -> list[Run]:
        return [Run(m, f, calibrated=True, parameter=p) for p in PARAMETER_CHOICES for f in PARAMETER_FILTERS
                for m in MODEL_ORDER]

    def tables(self, records: Records) -> list[Section]:
        rows = []
        for f in PARAMETER_FILTERS:
            for m in MODEL_ORDER:
                row = {"model": m, "filter": f}
                for p in PARAMETER_CHOICES:
                    row[p] = records.find(experiment="parameter", model=m, filter=f, parameter=p)
                rows.append(row)
        columns = [Column("model", label), Column("filter", lambda r: FILTER_LABELS[r["filter"]]),
                   Column("mu known: rel. L2 (score)", lambda r: rel_l2(r["known"])),
                   Column("mu estimated", lambda r: rel_l2(r["estimate"])),
                   Column("mu = prior mean", lambda r: rel_l2(r["prior"])),
                   Column("MSE estimated / known", lambda r: mse_ratio(r["estimate"], r["known"])),
                   Column("mu: median rel. error", lambda r: percent(_scores(r["estimate"]).get(
                       "final_relative_error_median"))),
                   Column("true mu in 95 % interval", lambda r: _in_interval(r["estimate"])),
                   Column("outside the training range", lambda r: fixed(_scores(r["estimate"]).get(
                       "final_out_of_range_fraction"), 2)),
                   Column("final std / prior std", lambda r: sig(_scores(r["estimate"]).get(
                       "final_std_ratio_median"), 2))]
        body = ("Final frame, mean over the test trajectories; the prior of the estimated mu is a uniform over the "
                "training range (in log mu where it spans a decade), its mean assumed by the third filter.",
                tabulate(rows, columns))
        return [Section("The parameter unknown: estimated with the state", body)]

    def figures(self, records: Records, folder: Path, results: dict[tuple, AssimilationResult] | None = None,
                dataset: Dataset | None = None) -> list[Path]:
        curves = {(m, f): scores["per_step_relative_error_median"] for f in PARAMETER_FILTERS for m in MODEL_ORDER
                  if (scores := _scores(records.find(experiment="parameter", model=m, filter=f,
                                                     parameter="estimate")))}
        return [parameter_figure(curves, folder / "parameter.png",
                                 title=f"{records.benchmark}: the parameter estimated with the state")]


__all__ = ["PARAMETER_FILTERS", "Parameter"]
