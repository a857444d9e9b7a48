"""The results file of ``dks-gym reproduce``: a versioned JSON schema, atomic save, validation, comparison.

One file holds the runs of one benchmark with one model preset::

    {
      "schema": "dks-gym-results", "schema_version": 1,
      "benchmark": "burgers", "preset": "lite",
      "protocol": {"name", "version", ..., "deviations"},          # optional: the protocol the runs follow
                                                                     # (dks_gym.evaluation.conformance)
      "dataset": {"path", "preset", "created", "fingerprint"},      # identity of the data evaluated on
      "config": {...},                                               # what every record shares (sensors, P0, Q, seeds,
                                                                     # device, versions, created, ...)
      "models": [{"model", "r", "T", "preset", "checkpoint", "steps", "train_time_s", ...}],   # optional
      "records": [RECORD, ...]
    }

A RECORD is one (experiment, model, filter, initial, noise, r, T, n_members, parameter) run over the test split::

    experiment  str     "main", "enkf", "ensemble", "noise", "latent", "multistep", "operator_norm", "timing"
    model       str     "koopman", "pdmd", "mlp", "xlstm"; or an estimator's name (filter "none"): "shred", a user's
    filter      str     "forward", "ekf", "enkf"; "none" for an estimator (r: its output rank)
    initial     str     "approximate", "exact"
    noise       float   noise level (sigma / max |observed channel|)
    r, T        int     latent dimension, training horizon
    n_members   int | null      EnKF ensemble size (null otherwise)
    batch       int     trajectories run together (the test split, or 1 for timing)
    final_mse_mean, final_mse_std   float | null   Eq. 18 at the final frame, mean and sample std over trajectories
    per_step_mse_mean               [n_t]          mean over trajectories at every frame (frame 0 = initial estimate)
    per_trajectory_final_mse        [B]
    per_trajectory_step_mse         [B][n_t]       (optional) for the temporal error figures
    max_forecast_norm               [B] | null     max_k ||F_k||_2 per trajectory (EKF, forward run)
    da_step_seconds                 float          mean wall time of one filter step of the whole batch
    wall_time                       float          seconds for the whole run
    trajectories, params            [B]            (optional) test indices and parameter values
    divergence_resets               [B]            (optional) restarts after a non-finite filter state
    final_coverage_mean, final_nees_mean, final_crps_mean    float | null   (optional) scores of the predictive
                                    std (``estimate_std``) at the final frame, mean over trajectories: the
                                    fraction of scored cells inside the central 95 % interval, the mean NEES
                                    per cell, the mean Gaussian CRPS (physical units); null without uncertainty
    per_step_coverage_mean, per_step_nees_mean, per_step_crps_mean   [n_t] | null   (optional) the same per frame
    final_channel_mse_mean, final_channel_nmse_mean   {channel: float}   (optional) Eq. 18 at the final frame per
                                    scored channel, mean over trajectories, in physical units and over the
                                    channel standardized by its data std (comparable across channels)
    per_step_gain_norm_mean, per_step_spread_mean     [n_t - 1]   (optional) ||K_k||_2 and the filter's spread
                                    sqrt(tr P / r) after each step, mean over trajectories
    final_rel_l2_mean, final_rel_l2_std   float | null   (optional) the relative L2 error ||x^ - x|| / ||x|| at the
                                    final frame (the cells, channels and units of Eq. 18; null where the truth
                                    is 0), mean and sample std over trajectories
    per_step_rel_l2_mean            [n_t]          (optional) its mean over trajectories at every frame
    per_trajectory_final_rel_l2     [B]            (optional)
    final_score_mean                float | null   (optional) 100 (1 - relative L2) at the final frame, mean over
                                    trajectories (the Common Task Framework's score; negative beyond 1)
    final_channel_rel_l2_mean       {channel: float}   (optional) the relative L2 error of each scored channel at
                                    the final frame, mean over trajectories
    parameter                       str            (optional, part of the key; absent: "known") how the filter
                                    treated mu: "estimate" (with the state), "prior" (the prior's mean assumed)
    parameter_scores                {...}          (optional) an estimated mu's scores: relative error, 95 %
                                    interval coverage, out-of-range fraction (assimilation.parameter_summary)
    final_mse_iqm, final_mse_ci95   float | null, [low, high] | null   (optional) the interquartile mean and the
                                    95 % percentile bootstrap interval of the mean of ``per_trajectory_final_mse``,
                                    resampled within trajectories when they repeat (noise seeds); the same for
                                    ``final_rel_l2_*`` and a placement record's ``time_mean_mse_*``
                                    (:mod:`~dks_gym.evaluation.intervals`); tables print them as stored
    final_spread_skill, per_step_spread_skill   float | null, [n_t] | null   (optional) the spread-skill ratio
                                    sqrt(mean over trajectories of the predicted MSE (mean std^2 over the scored
                                    cells) / mean over trajectories of the MSE), at the final frame and per frame:
                                    1 when calibrated, < 1 overconfident (:mod:`~dks_gym.assimilation.spread`);
                                    null without uncertainty
    rank_histogram_sensors, rank_histogram_cells   [n_members + 1] ints   (optional, EnKF with uncertainty) how
                                    often the noise-free truth ranked 0..n among the decoded members, over every
                                    trajectory and frame 1..n_t-1, at the sensors read and at 8 fixed fluid
                                    cells (``spread.rank_cells``); flat when calibrated

A record may carry ``protocol_deviations`` ([str]: the protocol fields its run leaves). ``protocol`` is
optional, so the files of an older dks-gym stay valid under ``schema_version`` 1: it adds to the schema
without changing what any other field means. Non-finite numbers are stored as ``null`` (strict JSON).
:func:`compare` pairs the records of two files by their key and gives the ratios B / A.
"""

from __future__ import annotations

import gzip
import json
import math
from collections.abc import Iterable
from pathlib import Path
from typing import Any, TypedDict

import numpy as np

from ..assimilation import ctf_score, parameter_summary
from ..assimilation.config import PARAMETER_CHOICES
from ..atomic import atomic_path
from ..names import FILTERS, MODEL_KINDS
from .intervals import interval_fields
from .record_fields import UNCERTAINTY_SCORES, ResultsError, check_list, check_optional_fields, is_number

SCHEMA = "dks-gym-results"
SCHEMA_VERSION = 1
#: The name every writer gives its results file (gzip-compressed JSON: a tenth of the plain size).
RESULTS_FILE = "results.json.gz"
RECORD_KEY = ("experiment", "model", "filter", "initial", "noise", "r", "T", "n_members", "parameter")
#: A key field a record may leave out, and its value then (files made before it read the same).
KEY_DEFAULTS = {"parameter": "known"}
RECORD_FILTERS = FILTERS + ("none",)  # "none": an estimator's record (no filter)
INITIALS = ("approximate", "exact")
PARAMETERS = (*PARAMETER_CHOICES, "assumed")  # "assumed": a value given by the caller
_REQUIRED_TOP = ("schema", "schema_version", "benchmark", "preset", "dataset", "config", "records")
_REQUIRED_RECORD = RECORD_KEY[:-1] + (
    "batch", "final_mse_mean", "final_mse_std", "per_step_mse_mean", "per_trajectory_final_mse",
    "max_forecast_norm", "da_step_seconds", "wall_time",
)


class _RecordKey(TypedDict):
    experiment: str
    model: str
    filter: str
    initial: str
    noise: float
    r: int
    T: int
    n_members: int | None
    batch: int
    final_mse_mean: float | None
    final_mse_std: float | None
    per_step_mse_mean: list[float | None]
    per_trajectory_final_mse: list[float | None]
    max_forecast_norm: list[float | None] | None
    da_step_seconds: float | None
    wall_time: float | None


class Record(_RecordKey, total=False):
    """One run's record (the fields of the schema above); the optional fields are those after ``wall_time``
    there, and a harness may add fields of its own (the placement records: ``policy``, ``sensors`` ...)."""

    per_trajectory_step_mse: list[list[float | None]]
    trajectories: list[int]
    params: list[float | None]
    divergence_resets: list[int]
    final_coverage_mean: float | None
    final_nees_mean: float | None
    final_crps_mean: float | None
    per_step_coverage_mean: list[float | None] | None
    per_step_nees_mean: list[float | None] | None
    per_step_crps_mean: list[float | None] | None
    final_channel_mse_mean: dict[str, float | None]
    final_channel_nmse_mean: dict[str, float | None]
    per_step_gain_norm_mean: list[float | None]
    per_step_spread_mean: list[float | None]
    final_rel_l2_mean: float | None
    final_rel_l2_std: float | None
    per_step_rel_l2_mean: list[float | None]
    per_trajectory_final_rel_l2: list[float | None]
    final_score_mean: float | None
    final_channel_rel_l2_mean: dict[str, float | None]
    final_mse_iqm: float | None
    final_mse_ci95: list[float] | None
    final_rel_l2_iqm: float | None
    final_rel_l2_ci95: list[float] | None
    final_spread_skill: float | None
    per_step_spread_skill: list[float | None] | None
    rank_histogram_sensors: list[int]
    rank_histogram_cells: list[int]


class _DocumentRequired(TypedDict):
    schema: str
    schema_version: int
    benchmark: str
    preset: str
    dataset: dict[str, Any]
    config: dict[str, Any]
    records: list[Record]


class ResultsDocument(_DocumentRequired, total=False):
    """A results file's content (the layout above)."""

    protocol: dict[str, Any]
    models: list[dict[str, Any]]


# Building ----------------------------------------------------------------------------------------------
def _number(x: Any) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def _numbers(values: Any) -> Any:
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim == 0:
        return _number(arr)
    return [_numbers(v) for v in arr] if arr.ndim > 1 else [_number(v) for v in arr]


def make_record(result: Any, *, experiment: str, T: int = 1, keep_curves: bool = True) -> Record:
    """A schema record from an :class:`~dks_gym.assimilation.AssimilationResult`."""
    cfg = result.config
    record: Record = {
        "experiment": experiment,
        "model": result.model,
        "filter": cfg.filter.kind,
        "initial": cfg.filter.initial,
        "noise": float(cfg.noise_level),
        "r": int(result.r),
        "T": int(T),
        "n_members": int(cfg.filter.n_members) if cfg.filter.kind == "enkf" else None,
        "batch": int(result.batch),
        "final_mse_mean": _number(result.final_mse_mean),
        "final_mse_std": _number(result.final_mse_std),
        "per_step_mse_mean": _numbers(result.per_step_mse_mean),
        "per_trajectory_final_mse": _numbers(result.final_mse),
        "max_forecast_norm": None if result.max_forecast_norm is None else _numbers(result.max_forecast_norm),
        "da_step_seconds": _number(result.da_step_seconds),
        "wall_time": _number(result.wall_time),
        "trajectories": [int(i) for i in result.trajectories],
        "params": _numbers(result.params),
        "divergence_resets": [int(n) for n in result.divergence_resets],
    }
    for name in UNCERTAINTY_SCORES:
        steps = getattr(result, f"step_{name}", None)
        record[f"final_{name}_mean"] = None if steps is None else _number(np.mean(steps[:, -1]))
        record[f"per_step_{name}_mean"] = None if steps is None else _numbers(np.mean(steps, axis=0))
    if getattr(result, "final_channel_mse", None) is not None:
        for name in ("final_channel_mse", "final_channel_nmse"):
            record[f"{name}_mean"] = {c: _number(v) for c, v in zip(result.channels, getattr(result, name).mean(0))}
    for name in ("gain_norm", "spread"):
        values = getattr(result, name, None)
        if values is not None:
            record[f"per_step_{name}_mean"] = _numbers(np.mean(values, axis=1))
    ratio = getattr(result, "spread_skill", None)
    record["final_spread_skill"] = None if ratio is None else _number(ratio[-1])
    record["per_step_spread_skill"] = None if ratio is None else _numbers(ratio)
    for name in ("rank_histogram_sensors", "rank_histogram_cells"):
        if getattr(result, name, None) is not None:
            record[name] = [int(c) for c in getattr(result, name)]
    if getattr(result, "step_rel_l2", None) is not None:
        record.update(relative_fields(result.step_rel_l2, result.final_channel_rel_l2, result.channels))
    if cfg.filter.parameter != "known":  # absent: the filter was told the true mu
        record["parameter"] = cfg.filter.parameter if isinstance(cfg.filter.parameter, str) else "assumed"
    if getattr(result, "step_parameter", None) is not None:
        record["parameter_scores"] = parameter_summary(result.step_parameter)
    record.update(interval_fields(record))
    if keep_curves:
        record["per_trajectory_step_mse"] = _numbers(result.step_mse)
    return record


def relative_fields(step_rel_l2: np.ndarray, final_channel_rel_l2: np.ndarray,
                    channels: Iterable[str]) -> dict[str, Any]:
    """A record's relative L2 fields from the relative errors of its episodes at every frame (B, n_t) and of
    each scored channel (``channels``) at the final frame (B, n_scored)."""
    final = np.asarray(step_rel_l2, dtype=np.float64)[:, -1]
    return {"final_rel_l2_mean": _number(np.mean(final)),
            "final_rel_l2_std": _number(np.std(final, ddof=1)) if len(final) > 1 else None,
            "per_step_rel_l2_mean": _numbers(np.mean(step_rel_l2, axis=0)),
            "per_trajectory_final_rel_l2": _numbers(final),
            "final_score_mean": _number(np.mean(ctf_score(final))),
            "final_channel_rel_l2_mean": {c: _number(v) for c, v in zip(channels, np.mean(final_channel_rel_l2, 0))}}


def shared_dataset(identity: dict[str, Any]) -> dict[str, Any]:
    """A dataset identity fit to share and commit: the file's name, not its path (the fingerprint identifies
    the data)."""
    return {**identity, "path": Path(str(identity.get("path", ""))).name}


def new_results(benchmark: str, preset: str, dataset: dict[str, Any], config: dict[str, Any],
                records: Iterable[dict[str, Any]] = (), models: Iterable[dict[str, Any]] = ()) -> dict[str, Any]:
    """A results document (validated)."""
    doc = {
        "schema": SCHEMA, "schema_version": SCHEMA_VERSION,
        "benchmark": benchmark,
        "preset": preset,
        "dataset": shared_dataset(dataset),  # a results file is shared and committed
        "config": dict(config),
        "models": [{**m, "checkpoint": Path(str(m["checkpoint"])).name} if m.get("checkpoint") else dict(m)
                   for m in models],
        "records": list(records),
    }
    validate(doc)
    return doc


def record_key(record: dict[str, Any]) -> tuple:
    """The identity of a run: (experiment, model, filter, initial, noise, r, T, n_members, parameter)."""
    return tuple(record.get(k, KEY_DEFAULTS.get(k)) if k in KEY_DEFAULTS else record[k] for k in RECORD_KEY)


def run_key(record: dict[str, Any]) -> tuple:
    """The identity of a run regardless of the experiment that asked for it."""
    return record_key(record)[1:]


# Validation ---------------------------------------------------------------------------------------------
def validate_record(rec: Any, where: str = "record") -> None:
    """Raise :class:`ResultsError` naming what is missing or malformed in one record."""
    if not isinstance(rec, dict):
        raise ResultsError(f"{where} must be a JSON object, got {type(rec).__name__}")
    missing = [k for k in _REQUIRED_RECORD if k not in rec]
    if missing:
        raise ResultsError(f"{where} lacks {', '.join(missing)}")
    if not isinstance(rec["experiment"], str) or not rec["experiment"]:
        raise ResultsError(f"{where}: 'experiment' must be a non-empty string")
    for name, allowed in (("filter", RECORD_FILTERS), ("initial", INITIALS), ("parameter", PARAMETERS)):
        if rec.get(name, KEY_DEFAULTS.get(name)) not in allowed:
            raise ResultsError(f"{where}: {name!r} is {rec[name]!r}; expected one of {', '.join(allowed)}")
    if rec["model"] not in MODEL_KINDS and (rec["filter"] != "none" or not str(rec["model"] or "").strip()):
        raise ResultsError(f"{where}: 'model' {rec['model']!r} is none of {MODEL_KINDS} (any name: filter 'none')")
    if not is_number(rec["noise"], nullable=False) or rec["noise"] <= 0:
        raise ResultsError(f"{where}: 'noise' must be a positive number, got {rec['noise']!r}")
    for name in ("r", "T", "batch"):
        if not isinstance(rec[name], int) or isinstance(rec[name], bool) or rec[name] < 1:
            raise ResultsError(f"{where}: {name!r} must be a positive integer, got {rec[name]!r}")
    if rec["filter"] == "enkf":
        if not isinstance(rec["n_members"], int) or rec["n_members"] < 2:
            raise ResultsError(f"{where}: an EnKF record needs 'n_members' >= 2, got {rec['n_members']!r}")
    elif rec["n_members"] is not None:
        raise ResultsError(f"{where}: 'n_members' must be null for filter {rec['filter']!r}")
    for name in ("final_mse_mean", "final_mse_std", "da_step_seconds", "wall_time"):
        if not is_number(rec[name]):
            raise ResultsError(f"{where}: {name!r} must be a number or null, got {rec[name]!r}")
    batch = rec["batch"]
    check_list(rec, "per_trajectory_final_mse", where, batch)
    check_list(rec, "per_step_mse_mean", where, None)
    if len(rec["per_step_mse_mean"]) < 2:
        raise ResultsError(f"{where}: 'per_step_mse_mean' must have one entry per frame (at least 2)")
    if rec["max_forecast_norm"] is not None:
        check_list(rec, "max_forecast_norm", where, batch)
    elif rec["filter"] not in ("enkf", "none"):
        raise ResultsError(f"{where}: 'max_forecast_norm' may be null only for the EnKF (it uses no Jacobian) "
                           "and an estimator without a filter")
    curves = rec.get("per_trajectory_step_mse")
    if curves is not None:
        n_t = len(rec["per_step_mse_mean"])
        if (not isinstance(curves, list) or len(curves) != batch
                or not all(isinstance(c, list) and len(c) == n_t and all(is_number(v) for v in c) for c in curves)):
            raise ResultsError(f"{where}: 'per_trajectory_step_mse' must be {batch} lists of {n_t} numbers")
    check_optional_fields(rec, where)


def _validate_protocol(doc: dict[str, Any]) -> None:
    """The optional protocol block (a name, a positive version, a dict of deviations) and the records' marks."""
    block = doc.get("protocol")
    if block is not None:
        if not isinstance(block, dict) or not isinstance(block.get("name"), str) or not block["name"]:
            raise ResultsError(f"'protocol' must be an object with a non-empty 'name', got {block!r:.80}")
        version = block.get("version")
        if not isinstance(version, int) or isinstance(version, bool) or version < 1:
            raise ResultsError(f"'protocol' needs a positive integer 'version', got {version!r}")
        if not isinstance(block.get("deviations", {}), dict):
            raise ResultsError("'protocol.deviations' must map protocol fields to the run's values")
    for i, rec in enumerate(doc["records"]):
        marks = rec.get("protocol_deviations") if isinstance(rec, dict) else None
        if marks is not None and not (isinstance(marks, list) and all(isinstance(m, str) for m in marks)):
            raise ResultsError(f"records[{i}]: 'protocol_deviations' must be a list of field names, got {marks!r}")


def validate(doc: Any) -> dict[str, Any]:
    """Raise :class:`ResultsError` if ``doc`` is not a results document of this schema; return it."""
    if not isinstance(doc, dict):
        raise ResultsError(f"a results file holds a JSON object, got {type(doc).__name__}")
    missing = [k for k in _REQUIRED_TOP if k not in doc]
    if missing:
        raise ResultsError(f"results lack {', '.join(missing)}")
    if doc["schema"] != SCHEMA:
        raise ResultsError(f"'schema' is {doc['schema']!r}, not {SCHEMA!r}: this is not a dks-gym results file")
    if doc["schema_version"] != SCHEMA_VERSION:
        raise ResultsError(
            f"schema_version {doc['schema_version']!r} is not supported (this dks-gym reads {SCHEMA_VERSION}); "
            "upgrade dks-gym or rerun `dks-gym reproduce`"
        )
    for name in ("benchmark", "preset"):
        if not isinstance(doc[name], str) or not doc[name]:
            raise ResultsError(f"{name!r} must be a non-empty string")
    for name in ("dataset", "config"):
        if not isinstance(doc[name], dict):
            raise ResultsError(f"{name!r} must be a JSON object")
    if not isinstance(doc.get("models", []), list):
        raise ResultsError("'models' must be a list")
    if not isinstance(doc["records"], list):
        raise ResultsError("'records' must be a list")
    _validate_protocol(doc)
    seen: dict[tuple, int] = {}
    for i, rec in enumerate(doc["records"]):
        validate_record(rec, f"records[{i}]")
        key = record_key(rec)
        if key in seen:
            raise ResultsError(f"records[{i}] repeats records[{seen[key]}] (same {', '.join(RECORD_KEY)})")
        seen[key] = i
    return doc


# Files ---------------------------------------------------------------------------------------------------
def save_results(doc: ResultsDocument, path: str | Path) -> Path:
    """Validate and write ``doc`` to ``path`` atomically (temporary file in the same folder, then rename);
    gzip-compressed when the name ends in ``.gz`` (byte-reproducible: no time stamp or name in the header)."""
    validate(doc)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(doc, indent=1, allow_nan=False) + "\n"
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        if path.name.endswith(".gz"):
            with gzip.GzipFile(filename="", mode="wb", fileobj=f, compresslevel=9, mtime=0) as z:
                z.write(text.encode())
        else:
            f.write(text.encode())
    return path


def load_results(path: str | Path) -> ResultsDocument:
    """Read and validate a results file (plain JSON, or gzip-compressed JSON when the name ends in ``.gz``)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no results file at {path}; produce one with `dks-gym reproduce BENCHMARK --out DIR`")
    try:
        with (gzip.open(path, "rt") if path.name.endswith(".gz") else open(path)) as f:
            doc = json.load(f)
    except (json.JSONDecodeError, OSError, EOFError) as exc:
        raise ResultsError(f"{path} is not valid JSON ({exc})") from exc
    try:
        return validate(doc)
    except ResultsError as exc:
        raise ResultsError(f"{path}: {exc}") from exc


def select(doc: ResultsDocument, **criteria: Any) -> list[Record]:
    """The records whose fields equal ``criteria`` (e.g. ``experiment="main", filter="ekf"``); a key field a
    record leaves out has its default (:data:`KEY_DEFAULTS`), also as a criterion: a run with an estimated
    parameter is found only when ``parameter="estimate"`` is asked for."""
    criteria = {**KEY_DEFAULTS, **criteria}
    return [r for r in doc["records"] if all(r.get(k, KEY_DEFAULTS.get(k)) == v for k, v in criteria.items())]


def merge(old: dict[str, Any], new: dict[str, Any]) -> dict[str, Any]:
    """``new`` plus the records of ``old`` from experiments ``new`` did not run (same benchmark, preset, data)."""
    if (old["benchmark"], old["preset"]) != (new["benchmark"], new["preset"]):
        raise ResultsError(
            f"cannot merge results of {old['benchmark']}/{old['preset']} into {new['benchmark']}/{new['preset']}"
        )
    if old["dataset"].get("fingerprint") != new["dataset"].get("fingerprint"):
        raise ResultsError("cannot merge results computed on different datasets (fingerprints differ)")
    ran = {r["experiment"] for r in new["records"]}
    kept = [r for r in old["records"] if r["experiment"] not in ran]
    models = {(m.get("model"), m.get("r"), m.get("T")): m for m in old.get("models", []) + new.get("models", [])}
    out = dict(new, records=kept + new["records"], models=list(models.values()))
    return validate(out)


__all__ = [
    "RECORD_KEY",
    "RESULTS_FILE",
    "Record",
    "ResultsDocument",
    "SCHEMA",
    "SCHEMA_VERSION",
    "UNCERTAINTY_SCORES",
    "ResultsError",
    "load_results",
    "make_record",
    "merge",
    "new_results",
    "record_key",
    "relative_fields",
    "run_key",
    "save_results",
    "select",
    "validate",
    "validate_record",
]
