"""Writing a dataset file: atomically, under a lock, with the train split's statistics; and generating one.

Files are written to a temporary name next to the target, under a lock (kept in ``$DKS_GYM_HOME/.locks``,
see :mod:`dks_gym.locks`), and renamed into place only when complete, so a failed generation, Ctrl-C,
SIGTERM or SIGHUP never leaves a file that looks valid, nor a temporary one.
"""

from __future__ import annotations

import json
import shutil
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from filelock import Timeout

from ..atomic import atomic_path
from ..benchmarks import Benchmark, GeneratedData, check_preset, get_benchmark
from ..home import dataset_path, ensure_writable
from ..interrupt import exit_on_signals
from ..locks import file_lock
from .schema import AXES, SCHEMA_VERSION, SPLITS

_CHUNK_BYTES = 1 << 20  # h5py's guidance: chunks of 10 KiB to 1 MiB


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
        # What a custom benchmark's file must say beyond its fields (schema.custom_benchmark reads them back).
        f.attrs["param_range"] = np.asarray(bench.param_range, dtype=np.float64)
        if bench.cell_type_codes:
            f.attrs["cell_type_codes"] = json.dumps(bench.cell_type_codes, sort_keys=True)
            f.attrs["solid_codes"] = np.asarray(bench.solid_codes, dtype=np.int64)
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
