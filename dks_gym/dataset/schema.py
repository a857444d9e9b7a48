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
"""

from __future__ import annotations

import json
from typing import Any

import h5py
import numpy as np

from ..benchmarks import BENCHMARKS, Benchmark

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
    """Check an open file against the schema; return its benchmark or raise SchemaError naming the problem."""
    where = f.filename
    for name in REQUIRED_ATTRS:
        if name not in f.attrs:
            raise SchemaError(f"{where}: missing root attribute {name!r}")
    name = as_str(f.attrs["benchmark"])
    if name not in BENCHMARKS:
        raise SchemaError(f"{where}: attribute 'benchmark' is {name!r}; expected one of {', '.join(BENCHMARKS)}")
    bench = BENCHMARKS[name]
    if int(f.attrs["schema_version"]) != SCHEMA_VERSION:
        raise SchemaError(
            f"{where}: schema_version {f.attrs['schema_version']} is not supported "
            f"(this dks-gym reads {SCHEMA_VERSION})"
        )
    channels = as_str_list(f.attrs["channels"], "channels")
    if channels != list(bench.channels):
        raise SchemaError(f"{where}: attribute 'channels' is {channels}; "
                          f"the {name} benchmark has {list(bench.channels)}")
    observed = as_str(f.attrs["observed_channel"])
    if observed not in channels:
        raise SchemaError(f"{where}: attribute 'observed_channel' {observed!r} is not one of the channels {channels}")
    scored = as_str_list(f.attrs["scored_channels"], "scored_channels")
    if not scored or any(c not in channels for c in scored):
        raise SchemaError(f"{where}: attribute 'scored_channels' {scored} must be a non-empty subset of {channels}")
    try:
        dt = float(f.attrs["dt"])
    except (TypeError, ValueError) as exc:
        raise SchemaError(f"{where}: attribute 'dt' must be a number, got {f.attrs['dt']!r}") from exc
    if not dt > 0:
        raise SchemaError(f"{where}: attribute 'dt' must be positive, got {dt}")
    try:
        json.loads(as_str(f.attrs["generator"]))
    except json.JSONDecodeError as exc:
        raise SchemaError(f"{where}: attribute 'generator' is not valid JSON ({exc})") from exc

    if "time" not in f or f["time"].ndim != 1:
        raise SchemaError(f"{where}: missing or malformed dataset 'time' (expected shape (n_t,))")
    n_t = f["time"].shape[0]
    expected_frame = (len(channels), *bench.grid)
    for split in SPLITS:
        if split not in f or not isinstance(f[split], h5py.Group):
            raise SchemaError(f"{where}: missing group {split!r}")
        for item in ("fields", "params"):
            if item not in f[split]:
                raise SchemaError(f"{where}: missing dataset '{split}/{item}'")
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
        if "stats" not in f or item not in f["stats"] or f["stats"][item].shape != (len(channels),):
            raise SchemaError(f"{where}: missing or malformed dataset 'stats/{item}' "
                              f"(expected shape ({len(channels)},))")
    if np.any(np.asarray(f["stats"]["std"]) <= 0):
        raise SchemaError(f"{where}: dataset 'stats/std' has non-positive entries")
    return bench
