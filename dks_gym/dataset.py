"""The HDF5 dataset layer (SPEC section 1): write atomically, validate on load, read lazily.

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

Files are written to a temporary name next to the target, under a lock (kept in ``$DKS_GYM_HOME/.locks``,
see :mod:`dks_gym.locks`), and renamed into place only when complete, so a failed generation, Ctrl-C,
SIGTERM or SIGHUP never leaves a file that looks valid, nor a temporary one. Reading refuses a damaged
file or NaN/inf in a trajectory with :class:`DataError`, naming the file and what to do.
"""

from __future__ import annotations

import json
import os
import shutil
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from filelock import Timeout

from .atomic import atomic_path
from .benchmarks import BENCHMARKS, PRESETS, Benchmark, GeneratedData, check_preset, get_benchmark
from .home import dataset_path, ensure_writable
from .interrupt import exit_on_signals
from .locks import file_lock

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
_CHUNK_BYTES = 1 << 20  # h5py's guidance: chunks of 10 KiB to 1 MiB


class SchemaError(ValueError):
    """A file does not follow the dks-gym HDF5 schema; the message names the offending item."""


class DatasetMissing(FileNotFoundError):
    """No dataset file where one was expected; the message says how to create it."""


class DataError(SchemaError):
    """A file in the schema whose stored values cannot be used: a damaged block that HDF5 cannot read back,
    or NaN/inf in a trajectory. The message names the file, the split and trajectory, and what to do."""


# Writing ---------------------------------------------------------------------------------------------


class _ChannelStats:
    """Per-channel mean and variance merged trajectory by trajectory (Chan et al.), exact in float64."""

    def __init__(self, n_channels: int) -> None:
        self.count = 0
        self.mean = np.zeros(n_channels)
        self.m2 = np.zeros(n_channels)

    def add(self, fields: np.ndarray) -> None:
        x = np.moveaxis(np.asarray(fields, dtype=np.float64), 1, 0).reshape(fields.shape[1], -1)
        n = x.shape[1]
        mean = x.mean(axis=1)
        m2 = ((x - mean[:, None]) ** 2).sum(axis=1)
        delta = mean - self.mean
        total = self.count + n
        self.mean = self.mean + delta * n / total
        self.m2 = self.m2 + m2 + delta**2 * self.count * n / total
        self.count = total

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(self.m2 / max(self.count - 1, 1))


def _chunks(n_t: int, frame_shape: tuple[int, ...]) -> tuple[int, ...]:
    frame_bytes = 4 * int(np.prod(frame_shape))
    frames = int(max(1, min(n_t, _CHUNK_BYTES // max(frame_bytes, 1))))
    return (1, frames, *frame_shape)


def write_dataset(
    data: GeneratedData,
    benchmark: str | Benchmark,
    path: str | Path,
    *,
    extra_attrs: dict[str, Any] | None = None,
    lock_timeout: float = -1,
) -> Path:
    """Write ``data`` to ``path`` atomically (temporary file, then rename) under a file lock.

    ``lock_timeout`` is how long to wait for another writer of the same file (-1: wait forever). The lock
    file lives in ``$DKS_GYM_HOME/.locks`` (:func:`dks_gym.locks.file_lock`), not beside ``path``.
    """
    bench = get_benchmark(benchmark)
    path = Path(path)
    ensure_writable(path.parent)
    lock = file_lock(path, "write", timeout=lock_timeout)
    try:
        lock.acquire()
    except Timeout as exc:
        raise RuntimeError(
            f"another process is writing {path} (it holds the lock {lock.lock_file}); wait for it to finish "
            "or stop it (the lock is released when that process exits)"
        ) from exc
    try:
        # On errors, Ctrl-C, SIGTERM and SIGHUP alike the temporary file goes: nothing half-written survives.
        # The lazy generators (Burgers) do their solving here, while the trajectories are written.
        with atomic_path(path) as tmp:
            _write(data, bench, tmp, extra_attrs or {})
    finally:
        lock.release()
    return path


def _write(data: GeneratedData, bench: Benchmark, tmp: Path, extra_attrs: dict[str, Any]) -> None:
    n_t = len(data.time)
    n_c = len(bench.channels)
    frame_shape = (n_c, *bench.grid)
    stats = _ChannelStats(n_c)
    with h5py.File(tmp, "w") as f:
        f.attrs["benchmark"] = bench.name
        f.attrs["channels"] = list(bench.channels)
        f.attrs["observed_channel"] = bench.observed_channel
        f.attrs["scored_channels"] = list(bench.scored_channels)
        f.attrs["param_name"] = bench.param_name
        f.attrs["dt"] = float(bench.dt)
        f.attrs["generator"] = json.dumps(data.generator, sort_keys=True, default=_json_default)
        f.attrs["schema_version"] = SCHEMA_VERSION
        f.attrs["created"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
        for key, value in extra_attrs.items():
            f.attrs[key] = value
        f.create_dataset("time", data=np.asarray(data.time, dtype=np.float64))
        if data.cell_type is not None:
            f.create_dataset("cell_type", data=np.asarray(data.cell_type, dtype=np.int8))
        coords = f.create_group("coords")
        for axis, values in zip(AXES, data.coords):
            coords.create_dataset(axis, data=np.asarray(values, dtype=np.float64))
        written = {}
        for split in SPLITS:
            params = np.asarray(data.params[split], dtype=np.float64)
            g = f.create_group(split)
            g.create_dataset("params", data=params)
            g.create_dataset(
                "fields",
                shape=(len(params), n_t, *frame_shape),
                dtype=np.float32,
                chunks=_chunks(n_t, frame_shape),
                compression="gzip",
                compression_opts=1,
                shuffle=True,
            )
            written[split] = np.zeros(len(params), dtype=bool)
        for split, index, fields in data.trajectories:
            fields = np.asarray(fields, dtype=np.float32)
            if fields.shape != (n_t, *frame_shape):
                raise ValueError(
                    f"generator produced {split}[{index}] with shape {fields.shape}, expected {(n_t, *frame_shape)}"
                )
            if not np.all(np.isfinite(fields)):
                raise ValueError(f"generator produced non-finite values in {split}[{index}]")
            f[split]["fields"][index] = fields
            written[split][index] = True
            if split == "train":
                stats.add(fields)
        for split, done in written.items():
            if not done.all():
                raise ValueError(f"generator left {split} trajectories {np.flatnonzero(~done).tolist()} unwritten")
        for split, series in data.extras.items():
            if split not in SPLITS:
                raise ValueError(f"generator produced extras for unknown split {split!r}; expected {SPLITS}")
            group = f[split].create_group("extras")
            for name, values in series.items():
                values = np.asarray(values)
                if values.shape[:1] != (len(written[split]),):
                    raise ValueError(
                        f"generator produced extras {split}/{name} with shape {values.shape}; the first axis "
                        f"must be the {len(written[split])} trajectories of the split"
                    )
                group.create_dataset(name, data=values)
        stats_group = f.create_group("stats")
        stats_group.create_dataset("mean", data=stats.mean)
        stats_group.create_dataset("std", data=stats.std)


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot store {type(obj).__name__} in the generator metadata")


def generate_dataset(
    benchmark: str | Benchmark,
    preset: str = "paper",
    *,
    path: str | Path | None = None,
    seed: int = 0,
    overwrite: bool = False,
    progress: bool = True,
    keep_workdir: bool = False,
    **options: Any,
) -> Path:
    """Generate ``benchmark``'s dataset for ``preset`` unless it exists; return the file's path.

    Generators that cache work (the OpenFOAM runs of the CFD benchmarks) use ``<stem>.work`` next to the
    file. It is deleted after a successful write unless ``keep_workdir`` (or the generator option
    ``keep_cases``) is set, and kept after a failure or an interruption so that a rerun resumes from it.
    ``options`` go to the benchmark's generator (e.g. ``workers=2`` for the CFD benchmarks).

    Two processes generating the same file take turns (a lock in ``$DKS_GYM_HOME/.locks``); the second finds
    the file written and returns. SIGTERM and SIGHUP stop the generation like Ctrl-C: the generator's own
    cleanup runs (its solver subprocesses are stopped), no temporary file stays, the work folder is kept,
    and :class:`~dks_gym.interrupt.Terminated` (exit status 128 + signal number) is raised.
    """
    bench = get_benchmark(benchmark)
    check_preset(preset)
    path = Path(path) if path is not None else dataset_path(bench.name, preset)
    ensure_writable(path.parent)
    with exit_on_signals(), file_lock(path, "generate"):
        if path.exists() and not overwrite:
            return path
        workdir = path.with_name(f"{path.stem}.work")
        data = bench.generate(preset, seed=seed, workdir=workdir, progress=progress, **options)
        write_dataset(data, bench, path, extra_attrs={"preset": preset, "seed": seed})
        if not (keep_workdir or options.get("keep_cases")):
            shutil.rmtree(workdir, ignore_errors=True)
    return path


# Reading ---------------------------------------------------------------------------------------------


def _as_str_list(value: Any, name: str) -> list[str]:
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


def _as_str(value: Any) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


def validate(f: h5py.File) -> Benchmark:
    """Check an open file against the schema; return its benchmark or raise SchemaError naming the problem."""
    where = f.filename
    for name in REQUIRED_ATTRS:
        if name not in f.attrs:
            raise SchemaError(f"{where}: missing root attribute {name!r}")
    name = _as_str(f.attrs["benchmark"])
    if name not in BENCHMARKS:
        raise SchemaError(f"{where}: attribute 'benchmark' is {name!r}; expected one of {', '.join(BENCHMARKS)}")
    bench = BENCHMARKS[name]
    if int(f.attrs["schema_version"]) != SCHEMA_VERSION:
        raise SchemaError(
            f"{where}: schema_version {f.attrs['schema_version']} is not supported (this dks-gym reads {SCHEMA_VERSION})"
        )
    channels = _as_str_list(f.attrs["channels"], "channels")
    if channels != list(bench.channels):
        raise SchemaError(f"{where}: attribute 'channels' is {channels}; the {name} benchmark has {list(bench.channels)}")
    observed = _as_str(f.attrs["observed_channel"])
    if observed not in channels:
        raise SchemaError(f"{where}: attribute 'observed_channel' {observed!r} is not one of the channels {channels}")
    scored = _as_str_list(f.attrs["scored_channels"], "scored_channels")
    if not scored or any(c not in channels for c in scored):
        raise SchemaError(f"{where}: attribute 'scored_channels' {scored} must be a non-empty subset of {channels}")
    try:
        dt = float(f.attrs["dt"])
    except (TypeError, ValueError) as exc:
        raise SchemaError(f"{where}: attribute 'dt' must be a number, got {f.attrs['dt']!r}") from exc
    if not dt > 0:
        raise SchemaError(f"{where}: attribute 'dt' must be positive, got {dt}")
    try:
        json.loads(_as_str(f.attrs["generator"]))
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
            raise SchemaError(f"{where}: missing or malformed dataset 'stats/{item}' (expected shape ({len(channels)},))")
    if np.any(np.asarray(f["stats"]["std"]) <= 0):
        raise SchemaError(f"{where}: dataset 'stats/std' has non-positive entries")
    return bench


class Dataset:
    """A validated dks-gym HDF5 file, read lazily.

    The file handle is reopened after a fork, so a Dataset can be shared with subprocess vector envs.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise DatasetMissing(f"no dataset file at {self.path}")
        self._file: h5py.File | None = None
        self._pid = -1
        f = self._h5
        self.benchmark = validate(f)
        self.channels = tuple(_as_str_list(f.attrs["channels"], "channels"))
        self.observed_channel = _as_str(f.attrs["observed_channel"])
        self.scored_channels = tuple(_as_str_list(f.attrs["scored_channels"], "scored_channels"))
        self.param_name = _as_str(f.attrs["param_name"])
        self.dt = float(f.attrs["dt"])
        self.generator = json.loads(_as_str(f.attrs["generator"]))
        self.preset = _as_str(f.attrs["preset"]) if "preset" in f.attrs else None
        self.created = _as_str(f.attrs["created"])
        self.time = np.asarray(f["time"])
        self.cell_type = np.asarray(f["cell_type"], dtype=np.int8) if "cell_type" in f else None
        self.coords = tuple(np.asarray(f["coords"][a]) for a in AXES[: self.benchmark.ndim])
        self.stats_mean = np.asarray(f["stats"]["mean"], dtype=np.float64)
        self.stats_std = np.asarray(f["stats"]["std"], dtype=np.float64)
        # Small and fixed for the file's life: read once, not on every env step (an HDF5 read costs ~0.3 ms).
        self._params = {split: np.asarray(f[split]["params"], dtype=np.float64) for split in SPLITS if split in f}

    @property
    def _h5(self) -> h5py.File:
        if self._file is None or self._pid != os.getpid():
            try:
                self._file = h5py.File(self.path, "r")
            except OSError as exc:
                raise SchemaError(f"{self.path} is not a readable HDF5 file ({exc})") from exc
            self._pid = os.getpid()
        return self._file

    def _check_split(self, split: str) -> str:
        if split not in SPLITS:
            raise ValueError(f"unknown split {split!r}; choose 'train' or 'test'")
        return split

    @property
    def n_frames(self) -> int:
        return len(self.time)

    @property
    def grid(self) -> tuple[int, ...]:
        return self.benchmark.grid

    def fields(self, split: str) -> h5py.Dataset:
        """The lazy (n_traj, n_t, C, *grid) array of ``split``."""
        return self._h5[self._check_split(split)]["fields"]

    def params(self, split: str) -> np.ndarray:
        """Parameter value of every trajectory of ``split`` (a copy: callers may change it)."""
        split = self._check_split(split)
        if split not in self._params:
            self._params[split] = np.asarray(self._h5[split]["params"], dtype=np.float64)  # raises the usual error
        return self._params[split].copy()

    def extras(self, split: str) -> dict[str, np.ndarray]:
        """The generator's per-trajectory side series of ``split`` (e.g. lift, drag); empty if none."""
        group = self._h5[self._check_split(split)].get("extras")
        return {} if group is None else {name: np.asarray(group[name]) for name in group}

    def n_trajectories(self, split: str) -> int:
        return int(self.fields(split).shape[0])

    def trajectory(self, split: str, index: int) -> np.ndarray:
        """One whole trajectory (n_t, C, *grid), float32, physical units."""
        n = self.n_trajectories(split)
        if not 0 <= int(index) < n:
            raise IndexError(f"trajectory {index} is out of range for split {split!r} with {n} trajectories")
        return self.read(split, int(index))

    def frame(self, split: str, index: int, k: int) -> np.ndarray:
        """Frame ``k`` of one trajectory, (C, *grid)."""
        return self.read(split, int(index), int(k))

    def read(self, split: str, index: int, *selection: Any) -> np.ndarray:
        """``fields(split)[index, *selection]`` as float32; a block HDF5 cannot decode raises :class:`DataError`.

        A file whose header is intact but whose data is damaged (a truncated copy, a bad disk, bytes
        overwritten) fails only here, when the damaged block is read.
        """
        fields = self.fields(split)
        try:
            return np.asarray(fields[(int(index), *selection)], dtype=np.float32)
        except OSError as exc:
            raise DataError(
                f"{self.path} is damaged: trajectory {index} of split {split!r} cannot be read back ({exc}). "
                f"{self._regenerate_hint()}"
            ) from exc

    def check_finite(
        self, values: np.ndarray, split: str, index: int, channels: tuple[int, ...] | None = None
    ) -> None:
        """Raise :class:`DataError` if ``values`` (frames of trajectory ``index``: (n_t, C, *grid), or
        (n_t, *grid) of the one channel in ``channels``) hold NaN or inf, naming the channel and the frame."""
        if np.isfinite(values).all():  # the cheap common path: one pass, no copies kept
            return
        channels = tuple(range(len(self.channels))) if channels is None else tuple(channels)
        per_channel = values[:, None] if values.ndim == 1 + len(self.grid) else values
        for c, channel in enumerate(channels):
            bad = ~np.isfinite(per_channel[:, c].reshape(per_channel.shape[0], -1)).all(axis=1)
            if bad.any():
                frames = np.flatnonzero(bad)
                raise DataError(
                    f"{self.path}: split {split!r}, trajectory {index}, channel {self.channels[channel]!r} holds NaN "
                    f"or inf in {len(frames)} of {len(bad)} frames (first: frame {frames[0]}); the file is unusable "
                    f"as data. {self._regenerate_hint()} If another tool wrote it, check that writer: the "
                    "dks-gym writer refuses non-finite values."
                )

    def _regenerate_hint(self) -> str:
        name = self.benchmark.name
        if self.preset in PRESETS and self.benchmark.generator_available:
            default = dataset_path(name, self.preset)
            out = "" if self.path.resolve() == default.resolve() else f" --out {self.path}"
            return (f"Regenerate it with `dks-gym data generate {name} --preset {self.preset}{out} --overwrite` "
                    "or delete it.")
        return "Regenerate it with the tool that wrote it, or delete it."

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> "Dataset":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_file"], state["_pid"] = None, -1
        return state

    def summary(self) -> str:
        """A human-readable description of the file."""
        lines = [
            f"file:        {self.path}",
            f"benchmark:   {self.benchmark.name} (preset {self.preset or 'unknown'})",
            f"grid:        {' x '.join(map(str, self.grid))}",
            f"channels:    {', '.join(self.channels)} (observed {self.observed_channel}; "
            f"scored {', '.join(self.scored_channels)})",
            f"frames:      {self.n_frames}, dt = {self.dt:g}, t = {self.time[0]:g} .. {self.time[-1]:g}",
        ]
        for split in SPLITS:
            p = self.params(split)
            lines.append(
                f"{split + ':':<12} {len(p)} trajectories, {self.param_name} in [{p.min():.4g}, {p.max():.4g}]"
            )
        for c, m, s in zip(self.channels, self.stats_mean, self.stats_std):
            lines.append(f"stats {c:<8} mean {m: .4e}  std {s:.4e}")
        lines.append(f"generator:   {json.dumps(self.generator, sort_keys=True)}")
        return "\n".join(lines)


def load_dataset(benchmark: str, preset: str = "paper", path: str | Path | None = None) -> Dataset:
    """Open a benchmark's dataset from the data home (or ``path``), with a clear error if it is missing."""
    bench = get_benchmark(benchmark)
    check_preset(preset)
    path = Path(path) if path is not None else dataset_path(bench.name, preset)
    if not path.exists():
        raise DatasetMissing(missing_message(bench, preset, path))
    ds = Dataset(path)
    if ds.benchmark.name != bench.name:
        raise SchemaError(f"{path} holds the {ds.benchmark.name} benchmark, not {bench.name}")
    return ds


def missing_message(bench: Benchmark, preset: str, path: Path) -> str:
    """What to tell a user whose dataset file is missing."""
    if bench.generator_available:

        def command(name: str) -> str:
            cost = bench.generation_costs.get(name)
            return f"`dks-gym data generate {bench.name} --preset {name}`" + (f" ({cost.describe()})" if cost else "")

        others = [p for p in PRESETS if p != preset]
        lead = "try the benchmark first with the small preset" if preset != "small" else "the paper's data"
        return (
            f"no {bench.name} {preset} dataset at {path}. Generate it with {command(preset)}; "
            f"{lead}: " + "; ".join(command(p) for p in others) + ". Or pass data_path= to use a file in the "
            "dks-gym HDF5 schema."
        )
    return (
        f"no {bench.name} dataset at {path}, and the {bench.name} data generator is not part of this version of "
        f"dks-gym yet. Once it is, `dks-gym data generate {bench.name} --preset {preset}` will create it; until then "
        "pass data_path= with a file in the dks-gym HDF5 schema (see `dks-gym data info`)."
    )
