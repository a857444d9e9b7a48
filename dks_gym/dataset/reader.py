"""Reading a dataset file: validated on opening, read lazily, refusing damaged blocks and NaN/inf.

Reading refuses a damaged file or NaN/inf in a trajectory with :class:`~dks_gym.dataset.schema.DataError`,
naming the file and what to do.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from ..benchmarks import PRESETS, Benchmark, check_preset, get_benchmark
from ..home import dataset_path
from .schema import AXES, SPLITS, DataError, DatasetMissing, SchemaError, as_str, as_str_list, validate


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
        self.channels = tuple(as_str_list(f.attrs["channels"], "channels"))
        self.observed_channel = as_str(f.attrs["observed_channel"])
        self.scored_channels = tuple(as_str_list(f.attrs["scored_channels"], "scored_channels"))
        self.param_name = as_str(f.attrs["param_name"])
        self.dt = float(f.attrs["dt"])
        self.generator = json.loads(as_str(f.attrs["generator"]))
        self.preset = as_str(f.attrs["preset"]) if "preset" in f.attrs else None
        self.created = as_str(f.attrs["created"])
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


def load_dataset(benchmark: str | Benchmark | None, preset: str = "paper", path: str | Path | None = None) -> Dataset:
    """Open a benchmark's dataset from the data home (or ``path``), with a clear error if it is missing.

    ``benchmark`` None takes whatever benchmark the file at ``path`` describes (a custom one included); a
    benchmark (name or object) must be the file's."""
    if benchmark is None:
        if path is None:
            raise ValueError("without a benchmark, name the file: data_path=... (a file in the dks-gym HDF5 schema)")
        if not Path(path).exists():
            raise DatasetMissing(f"no dataset file at {path}; write one in the dks-gym HDF5 schema (docs/envs.md, "
                                 "\"Your own flow\")")
        return Dataset(path)
    bench = get_benchmark(benchmark)
    check_preset(preset)
    path = Path(path) if path is not None else dataset_path(bench.name, preset)
    if not path.exists():
        raise DatasetMissing(missing_message(bench, preset, path))
    ds = Dataset(path)
    if ds.benchmark.name != bench.name:
        raise SchemaError(f"{path} holds the {ds.benchmark.name} benchmark, not {bench.name}")
    return ds


def load_benchmark(path: str | Path) -> Benchmark:
    """The benchmark a schema file describes: one of the four paper benchmarks, or the
    :class:`~dks_gym.benchmarks.CustomBenchmark` of your own flow (grid, channels, dt, parameter, cell types
    and the default sensor layout, all from the file), validated like any dataset."""
    if not Path(path).exists():
        raise DatasetMissing(f"no dataset file at {path}")
    with Dataset(path) as ds:
        return ds.benchmark


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
