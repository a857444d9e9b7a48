"""What every benchmark is: a fixed grid, named channels, a parameter range and a data generator.

A benchmark module (``burgers.py``, ``cylinder.py`` ...) defines one :class:`Benchmark` subclass holding
the numbers of SPEC section 1, the geometry (coordinates, cell types) and the paper's sensor layout
(SPEC section 2), and names its data generator by entry point (``"module:function"``). Benchmarks never
touch HDF5: the dataset layer (:mod:`dks_gym.dataset`) consumes what :meth:`Benchmark.generate` yields
and stores it.

The generators of the CFD benchmarks live in :mod:`dks_gym.solvers`, which imports the benchmarks for
their geometry; naming them by string (as Gymnasium names env classes) keeps the benchmarks from
importing the solvers back, and keeps OpenFOAM's and the lattice Boltzmann solver's imports out of
``import dks_gym.benchmarks``.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

PRESETS = ("paper", "small")


class GeneratorUnavailable(RuntimeError):
    """Raised when a benchmark's data generator is not part of this version of dks-gym."""


@dataclass
class GeneratedData:
    """What a generator hands to the dataset layer.

    ``trajectories`` yields ``(split, index, fields)`` with ``fields`` of shape ``(n_t, C, *grid)`` in
    physical units, in any order, each ``(split, index)`` exactly once. It is an iterator so that large
    benchmarks (the sphere is 42 GB) never sit in memory whole.
    """

    time: np.ndarray
    params: dict[str, np.ndarray]
    trajectories: Iterator[tuple[str, int, np.ndarray]]
    generator: dict[str, Any]
    coords: tuple[np.ndarray, ...]
    cell_type: np.ndarray | None = None
    # Per-trajectory side series (lift, drag, water volume...): {split: {name: (n_traj, ...) array}};
    # stored under /{split}/extras/{name}, with one row per trajectory in the split's order.
    extras: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)


@dataclass(frozen=True)
class GenerationCost:
    """What generating one preset of a benchmark takes, as measured (docs/envs.md has the commands)."""

    time: str  # wall time in words, with the machine it was measured on, e.g. "2 min 30 s with --workers 2"
    needs: tuple[str, ...] = ()  # what must be installed or present, e.g. ("OpenFOAM",)
    gpu: bool = False  # impractical without a CUDA GPU: `dks-gym data generate` refuses it on a CPU

    def describe(self) -> str:
        """``time``, plus what it needs: one phrase for messages."""
        return self.time + (f"; needs {' and '.join(self.needs)}" if self.needs else "")


@dataclass(frozen=True)
class Benchmark:
    """Static description of one benchmark (SPEC section 1).

    ``channels`` are the physical fields stored in the file; the cell type, where present, is a separate
    root dataset that models append as an extra input channel.
    """

    name: str
    env_id: str
    grid: tuple[int, ...]
    channels: tuple[str, ...]
    observed_channel: str
    scored_channels: tuple[str, ...]
    param_name: str
    param_range: tuple[float, float]
    dt: float
    n_frames: int
    n_train: int
    n_test: int
    cell_type_codes: dict[str, int] = field(default_factory=dict)
    # Cell-type codes of solid cells (bodies, obstacles): never fluid, never a sensor.
    solid_codes: tuple[int, ...] = ()
    # The data generator as "module:function", called as function(benchmark, preset, seed=..., workdir=...,
    # progress=..., **options) -> GeneratedData; None where this version of dks-gym has none.
    generator_entry_point: str | None = None
    # Per preset, what generating it costs (for the missing-data message and `dks-gym data generate`).
    generation_costs: dict[str, GenerationCost] = field(default_factory=dict)

    @property
    def ndim(self) -> int:
        return len(self.grid)

    @property
    def n_cells(self) -> int:
        return int(np.prod(self.grid))

    @property
    def observed_index(self) -> int:
        return self.channels.index(self.observed_channel)

    @property
    def scored_indices(self) -> tuple[int, ...]:
        return tuple(self.channels.index(c) for c in self.scored_channels)

    # Geometry --------------------------------------------------------------------------------------
    def coords(self) -> tuple[np.ndarray, ...]:
        """Cell-centre coordinates, one 1D array per axis (physical units)."""
        raise NotImplementedError

    def cell_type(self) -> np.ndarray | None:
        """Integer cell-type codes on the grid (SPEC section 1), or None for benchmarks without one."""
        return None

    def fluid_mask(self, cell_type: np.ndarray | None = None) -> np.ndarray:
        """Boolean grid mask of cells that may carry a sensor (everything but solid cells)."""
        ct = self.cell_type() if cell_type is None else cell_type
        if ct is None:
            return np.ones(self.grid, dtype=bool)
        return ~np.isin(ct, self.solid_codes)

    def paper_layout(self, m: int = 16) -> np.ndarray:
        """The paper's sensor layout: ``m`` distinct flat (C-order) grid indices (SPEC section 2)."""
        raise NotImplementedError

    # Data ------------------------------------------------------------------------------------------
    @property
    def generator_available(self) -> bool:
        """Whether this version of dks-gym can generate the benchmark's data."""
        return self.generator_entry_point is not None

    def generate(
        self,
        preset: str = "paper",
        *,
        seed: int = 0,
        workdir: Path | None = None,
        progress: bool = True,
        **options: Any,
    ) -> GeneratedData:
        """Generate the benchmark's trajectories for ``preset`` ("paper" or "small") with its generator.

        ``workdir`` is where a generator may cache work (the OpenFOAM runs); ``options`` are the
        generator's own (``workers`` for the OpenFOAM benchmarks, ``device`` for the torch solvers ...),
        see the function :attr:`generator_entry_point` names.
        """
        if self.generator_entry_point is None:
            raise GeneratorUnavailable(
                f"The {self.name} data generator is not part of this version of dks-gym. "
                f"Once it is, `dks-gym data generate {self.name}` will create the dataset; "
                "if you already have a file in the dks-gym HDF5 schema, pass it with data_path=..."
            )
        generate = load_generator(self.generator_entry_point)
        return generate(self, preset, seed=seed, workdir=workdir, progress=progress, **options)


def load_generator(entry_point: str) -> Callable[..., GeneratedData]:
    """The function an entry point ``"package.module:function"`` names, its module imported on first use."""
    module, _, name = entry_point.partition(":")
    if not module or not name:
        raise ValueError(f"a generator entry point reads 'package.module:function', got {entry_point!r}")
    return getattr(importlib.import_module(module), name)


def check_preset(preset: str) -> str:
    """Return ``preset`` or raise a ValueError naming the valid presets."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    return preset


def interleaved_sweep(
    low: float, high: float, n_train: int, n_test: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Stratified uniform parameter sample with test values interleaved among the training values.

    The range is cut into ``n_train + n_test`` equal bins and one value is drawn uniformly in each, so
    every value is uniform over its bin, all values are distinct, and the test bins (spread evenly
    across the range) sit between training bins. Returns sorted ``(train, test)`` arrays.
    """
    n = n_train + n_test
    edges = np.linspace(low, high, n + 1)
    values = edges[:-1] + rng.uniform(size=n) * np.diff(edges)
    # Evenly spaced test bins, centred so neither end of the range is test-only.
    test_bins = np.unique(np.round((np.arange(n_test) + 0.5) * n / max(n_test, 1) - 0.5).astype(int))
    is_test = np.zeros(n, dtype=bool)
    is_test[test_bins] = True
    return np.sort(values[~is_test]), np.sort(values[is_test])
