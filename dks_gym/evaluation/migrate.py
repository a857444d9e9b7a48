"""``python -m dks_gym.evaluation.migrate [--relative] PATH...``: bring results files of an older dks-gym up to date.

Each results document given, or found under a folder given (``results.json.gz``, ``placement.json.gz`` and
their plain ``.json`` forms), is loaded, stamped with its benchmark's protocol
(:func:`~dks_gym.evaluation.conformance.stamp_protocol`: the protocol block, the records that leave it
marked), given the interval fields its records lack (:func:`add_intervals`: the interquartile mean and the
95 % bootstrap interval, computed from the per-episode values the records store) and written back
byte-reproducibly when that changed it; nothing else in the file changes. A file that names a protocol
already is stamped again (the same bytes unless the protocol's fields changed); interval fields a record
holds are kept as they are (a bootstrap may draw differently under another scipy), so a second run changes
nothing.

``--relative`` also derives the relative L2 fields that records older than them lack (:func:`add_relative`)
from the MSEs they store and the data they were computed on: Eq. 18's MSE is the mean of the squared error
over the ``N`` scored values of a frame (the scored channels times every cell) and the relative L2 error is
``||x^ - x|| / ||x||`` over the same values, so ``rel = sqrt(MSE N / ||x||^2)`` with ``x`` the true frame of
the record's test trajectory. That needs the dataset: the document's ``{benchmark}-{preset}.h5`` in the
data home (``$DKS_GYM_HOME``, or ``--data-home DIR``), refused when missing or when its fingerprint differs
from the document's. Records that carry the fields from their run are derived too and must agree with what
they store (:data:`RELATIVE_RTOL`), a check of the data and of the derivation.
What a record's MSEs do not determine stays absent: the per-frame mean (``per_step_rel_l2_mean``) of a
record that keeps only its final MSEs (every experiment but ``main``, every placement record), and the
per-channel errors (``final_channel_rel_l2_mean``) of a benchmark scoring several channels (the records keep
no per-trajectory MSE per channel).
"""

from __future__ import annotations

import argparse
import copy
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..benchmarks import get_benchmark
from ..dataset import Dataset, DatasetMissing, missing_message
from ..home import dataset_path
from ..models.checkpoint import dataset_identity
from .conformance import stamp_protocol
from .intervals import INTERVAL_SOURCES, interval_fields
from .results import RESULTS_FILE, ResultsError, load_results, relative_fields, save_results

#: The names results documents go by: reproduce's and the demo's, and the placement harness's
#: (``dks_gym_agents.records.PLACEMENT_FILE``, a later stage than this one; a test checks they agree).
RESULTS_NAMES = (RESULTS_FILE, "placement.json.gz", "results.json", "placement.json")
#: How closely a relative L2 error derived from a stored MSE must match the one its run stored: the run
#: sums in float64, the MSE it stores was summed in float32 (observed on the committed results: below 1e-7).
RELATIVE_RTOL = 1e-5


class DataMismatch(ValueError):
    """The data at hand is not the data a results document was computed on."""


def results_files(paths: Iterable[str | Path]) -> list[Path]:
    """The results documents among ``paths``: files as given, folders searched for :data:`RESULTS_NAMES`."""
    out: list[Path] = []
    for path in map(Path, paths):
        if path.is_dir():
            out += sorted(p for name in RESULTS_NAMES for p in path.rglob(name))
        elif path.exists():
            out.append(path)
        else:
            raise FileNotFoundError(f"no results file or folder at {path}")
    return list(dict.fromkeys(out))


def add_intervals(doc: dict[str, Any]) -> dict[str, Any]:
    """Give each record the interval fields it lacks (:func:`~dks_gym.evaluation.intervals.interval_fields`,
    from its stored per-episode values), appended after its other fields; those it holds stay. In place."""
    for record in doc["records"]:
        wanted = [f"{prefix}_{kind}" for prefix, source in INTERVAL_SOURCES if record.get(source) is not None
                  for kind in ("iqm", "ci95")]
        if any(name not in record for name in wanted):
            for name, value in interval_fields(record).items():
                record.setdefault(name, value)
    return doc


# The relative L2 error from the stored MSE --------------------------------------------------------------------
def open_dataset(doc: dict[str, Any], home: str | Path | None = None) -> Dataset:
    """The dataset a results document was computed on: ``{benchmark}-{preset}.h5`` in the data home (or in
    ``home``), refused (:class:`~dks_gym.dataset.DatasetMissing`, :class:`DataMismatch`) when it is missing or
    its fingerprint differs from the document's."""
    identity = doc["dataset"]
    preset = identity.get("preset") or doc["config"].get("data_preset") or "paper"
    path = dataset_path(doc["benchmark"], preset, home)
    if not path.exists():
        raise DatasetMissing(f"{missing_message(get_benchmark(doc['benchmark']), preset, path)} The relative L2 "
                             "errors are derived from the records' MSEs and the true fields of that file "
                             "(--data-home DIR: a data home holding it as DIR/data/" + path.name + ").")
    dataset = Dataset(path)
    found = dataset_identity(dataset)["fingerprint"]
    if found != identity.get("fingerprint"):
        dataset.close()
        raise DataMismatch(f"{path} is not the data these results were computed on: its fingerprint is "
                           f"{found[:12]}, the results name {str(identity.get('fingerprint'))[:12]} (created "
                           f"{identity.get('created')}). Regenerate it with `dks-gym data generate {doc['benchmark']} "
                           f"--preset {preset} --overwrite` or point --data-home at the home holding that data.")
    return dataset


def truth_norms(dataset: Dataset, split: str, trajectories: Iterable[int]) -> dict[int, np.ndarray]:
    """``||x_{i,k}||^2`` of each trajectory ``i`` of ``split`` at every frame ``k``, (n_t,) float64: the sum of
    squares over the scored channels and every cell, the values Eq. 18 averages over."""
    scored = list(dataset.benchmark.scored_indices)
    out = {}
    for i in sorted({int(t) for t in trajectories}):
        x = dataset.trajectory(split, i)[:, scored].astype(np.float64)
        out[i] = np.square(x).reshape(len(x), -1).sum(axis=1)
    return out


def _values(values: Any) -> np.ndarray:
    """Stored numbers (``null`` for non-finite) as float64 with NaN."""
    return np.array(values, dtype=np.float64)  # numpy reads None as NaN


def derived_relative(record: dict[str, Any], norms: dict[int, np.ndarray], n_values: int,
                     channels: Sequence[str]) -> dict[str, Any]:
    """A record's relative L2 fields (:func:`~dks_gym.evaluation.results.relative_fields`) derived from its stored
    MSEs: ``sqrt(MSE n_values / ||x||^2)`` per trajectory and frame (``n_values``: scored channels x cells,
    ``norms``: :func:`truth_norms` of its trajectories); NaN where the MSE is missing or the truth is 0. Per frame
    only from ``per_trajectory_step_mse``; per channel only with one scored channel (``channels``)."""
    trajectories = [int(t) for t in record["trajectories"]]
    curves = record.get("per_trajectory_step_mse")
    norm = np.stack([norms[t] for t in trajectories])  # (B, n_t): the record's frames are the dataset's (checked)
    if curves is not None:
        mse = _values(curves)
    else:  # the final frame alone
        mse, norm = _values(record["per_trajectory_final_mse"])[:, None], norm[:, -1:]
    with np.errstate(divide="ignore", invalid="ignore"):
        relative = np.where(norm > 0, np.sqrt(mse * n_values / np.where(norm > 0, norm, 1.0)), np.nan)
    single = len(channels) == 1
    fields = relative_fields(relative, relative[:, -1:] if single else relative[:, :0], channels if single else ())
    if curves is None:
        del fields["per_step_rel_l2_mean"]
    if not single:
        del fields["final_channel_rel_l2_mean"]
    return fields


@dataclass
class RelativeReport:
    """What :func:`add_relative` did: records given the fields, records whose stored fields it re-derived, and
    the largest relative difference between a stored and a derived error."""

    added: int = 0
    checked: int = 0
    max_deviation: float = 0.0
    notes: list[str] = field(default_factory=list)


def _deviation(stored: dict[str, Any], derived: dict[str, Any]) -> float:
    """The largest relative difference between the stored and derived per-trajectory (and per-frame) errors."""
    worst = 0.0
    for name in ("per_trajectory_final_rel_l2", "per_step_rel_l2_mean"):
        if name in stored and name in derived:
            a, b = _values(stored[name]), _values(derived[name])
            if not np.array_equal(np.isnan(a), np.isnan(b)):
                return np.inf
            both = ~np.isnan(a)
            worst = max(worst, float(np.max(np.abs(a[both] - b[both]) / np.abs(a[both]), initial=0.0)))
    return worst


def _check_record(record: dict[str, Any], dataset: Dataset, split: str, where: str) -> None:
    """Refuse a record whose trajectories the data cannot hold or whose parameters differ from the data's."""
    if record.get("trajectories") is None:
        raise ResultsError(f"{where} stores no 'trajectories': its relative errors cannot be derived")
    n = dataset.n_trajectories(split)
    if len(record["per_step_mse_mean"]) != dataset.n_frames or not all(0 <= t < n for t in record["trajectories"]):
        raise DataMismatch(f"{where} has {len(record['per_step_mse_mean'])} frames and trajectories up to "
                           f"{max(record['trajectories'])}; {dataset.path} has {dataset.n_frames} frames and {n} "
                           f"{split} trajectories")
    if record.get("params") is not None and not np.allclose(
            _values(record["params"]), dataset.params(split)[record["trajectories"]], rtol=1e-12, atol=0.0):
        raise DataMismatch(f"{where}: the parameters of its trajectories differ from those of {dataset.path}")


def add_relative(doc: dict[str, Any], dataset: Dataset) -> RelativeReport:
    """Give each record of ``doc`` that lacks them the relative L2 fields derived from its MSEs and the true
    fields of ``dataset`` (:func:`derived_relative`), appended after its other fields; derive those a record
    holds too and refuse (:class:`DataMismatch`) where they differ by more than :data:`RELATIVE_RTOL`. In place."""
    split = doc["config"].get("split", "test")
    channels = tuple(dataset.scored_channels)
    if list(doc["config"].get("scored_channels", channels)) != list(channels):
        raise DataMismatch(f"the results score {doc['config']['scored_channels']}, {dataset.path} scores "
                           f"{list(channels)}")
    norms = truth_norms(dataset, split, (t for r in doc["records"] for t in r.get("trajectories") or ()))
    n_values = len(channels) * int(np.prod(dataset.grid))
    report = RelativeReport()
    for i, record in enumerate(doc["records"]):
        where = f"records[{i}] ({record['experiment']}, {record['model']}, {record['filter']})"
        _check_record(record, dataset, split, where)
        derived = derived_relative(record, norms, n_values, channels)
        if "final_rel_l2_mean" not in record:
            record.update(derived)
            report.added += 1
            continue
        deviation = _deviation(record, derived)
        if not deviation <= RELATIVE_RTOL:
            raise DataMismatch(f"{where}: the relative L2 errors it stores and those derived from its MSEs and "
                               f"{dataset.path} differ by up to {deviation:.2g} (relative): not the data it was "
                               "computed on")
        report.checked += 1
        report.max_deviation = max(report.max_deviation, deviation)
    if report.added and len(channels) > 1:
        report.notes.append(f"final_channel_rel_l2_mean not derived ({len(channels)} scored channels)")
    return report


# Files ---------------------------------------------------------------------------------------------------
def _lacks_relative(doc: dict[str, Any]) -> bool:
    return any("final_rel_l2_mean" not in r for r in doc["records"])


def migrate_file(path: str | Path, *, relative: bool = False, home: str | Path | None = None,
                 log: Any = None) -> bool:
    """Stamp the protocol into one results file, add its missing intervals and, with ``relative``, its missing
    relative L2 fields (the data from the data home or ``home``: :func:`open_dataset`); return whether it
    changed. ``log``: called with a line saying what the relative step did."""
    doc = load_results(path)
    migrated = stamp_protocol(copy.deepcopy(doc))
    if relative and _lacks_relative(migrated):
        with open_dataset(migrated, home) as dataset:
            report = add_relative(migrated, dataset)
        if log is not None:
            checked = (f"; {report.checked} stored ones reproduced to {report.max_deviation:.1e}"
                       if report.checked else "")
            log(f"{path}: relative L2 derived for {report.added} records{checked}"
                + "".join(f"; {note}" for note in report.notes))
    add_intervals(migrated)
    if migrated == doc and list(migrated) == list(doc):
        return False
    save_results(migrated, path)
    return True


def migrate(paths: Iterable[str | Path], *, relative: bool = False, home: str | Path | None = None) -> list[Path]:
    """Migrate every results file among ``paths`` (:func:`results_files`); return those that changed."""
    return [path for path in results_files(paths) if migrate_file(path, relative=relative, home=home)]


def main(argv: Sequence[str] | None = None) -> int:
    """The command line: migrate the files and folders named, print what changed."""
    parser = argparse.ArgumentParser(prog="python -m dks_gym.evaluation.migrate",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="+", metavar="PATH", help="results files, or folders to search for them")
    parser.add_argument("--relative", action="store_true",
                        help="derive the relative L2 fields records lack from their MSEs and the data")
    parser.add_argument("--data-home", metavar="DIR", default=None,
                        help="the data home holding DIR/data/BENCHMARK-PRESET.h5 (default: $DKS_GYM_HOME)")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    if args.data_home is not None and not args.relative:
        parser.error("--data-home is read by --relative only")
    files = results_files(args.paths)
    changed = [path for path in files if migrate_file(path, relative=args.relative, home=args.data_home, log=print)]
    for path in changed:
        print(f"migrated {path}")
    print(f"{len(changed)} of {len(files)} results files changed")
    return 0


__all__ = ["RELATIVE_RTOL", "RESULTS_NAMES", "DataMismatch", "RelativeReport", "add_intervals", "add_relative",
           "derived_relative", "main", "migrate", "migrate_file", "open_dataset", "results_files", "truth_norms"]

if __name__ == "__main__":
    sys.exit(main())
