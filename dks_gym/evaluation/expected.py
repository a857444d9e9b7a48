"""What the shipped models score under each benchmark's protocol: one table of expected scores (DAPPER's
"suggested tuning" convention), and the check that a machine reproduces it.

:data:`EXPECTED_SCORES` holds, for each benchmark with shipped models, each of the four ``lite`` models and
each filter (the forward run, the EKF and the EnKF with n = 20, calibrated Q and P0, the defaults a user meets):
the final-frame relative L2 error over the scored channels (mean over the protocol's test trajectories), its
95 % stratified bootstrap interval, and the 95 % coverage of the predictive std (the fraction of scored cells
whose truth lies in the central 95 % interval, final frame, mean over trajectories; the forward run's is not
tabulated). The values are those of the committed ``calibrated`` experiment (docs/results/BENCHMARK) to four
significant digits, under the protocol named by :data:`EXPECTED_PROTOCOL`.

``dks-gym expected BENCHMARK --check`` reruns the twelve runs with the shipped files on the local data and
compares them to three digits; the test suite does so for Burgers on freshly generated data. A changed shipped
weight, filter or scoring shows up as a mismatch here before it shows up in anyone's paper.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass

from ..assimilation import AssimilationConfig, run_assimilation
from ..benchmarks.protocol import PROTOCOL_NAME, PROTOCOL_VERSION, get_protocol
from ..dataset import Dataset
from ..models import FilterableModel, load_model
from ..models.shipped import find_shipped
from ..names import FILTERS, MODEL_KINDS
from .formatting import fixed, interval, markdown_table, percent
from .results import Record, make_record

#: The protocol (name, version) the table was measured under.
EXPECTED_PROTOCOL = (PROTOCOL_NAME, PROTOCOL_VERSION)
#: Agreement asked of a rerun: relative difference of each number (three significant digits; the table keeps four).
EXPECTED_RTOL = 1e-3


@dataclass(frozen=True)
class ExpectedScore:
    """The expected scores of one model and filter on one benchmark."""

    relative_l2: float
    """Final-frame relative L2 error ||x^ - x|| / ||x|| over the scored channels, mean over test trajectories."""
    relative_l2_ci95: tuple[float, float]
    """Its 95 % stratified bootstrap interval over trajectories and noise seeds (``final_rel_l2_ci95``)."""
    coverage: float | None
    """Fraction of scored cells whose truth lies in the central 95 % predictive interval, final frame, mean over
    trajectories; None for the forward run (its std, P0 and Q carried without an update, is not a filter's and
    the committed runs do not score it)."""


# fmt: off
#: Expected scores by benchmark, then (model, filter): the shipped lite models (r = 32, T = 1) under the
#: benchmark's protocol (20 % noise, seed 0, 16 sensors on the paper layout, test split, approximate initial
#: condition), calibrated Q and P0, EnKF n = 20. From `dks-gym reproduce BENCHMARK --only calibrated --no-train`.
EXPECTED_SCORES: dict[str, dict[tuple[str, str], ExpectedScore]] = {
    "burgers": {
        ("koopman", "forward"): ExpectedScore(0.01033, (0.006474, 0.01501), None),
        ("pdmd", "forward"): ExpectedScore(0.0004417, (0.0003163, 0.000672), None),
        ("mlp", "forward"): ExpectedScore(0.01794, (0.01155, 0.0247), None),
        ("xlstm", "forward"): ExpectedScore(0.04471, (0.02794, 0.06356), None),
        ("koopman", "ekf"): ExpectedScore(0.009423, (0.005218, 0.01491), 0.8428),
        ("pdmd", "ekf"): ExpectedScore(0.0004418, (0.0003163, 0.0006726), 0.7973),
        ("mlp", "ekf"): ExpectedScore(0.01905, (0.0135, 0.02553), 0.9243),
        ("xlstm", "ekf"): ExpectedScore(0.02445, (0.0149, 0.03642), 0.8801),
        ("koopman", "enkf"): ExpectedScore(0.009305, (0.005224, 0.01444), 0.8042),
        ("pdmd", "enkf"): ExpectedScore(0.0004538, (0.0003265, 0.0006881), 0.7648),
        ("mlp", "enkf"): ExpectedScore(0.01951, (0.01402, 0.02623), 0.9289),
        ("xlstm", "enkf"): ExpectedScore(0.02452, (0.01535, 0.03721), 0.8883),
    },
    "cylinder": {
        ("koopman", "forward"): ExpectedScore(0.2085, (0.17, 0.2518), None),
        ("pdmd", "forward"): ExpectedScore(0.2188, (0.1698, 0.2871), None),
        ("mlp", "forward"): ExpectedScore(0.1987, (0.1478, 0.249), None),
        ("xlstm", "forward"): ExpectedScore(0.1799, (0.1278, 0.2353), None),
        ("koopman", "ekf"): ExpectedScore(0.1517, (0.1327, 0.1722), 0.8418),
        ("pdmd", "ekf"): ExpectedScore(0.04942, (0.03992, 0.06301), 0.9749),
        ("mlp", "ekf"): ExpectedScore(0.07531, (0.06763, 0.08269), 0.945),
        ("xlstm", "ekf"): ExpectedScore(0.06088, (0.05712, 0.06524), 0.9583),
        ("koopman", "enkf"): ExpectedScore(0.1403, (0.123, 0.158), 0.8204),
        ("pdmd", "enkf"): ExpectedScore(0.0589, (0.04541, 0.07863), 0.9006),
        ("mlp", "enkf"): ExpectedScore(0.07712, (0.06688, 0.08797), 0.9371),
        ("xlstm", "enkf"): ExpectedScore(0.06043, (0.05757, 0.06404), 0.9546),
    },
    "dambreak": {
        ("koopman", "forward"): ExpectedScore(0.228, (0.1649, 0.2962), None),
        ("pdmd", "forward"): ExpectedScore(0.118, (0.08862, 0.1527), None),
        ("mlp", "forward"): ExpectedScore(0.3913, (0.2996, 0.4864), None),
        ("xlstm", "forward"): ExpectedScore(0.878, (0.6543, 1.143), None),
        ("koopman", "ekf"): ExpectedScore(0.2298, (0.1938, 0.2736), 0.9589),
        ("pdmd", "ekf"): ExpectedScore(0.4001, (0.3201, 0.4775), 0.9716),
        ("mlp", "ekf"): ExpectedScore(0.2267, (0.1608, 0.3286), 0.9667),
        ("xlstm", "ekf"): ExpectedScore(0.2728, (0.2077, 0.3488), 0.9361),
        ("koopman", "enkf"): ExpectedScore(0.231, (0.1996, 0.266), 0.9154),
        ("pdmd", "enkf"): ExpectedScore(0.5568, (0.4015, 0.7557), 0.7803),
        ("mlp", "enkf"): ExpectedScore(0.2646, (0.2004, 0.355), 0.9601),
        ("xlstm", "enkf"): ExpectedScore(0.2907, (0.2163, 0.3747), 0.9417),
    },
}
# fmt: on


def expected_scores(benchmark: str) -> dict[tuple[str, str], ExpectedScore]:
    """The expected scores of ``benchmark`` by (model, filter), or a ValueError naming the benchmarks that have them."""
    key = str(benchmark).lower()
    if key not in EXPECTED_SCORES:
        raise ValueError(f"no expected scores for {benchmark!r}: models ship for {', '.join(EXPECTED_SCORES)} only "
                         "(the sphere has no trained models yet)")
    return EXPECTED_SCORES[key]


def scores_of(records: Iterable[Record]) -> dict[tuple[str, str], ExpectedScore]:
    """The expected-score view of records (one per model and filter, e.g. a demo's or a ``calibrated`` run's)."""
    out = {}
    for rec in records:
        low, high = rec.get("final_rel_l2_ci95") or (math.nan, math.nan)
        out[(rec["model"], rec["filter"])] = ExpectedScore(rec["final_rel_l2_mean"], (low, high),
                                                           rec.get("final_coverage_mean"))
    return out


def shipped_models(benchmark: str, dataset: Dataset, device: str = "cpu") -> dict[str, FilterableModel]:
    """The four shipped lite models of ``benchmark``, loaded from the package (never the user's own checkpoints);
    a ValueError saying what differs when ``dataset`` is not the data they were trained on."""
    models = {}
    for kind in MODEL_KINDS:
        shipped = find_shipped(benchmark, kind)
        if shipped is None:
            raise ValueError(f"no shipped {kind} model for {benchmark!r}")
        differences = shipped.differences(dataset)
        if differences:
            raise ValueError(f"the shipped {kind} model of {benchmark} was trained on other data than "
                             f"{dataset.path.name}: {'; '.join(differences)}. Expected scores hold for the "
                             f"protocol's data: `dks-gym data generate {benchmark} --preset paper`")
        models[kind] = load_model(benchmark, kind, dataset=dataset, path=shipped.path, device=device, progress=False)
    return models


def run_filters(models: Mapping[str, FilterableModel], dataset: Dataset, *, experiment: str,
                filters: Sequence[str] = FILTERS, base: AssimilationConfig | None = None,
                on_record: Callable[[Record], None] | None = None, progress: bool = False) -> list[Record]:
    """One record per filter and model (filters outer, models inner): each model's whole test split under
    ``base`` (default: the protocol's settings with calibrated Q and P0) with ``kind`` set to the filter.
    ``on_record(record)`` is called after each run (a progress bar's hook)."""
    base = AssimilationConfig() if base is None else base
    records = []
    for filt in filters:
        for kind, model in models.items():
            result = run_assimilation(model, dataset, base.replace(kind=filt), progress=progress,
                                      description=f"{kind} {filt}")
            records.append(make_record(result, experiment=experiment, keep_curves=False))
            if on_record is not None:
                on_record(records[-1])
    return records


def measure_expected(benchmark: str, dataset: Dataset, *, device: str = "cpu",
                     on_record: Callable[[Record], None] | None = None, progress: bool = False) -> list[Record]:
    """Rerun the expected-score table's runs for ``benchmark`` with the shipped models on ``dataset``: the
    forward run, EKF and EnKF of each model under the protocol (a ValueError if ``AssimilationConfig``'s
    defaults no longer match it). About 30 s for Burgers on one core, minutes for the CFD benchmarks."""
    base = AssimilationConfig()
    protocol = get_protocol(benchmark)
    settings = {"noise_level": base.noise_level, "noise_seeds": [base.noise_seed], "split": base.split,
                "initial": base.filter.initial, "data_preset": dataset.preset}
    deviations = protocol.deviations(settings)
    if base.n_sensors != protocol.default_n_sensors:
        deviations["default_n_sensors"] = base.n_sensors
    if deviations:
        raise ValueError(f"the default assimilation settings leave the {protocol.name} protocol: {deviations}")
    return run_filters(shipped_models(benchmark, dataset, device), dataset, experiment="expected",
                       base=base, on_record=on_record, progress=progress)


@dataclass(frozen=True)
class Mismatch:
    """One number of a rerun that differs from the table by more than :data:`EXPECTED_RTOL`."""

    model: str
    filter: str
    field: str
    expected: float | None
    measured: float | None

    def __str__(self) -> str:
        return f"{self.model} {self.filter} {self.field}: expected {self.expected}, measured {self.measured}"


def compare_expected(benchmark: str, measured: Mapping[tuple[str, str], ExpectedScore],
                     rtol: float = EXPECTED_RTOL) -> list[Mismatch]:
    """Every number of the table for ``benchmark`` that ``measured`` does not reproduce to ``rtol`` (a missing
    run or number counts as a mismatch; an untabulated one, the forward run's coverage, is not checked). Empty:
    the rerun reproduces the table."""
    out = []
    for (model, filt), want in expected_scores(benchmark).items():
        got = measured.get((model, filt))
        pairs = [("relative_l2", want.relative_l2, got and got.relative_l2),
                 ("relative_l2_ci95 low", want.relative_l2_ci95[0], got and got.relative_l2_ci95[0]),
                 ("relative_l2_ci95 high", want.relative_l2_ci95[1], got and got.relative_l2_ci95[1]),
                 ("coverage", want.coverage, got and got.coverage)]
        for name, a, b in pairs:
            if not _agrees(a, b, rtol):
                out.append(Mismatch(model, filt, name, a, b))
    return out


def _agrees(expected: float | None, measured: float | None, rtol: float) -> bool:
    if expected is None:  # nothing tabulated (the forward run's coverage)
        return True
    if measured is None:
        return False
    # the table keeps four significant digits: allow their rounding on top of rtol
    return abs(measured - expected) <= rtol * abs(expected) + 0.5 * 10 ** (math.floor(math.log10(abs(expected))) - 3)


def expected_table(benchmark: str, measured: Mapping[tuple[str, str], ExpectedScore] | None = None) -> str:
    """The markdown table of ``benchmark``'s expected scores; with ``measured``, a rerun's numbers beside them."""
    header = ["model", "filter", "relative L2", "95 % CI", "score", "95 % coverage"]
    if measured is not None:
        header += ["measured rel. L2", "measured coverage"]
    rows = []
    for (model, filt), want in expected_scores(benchmark).items():
        row = [model, filt, percent(want.relative_l2), interval(*want.relative_l2_ci95, fmt=percent),
               fixed(100 * (1 - want.relative_l2), 1), fixed(want.coverage, 3)]
        if measured is not None:
            got = measured.get((model, filt))
            row += [percent(got and got.relative_l2), fixed(got and got.coverage, 3)]
        rows.append(row)
    return markdown_table(header, rows)


def expected_markdown() -> str:
    """docs/results/expected.md: every benchmark's table, with the protocol and the commands (ends in a newline)."""
    name, version = EXPECTED_PROTOCOL
    parts = ["# Expected scores of the shipped models", "",
             f"What the shipped lite models (r = 32, T = 1) score under each benchmark's protocol ({name} v{version}: "
             "test split, 20 % noise with seed 0, 16 sensors on the paper layout, approximate initial condition, "
             "scored channels over the final frame), with calibrated Q and P0 and an EnKF of 20 members. Relative "
             "L2: ||x^ - x|| / ||x|| over the scored channels, mean over the test trajectories, with its 95 % "
             "stratified bootstrap interval; score: 100 (1 - relative L2); 95 % coverage: the fraction of scored "
             "cells whose truth lies in the central 95 % predictive interval (1.96 predicted std), 0.95 when the "
             "predicted std is calibrated (not tabulated for the forward run, whose std is P0 and Q carried "
             "without an update).", "",
             "The table ships in the package (`dks_gym.evaluation.expected.EXPECTED_SCORES`); `dks-gym expected "
             "BENCHMARK --check` reruns it on the local data with the shipped files and fails on a difference in "
             "the third significant digit (the test suite checks Burgers on freshly generated data). This page is "
             "`dks-gym expected --markdown`."]
    for benchmark in EXPECTED_SCORES:
        parts += ["", f"## {benchmark.capitalize()}", "", expected_table(benchmark)]
    return "\n".join(parts) + "\n"


__all__ = ["EXPECTED_PROTOCOL", "EXPECTED_RTOL", "EXPECTED_SCORES", "ExpectedScore", "Mismatch", "compare_expected",
           "expected_markdown", "expected_scores", "expected_table", "measure_expected", "run_filters",
           "scores_of", "shipped_models"]
