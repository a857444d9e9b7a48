"""What the importers of other collections' files share: their error, the time-step check, the benchmark the
imported flow becomes, and the one write into the dks-gym schema.

An importer (:mod:`.the_well`, :mod:`.pdebench`) checks every file it is given before anything is written,
then hands an :class:`ImportedFlow` (trajectories read lazily, one at a time) to :func:`write_imported`,
which writes it with :func:`~dks_gym.dataset.writer.write_dataset`: a temporary file renamed into place when
complete, so an error, Ctrl-C, SIGTERM or SIGHUP halfway leaves no file behind. The train split's channel
statistics are computed there, as for a generated dataset.

The flow becomes one of the four paper benchmarks when its name is one of theirs (the round trip of the
project's own data: its grid, channels, dt and cell types must then be the benchmark's, the channels are put
in the benchmark's order), and otherwise a custom benchmark described by the file (any grid, the imported
channels, dt from the time axis, the parameter range of its trajectories).
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from ..benchmarks import BENCHMARKS, Benchmark, CustomBenchmark, GeneratedData
from .writer import write_dataset

#: How far apart the steps of a time axis may be, relative to the mean step (float32 times of the source
#: collections round to ~1e-7 of their magnitude; a genuinely uneven sampling differs by far more).
STEP_TOLERANCE = 1e-3


class LayoutError(ValueError):
    """A file breaks the layout its importer reads; the message names the file and what is missing or wrong."""


@dataclass
class ImportedFlow:
    """What an importer read, before it is written: the description and the trajectories (read lazily).

    ``trajectories`` yields ``(split, index, fields)`` with ``fields`` of shape ``(n_t, C, *grid)`` in the
    order of ``channels``, each ``(split, index)`` of ``params`` once. ``cell_type`` (int codes on the grid,
    named by ``cell_type_codes``) is None where the source has none. ``generator`` records where the data
    came from (the files, the choices made) in the written file's ``generator`` attribute.
    """

    name: str
    channels: tuple[str, ...]
    param_name: str
    time: np.ndarray
    coords: tuple[np.ndarray, ...]
    params: dict[str, np.ndarray]
    trajectories: Iterator[tuple[str, int, np.ndarray]]
    generator: dict[str, Any]
    cell_type: np.ndarray | None = None
    cell_type_codes: dict[str, int] = field(default_factory=dict)
    solid_codes: tuple[int, ...] = ()

    @property
    def grid(self) -> tuple[int, ...]:
        return tuple(len(c) for c in self.coords)

    @property
    def dt(self) -> float:
        return uniform_step(self.time, "the imported time axis")


def open_source(path: Path) -> h5py.File:
    """A source file of an importer, open for reading; a LayoutError naming it where HDF5 cannot read it."""
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise LayoutError(f"{path} is not a readable HDF5 file ({exc})") from exc


def uniform_step(time: np.ndarray, where: str) -> float:
    """The step of an evenly spaced, increasing time axis; a LayoutError naming ``where`` otherwise."""
    t = np.asarray(time, dtype=np.float64).reshape(-1)
    if t.size < 2:
        raise LayoutError(f"{where}: the time axis has {t.size} entries; at least 2 frames are needed")
    steps = np.diff(t)
    dt = float((t[-1] - t[0]) / (t.size - 1))
    if not np.all(np.isfinite(t)) or not dt > 0 or np.any(steps <= 0):
        raise LayoutError(f"{where}: the times must be finite and increasing, got {t[:4].tolist()}...")
    worst = int(np.argmax(np.abs(steps - dt)))
    if abs(steps[worst] - dt) > STEP_TOLERANCE * dt:
        raise LayoutError(
            f"{where}: the frames are not evenly spaced in time (step {worst} is {steps[worst]:.6g}, the mean step "
            f"{dt:.6g}); the dks-gym schema has one time step dt. Resample the data to a constant step first."
        )
    return dt


def benchmark_name(text: str) -> str:
    """A benchmark name from a collection's dataset name: lower case, runs of other characters as ``_``
    (it names checkpoint files), starting with a letter."""
    name = re.sub(r"[^a-z0-9_]+", "_", str(text).lower()).strip("_")
    if not name:
        raise ValueError(f"cannot make a benchmark name of {text!r}; give one (name=...)")
    return name if name[0].isalpha() else f"flow_{name}"


def target_benchmark(flow: ImportedFlow, observed: str | None = None) -> tuple[Benchmark, list[int]]:
    """The benchmark ``flow`` is written as, and the order of its channels in that benchmark's.

    A paper benchmark's name binds the flow to that benchmark (grid, channels, dt and cell types checked);
    any other name makes a custom benchmark: the flow's channels in their order, ``observed`` (default the
    first channel) observed, every channel scored, dt from the time axis, the parameter range spanned by the
    trajectories (:func:`parameter_range`)."""
    if flow.name in BENCHMARKS:
        return _paper_benchmark(flow, BENCHMARKS[flow.name], observed)
    channels = tuple(flow.channels)
    observed = channels[0] if observed is None else observed
    if observed not in channels:
        raise ValueError(f"the observed channel {observed!r} is not one of the imported channels {list(channels)}")
    # A CustomBenchmark checks the name, the grid and the cell-type codes here, before anything is written.
    bench = CustomBenchmark(
        name=flow.name, grid=flow.grid, channels=channels, observed_channel=observed,
        scored_channels=channels, param_name=flow.param_name, param_range=parameter_range(flow.params),
        dt=flow.dt, n_frames=len(flow.time),
        n_train=len(flow.params["train"]), n_test=len(flow.params["test"]),
        cell_type_codes=dict(flow.cell_type_codes), solid_codes=tuple(flow.solid_codes),
        coordinates=tuple(flow.coords), cell_types=flow.cell_type,
    )
    return bench, list(range(len(channels)))


def parameter_range(params: dict[str, np.ndarray]) -> tuple[float, float]:
    """The range the trajectories' parameters span; around a single value v, v -+ |v| / 2 (-+ 1/2 for 0).

    A flow whose trajectories all share one value (one PDEBench file, one file of The Well) still needs
    low < high: the models map the range onto [-1, 1]. The parameter then carries no information, and the
    range only keeps that map defined (positive for a positive value, so a logarithmic scale stays valid)."""
    values = np.concatenate([np.asarray(v, dtype=np.float64).reshape(-1) for v in params.values()])
    low, high = float(values.min()), float(values.max())
    if high > low:
        return low, high
    half = abs(low) / 2 if low != 0 else 0.5
    return low - half, low + half


def _paper_benchmark(flow: ImportedFlow, bench: Benchmark, observed: str | None) -> tuple[Benchmark, list[int]]:
    hint = "; give the import another name (name=...) to make it a custom benchmark"
    if sorted(flow.channels) != sorted(bench.channels):
        raise ValueError(f"the files are named {bench.name!r}, but their channels {list(flow.channels)} are not the "
                         f"{bench.name} benchmark's {list(bench.channels)}{hint}")
    if flow.grid != bench.grid:
        raise ValueError(f"the files are named {bench.name!r}, but their grid {flow.grid} is not the {bench.name} "
                         f"benchmark's {bench.grid}{hint}")
    if abs(flow.dt - bench.dt) > STEP_TOLERANCE * bench.dt:
        raise ValueError(f"the files are named {bench.name!r}, but their time step {flow.dt:.6g} is not the "
                         f"{bench.name} benchmark's {bench.dt:g}{hint}")
    if bench.cell_type_codes and (flow.cell_type is None or flow.cell_type_codes != bench.cell_type_codes):
        raise ValueError(f"the {bench.name} benchmark needs its cell types (codes {bench.cell_type_codes}); the files "
                         f"carry {flow.cell_type_codes or 'none'} (export_the_well writes them as a constant t0 "
                         "field with the attribute 'dks_gym_cell_type_codes')")
    if observed is not None and observed != bench.observed_channel:
        raise ValueError(f"the {bench.name} benchmark observes {bench.observed_channel!r}, not {observed!r}")
    return bench, [flow.channels.index(c) for c in bench.channels]


def write_imported(flow: ImportedFlow, out: str | Path, *, observed: str | None = None,
                   overwrite: bool = False) -> Path:
    """Write ``flow`` to the schema file ``out`` (atomically, the train statistics computed on the way)."""
    out = Path(out)
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} exists; choose another output file or pass overwrite=True (--overwrite)")
    for split in ("train", "test"):
        if len(flow.params.get(split, ())) == 0:
            raise LayoutError(f"the import has no {split} trajectories; the dks-gym schema needs both splits")
    bench, order = target_benchmark(flow, observed)
    identity = order == list(range(len(order)))
    trajectories = (flow.trajectories if identity
                    else ((split, i, fields[:, order]) for split, i, fields in flow.trajectories))
    data = GeneratedData(time=np.asarray(flow.time, dtype=np.float64), params=flow.params, trajectories=trajectories,
                         generator=flow.generator, coords=flow.coords, cell_type=flow.cell_type)
    return write_dataset(data, bench, out)


def check_finite(fields: np.ndarray, where: str) -> np.ndarray:
    """``fields`` unchanged, or a LayoutError naming ``where`` and the first frame holding NaN or inf."""
    if not np.isfinite(fields).all():
        bad = np.flatnonzero(~np.isfinite(fields.reshape(fields.shape[0], -1)).all(axis=1))
        raise LayoutError(f"{where} holds NaN or inf (first in frame {bad[0]}); the dks-gym schema stores finite "
                          "values only")
    return fields
