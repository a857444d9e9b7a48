"""The checks of a results record's fields, for :func:`~dks_gym.evaluation.results.validate_record`.

The schema itself (what each field means) is :mod:`~dks_gym.evaluation.results`' docstring; here are the
number and list checks every field uses and :func:`check_optional_fields`, the checks of the fields after
``wall_time`` there, which newer records add and older ones lack (a missing optional field is never an error).
"""

from __future__ import annotations

import math
from typing import Any

from .intervals import INTERVAL_SOURCES

#: The scores of the predictive std a record may hold (``final_{name}_mean``, ``per_step_{name}_mean``).
UNCERTAINTY_SCORES = ("coverage", "nees", "crps")
#: The EnKF's rank histograms of the truth among its decoded members (n_members + 1 counts each).
RANK_HISTOGRAMS = ("rank_histogram_sensors", "rank_histogram_cells")


class ResultsError(ValueError):
    """A results file does not follow the schema; the message names the offending item."""


def is_number(x: Any, *, nullable: bool = True) -> bool:
    """A finite int or float (not a bool), or None when ``nullable``."""
    if x is None:
        return nullable
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def check_list(rec: dict[str, Any], name: str, where: str, length: int | None,
               what: str = "the record's batch") -> None:
    """``rec[name]`` is a list of numbers (null for non-finite), of ``length`` entries unless None."""
    values = rec[name]
    if not isinstance(values, list) or not all(is_number(v) for v in values):
        raise ResultsError(f"{where}: {name!r} must be a list of numbers (null for non-finite), got {values!r:.80}")
    if length is not None and len(values) != length:
        raise ResultsError(f"{where}: {name!r} has {len(values)} entries but {what} is {length}")


def _check_numbers(rec: dict[str, Any], where: str, names: tuple[str, ...]) -> None:
    for name in names:
        if not is_number(rec.get(name)):
            raise ResultsError(f"{where}: {name!r} must be a number or null, got {rec[name]!r}")


def _check_per_frame(rec: dict[str, Any], where: str, name: str) -> None:
    """A per-frame list, one entry per frame like ``per_step_mse_mean``, where present and not null."""
    if rec.get(name) is not None:
        check_list(rec, name, where, len(rec["per_step_mse_mean"]), "the number of frames")


def _check_relative(rec: dict[str, Any], where: str) -> None:
    """The optional relative L2 fields."""
    _check_numbers(rec, where, ("final_rel_l2_mean", "final_rel_l2_std", "final_score_mean"))
    if "per_trajectory_final_rel_l2" in rec:
        check_list(rec, "per_trajectory_final_rel_l2", where, rec["batch"])
    _check_per_frame(rec, where, "per_step_rel_l2_mean")


def _check_intervals(rec: dict[str, Any], where: str) -> None:
    """The optional interval fields (``{prefix}_iqm``, ``{prefix}_ci95``)."""
    for prefix, _ in INTERVAL_SOURCES:
        _check_numbers(rec, where, (f"{prefix}_iqm",))
        name, b = f"{prefix}_ci95", rec.get(f"{prefix}_ci95")
        if b is not None and not (isinstance(b, list) and len(b) == 2 and is_number(b[0], nullable=False)
                                  and is_number(b[1], nullable=False) and b[0] <= b[1]):
            raise ResultsError(f"{where}: {name!r} must be null or [low, high] with low <= high, got {b!r:.80}")


def _check_spread(rec: dict[str, Any], where: str) -> None:
    """The spread diagnostics: the spread-skill ratio (a number per frame) and the EnKF's rank histograms
    (n_members + 1 non-negative integer counts; an EnKF record's only)."""
    _check_numbers(rec, where, ("final_spread_skill",))
    _check_per_frame(rec, where, "per_step_spread_skill")
    for name in RANK_HISTOGRAMS:
        counts = rec.get(name)
        if counts is None:
            continue
        if rec["filter"] != "enkf":
            raise ResultsError(f"{where}: {name!r} belongs to an EnKF record, not to filter {rec['filter']!r}")
        if (not isinstance(counts, list) or len(counts) != rec["n_members"] + 1
                or not all(isinstance(c, int) and not isinstance(c, bool) and c >= 0 for c in counts)):
            raise ResultsError(f"{where}: {name!r} must be n_members + 1 = {rec['n_members'] + 1} counts "
                               f"(non-negative integers), got {counts!r:.80}")


def check_optional_fields(rec: dict[str, Any], where: str) -> None:
    """Raise :class:`ResultsError` for an optional field of ``rec`` that is present but malformed (the
    required fields are checked already: ``batch``, ``filter``, ``n_members``, ``per_step_mse_mean``)."""
    for name in ("trajectories", "params", "divergence_resets"):
        if name in rec:
            check_list(rec, name, where, rec["batch"])
    for score in UNCERTAINTY_SCORES:
        _check_numbers(rec, where, (f"final_{score}_mean",))
        _check_per_frame(rec, where, f"per_step_{score}_mean")
    _check_relative(rec, where)
    _check_intervals(rec, where)
    _check_spread(rec, where)
    for name in ("final_channel_mse_mean", "final_channel_nmse_mean", "final_channel_rel_l2_mean"):
        value = rec.get(name)
        if value is not None and (not isinstance(value, dict)
                                  or not all(isinstance(k, str) and is_number(v) for k, v in value.items())):
            raise ResultsError(f"{where}: {name!r} must map channel names to numbers, got {value!r}")
    for name in ("per_step_gain_norm_mean", "per_step_spread_mean"):
        if rec.get(name) is not None:
            check_list(rec, name, where, len(rec["per_step_mse_mean"]) - 1, "the number of filter steps")


__all__ = ["RANK_HISTOGRAMS", "UNCERTAINTY_SCORES", "ResultsError", "check_list", "check_optional_fields",
           "is_number"]
