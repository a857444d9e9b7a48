"""The dks-gym HDF5 schema: its layout, its errors, and the check of an open file against it.

Layout of one file (one benchmark, one preset)::

    /train/fields   float32 (n_traj, n_t, C, *grid)   physical units, chunked by trajectory, gzip
    /train/params   float64 (n_traj,)
    /train/extras/NAME  optional per-trajectory series (n_traj, ...), e.g. lift and drag
    /test/...       the same
    /time           (n_t,)
    /cell_type      int8 (*grid)        absent for burgers
    /coords/x, /coords/y[, /coords/z]   cell-centre coordinates, one array per axis
    /stats/mean, /stats/std             float64 (C,), train split, over trajectories, frames and cells
    attrs: benchmark, channels, observed_channel, scored_channels, param_name, dt, generator (JSON),
           schema_version, created
           optional: param_range [low, high], cell_type_codes (JSON {name: code}), solid_codes [code, ...]

A ``benchmark`` attribute naming one of the four paper benchmarks binds the file to that benchmark's grid
and channels. Any other name (lower-case letters, digits, underscores) makes it a custom benchmark: the
file describes it, its grid (1 to 3 axes, any size) taken from ``train/fields``, and the optional
attributes say what the fields cannot (:func:`custom_benchmark`).
"""

from __future__ import annotations

import json
from typing import Any

import h5py
import numpy as np

from ..benchmarks import BENCHMARKS, Benchmark, CustomBenchmark
from ..benchmarks.custom import MAX_DIMENSIONS

SCHEMA_VERSION = 1
SPLITS = ("train", "test")
AXES = ("x", "y", "z")
REQUIRED_ATTRS = (
    "benchmark",
    "channels",
    "observed_channel",
    "scored_channels",
    "param_name",
    "dt",
    "generator",
    "schema_version",
    "created",
)


class SchemaError(ValueError):
    """A file does not follow the dks-gym HDF5 schema; the message names the offending item."""


class DatasetMissing(FileNotFoundError):
    """No dataset file where one was expected; the message says how to create it."""


class DataError(SchemaError):
    """A file in the schema whose stored values cannot be used: a damaged block that HDF5 cannot read back,
    or NaN/inf in a trajectory. The message names the file, the split and trajectory, and what to do."""


def as_str_list(value: Any, name: str) -> list[str]:
    """A list-of-strings attribute (stored as a list or as its JSON text) as a list of ``str``."""
    if isinstance(value, (str, bytes)):
        text = value.decode() if isinstance(value, bytes) else value
        try:
            value = json.loads(text)
        except json.JSONDecodeError:
            value = [text]
    try:
        return [v.decode() if isinstance(v, bytes) else str(v) for v in value]
    except TypeError as exc:
        raise SchemaError(f"attribute {name!r} must be a list of strings, got {value!r}") from exc


def as_str(value: Any) -> str:
    """A string attribute (``bytes`` or ``str``) as ``str``."""
    return value.decode() if isinstance(value, bytes) else str(value)


def validate(f: h5py.File) -> Benchmark:
    """Check an open file against the schema; return its benchmark or raise SchemaError naming the problem.

    A file whose ``benchmark`` attribute names one of the four paper benchmarks must match that benchmark's
    grid and channels; any other name is a custom benchmark (:func:`custom_benchmark`), described by the file.
    """
    where = f.filename
    for name in REQUIRED_ATTRS:
        if name not in f.attrs:
            raise SchemaError(f"{where}: missing root attribute {name!r}")
    if int(f.attrs["schema_version"]) != SCHEMA_VERSION:
        raise SchemaError(
            f"{where}: schema_version {f.attrs['schema_version']} is not supported "
            f"(this dks-gym reads {SCHEMA_VERSION})"
        )
    _check_layout(f)
    name = as_str(f.attrs["benchmark"])
    bench = BENCHMARKS[name] if name in BENCHMARKS else custom_benchmark(f)
    channels = as_str_list(f.attrs["channels"], "channels")
    if channels != list(bench.channels):
        raise SchemaError(f"{where}: attribute 'channels' is {channels}; "
                          f"the {name} benchmark has {list(bench.channels)}")
    _check_attrs(f, channels)
    n_t = f["time"].shape[0]
    expected_frame = (len(channels), *bench.grid)
    for split in SPLITS:
        fields, params = f[split]["fields"], f[split]["params"]
        if fields.ndim != 2 + len(expected_frame) or fields.shape[1:] != (n_t, *expected_frame):
            raise SchemaError(
                f"{where}: dataset '{split}/fields' has shape {fields.shape}; expected (n_traj, {n_t}, "
                f"{', '.join(map(str, expected_frame))}) for {name}"
            )
        if not np.issubdtype(fields.dtype, np.floating):
            raise SchemaError(f"{where}: dataset '{split}/fields' has dtype {fields.dtype}; expected float32")
        if params.shape != (fields.shape[0],) or not np.issubdtype(params.dtype, np.floating):
            raise SchemaError(
                f"{where}: dataset '{split}/params' has shape {params.shape} and dtype {params.dtype}; "
                f"expected float64 ({fields.shape[0]},), one value per trajectory"
            )
    _check_geometry(f, bench, len(channels))
    return bench


def _check_layout(f: h5py.File) -> None:
    """The groups and datasets every file has, whatever its benchmark (their shapes are checked later)."""
    where = f.filename
    if "time" not in f or f["time"].ndim != 1:
        raise SchemaError(f"{where}: missing or malformed dataset 'time' (expected shape (n_t,))")
    for split in SPLITS:
        if split not in f or not isinstance(f[split], h5py.Group):
            raise SchemaError(f"{where}: missing group {split!r}")
        for item in ("fields", "params"):
            if item not in f[split]:
                raise SchemaError(f"{where}: missing dataset '{split}/{item}'")


def _check_attrs(f: h5py.File, channels: list[str]) -> None:
    """The channel, dt and generator attributes."""
    where = f.filename
    observed = as_str(f.attrs["observed_channel"])
    if observed not in channels:
        raise SchemaError(f"{where}: attribute 'observed_channel' {observed!r} is not one of the channels {channels}")
    scored = as_str_list(f.attrs["scored_channels"], "scored_channels")
    if not scored or any(c not in channels for c in scored):
        raise SchemaError(f"{where}: attribute 'scored_channels' {scored} must be a non-empty subset of {channels}")
    dt = _number(f, "dt")
    if not dt > 0:
        raise SchemaError(f"{where}: attribute 'dt' must be positive, got {dt}")
    try:
        json.loads(as_str(f.attrs["generator"]))
    except json.JSONDecodeError as exc:
        raise SchemaError(f"{where}: attribute 'generator' is not valid JSON ({exc})") from exc


def _number(f: h5py.File, name: str) -> float:
    try:
        return float(f.attrs[name])
    except (TypeError, ValueError) as exc:
        raise SchemaError(f"{f.filename}: attribute {name!r} must be a number, got {f.attrs[name]!r}") from exc


def _check_geometry(f: h5py.File, bench: Benchmark, n_channels: int) -> None:
    """The cell type (where the benchmark has one), the coordinates and the statistics."""
    where, name = f.filename, bench.name
    if bench.cell_type_codes:
        if "cell_type" not in f:
            raise SchemaError(f"{where}: missing dataset 'cell_type' (required for {name})")
        ct = f["cell_type"]
        if ct.shape != bench.grid or not np.issubdtype(ct.dtype, np.integer):
            raise SchemaError(
                f"{where}: dataset 'cell_type' has shape {ct.shape} and dtype {ct.dtype}; expected int8 {bench.grid}"
            )
    if "coords" not in f:
        raise SchemaError(f"{where}: missing group 'coords'")
    for axis, n in zip(AXES, bench.grid):
        if axis not in f["coords"] or f["coords"][axis].shape != (n,):
            raise SchemaError(f"{where}: missing or malformed dataset 'coords/{axis}' (expected shape ({n},))")
    for item in ("mean", "std"):
        if "stats" not in f or item not in f["stats"] or f["stats"][item].shape != (n_channels,):
            raise SchemaError(f"{where}: missing or malformed dataset 'stats/{item}' "
                              f"(expected shape ({n_channels},))")
    if np.any(np.asarray(f["stats"]["std"]) <= 0):
        raise SchemaError(f"{where}: dataset 'stats/std' has non-positive entries")


def custom_benchmark(f: h5py.File) -> CustomBenchmark:
    """The :class:`~dks_gym.benchmarks.CustomBenchmark` an open file describes (its ``benchmark`` attribute names
    none of the four): the grid and the number of channels from ``train/fields``, the channel names, dt and
    the parameter's name from the attributes, the parameter range from the optional attribute ``param_range``
    (else the smallest and largest parameter of the file), the cell types from the optional dataset
    ``cell_type`` with the optional attributes ``cell_type_codes`` (JSON ``{name: code}``; default: each code
    named by its value) and ``solid_codes`` (default: none), and the coordinates from ``coords``."""
    where = f.filename
    fields = f["train"]["fields"]
    if not 4 <= fields.ndim <= 3 + MAX_DIMENSIONS:
        raise SchemaError(f"{where}: dataset 'train/fields' has shape {fields.shape}; expected (n_traj, n_t, C, "
                          f"*grid) with a grid of 1 to {MAX_DIMENSIONS} axes")
    grid = tuple(int(n) for n in fields.shape[3:])
    if "param_range" in f.attrs:
        param_range = tuple(float(v) for v in np.asarray(f.attrs["param_range"], dtype=np.float64).reshape(-1))
    else:
        params = np.concatenate([np.asarray(f[split]["params"], dtype=np.float64).reshape(-1) for split in SPLITS])
        if params.size == 0 or not params.max() > params.min():
            raise SchemaError(f"{where}: the trajectories' parameters span no range ({params.tolist()[:3]}...); "
                              "add the attribute 'param_range' = [low, high] that the parameter is meant to cover")
        param_range = (float(params.min()), float(params.max()))
    cell_types = np.asarray(f["cell_type"]) if "cell_type" in f else None
    codes = {}
    if cell_types is not None:
        codes = ({as_str(k): int(v) for k, v in json.loads(as_str(f.attrs["cell_type_codes"])).items()}
                 if "cell_type_codes" in f.attrs else {str(v): int(v) for v in np.unique(cell_types)})
    coords = f.get("coords")
    coordinates = None
    if coords is not None and all(a in coords and coords[a].shape == (n,) for a, n in zip(AXES, grid)):
        coordinates = tuple(np.asarray(coords[a], dtype=np.float64) for a in AXES[: len(grid)])
    try:
        return CustomBenchmark(
            name=as_str(f.attrs["benchmark"]), grid=grid, channels=tuple(as_str_list(f.attrs["channels"], "channels")),
            observed_channel=as_str(f.attrs["observed_channel"]),
            scored_channels=tuple(as_str_list(f.attrs["scored_channels"], "scored_channels")),
            param_name=as_str(f.attrs["param_name"]), param_range=param_range, dt=_number(f, "dt"),
            n_frames=int(f["time"].shape[0]), n_train=int(fields.shape[0]),
            n_test=int(f["test"]["fields"].shape[0]), coordinates=coordinates, cell_types=cell_types,
            cell_type_codes=codes, solid_codes=tuple(int(c) for c in np.asarray(f.attrs.get("solid_codes", []))),
        )
    except (ValueError, TypeError) as exc:
        raise SchemaError(f"{where}: {exc}") from exc
