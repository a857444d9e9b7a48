"""A benchmark of your own flow: any grid (1D, 2D or 3D, any size) and channels, described by its schema file.

A :class:`CustomBenchmark` holds what the four paper benchmarks hold in their modules (grid, channels, the
observed and scored channels, dt, the parameter's name and range, cell types where there are any) but takes
them from the user: the dataset layer builds one from a file in the dks-gym HDF5 schema whose ``benchmark``
attribute names none of the four (:func:`dks_gym.dataset.load_benchmark`), and a user who writes such a file
from Python may build one by hand and pass it to :func:`dks_gym.dataset.write_dataset`. Every custom
benchmark is served by one env id, ``DKS/Custom-v0`` (``gym.make("DKS/Custom-v0", data_path=...)``).

Its default sensor layout is SPEC section 2's rule for the paper's, "equidistant over the fluid cells",
stated for any grid by :func:`~dks_gym.benchmarks.layout.lattice_layout`: an equidistant lattice of cells,
each point on the nearest free fluid cell. There is no data generator: the data are the file's.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from .base import Benchmark
from .layout import lattice_layout

#: The Gymnasium id of every custom benchmark: the env reads which one from its ``data_path``.
CUSTOM_ENV_ID = "DKS/Custom-v0"
#: The grids the convolutional models and the renderer handle: one to three axes (x, y, z).
MAX_DIMENSIONS = 3
#: A custom benchmark's name: it names checkpoint files (``NAME-koopman-lite-r32-T1...``), so one plain word.
NAME_PATTERN = re.compile(r"[a-z][a-z0-9_]*")


@dataclass(frozen=True, kw_only=True)
class CustomBenchmark(Benchmark):
    """A benchmark described by the user (the module docstring says how one is made).

    ``coordinates``: the cell-centre coordinates, one array per axis (default: i + 1/2, unit cells);
    ``cell_types``: integer codes on the grid, or None where every cell is fluid; ``cell_type_codes`` names
    the codes (required with ``cell_types``: the models append the cell type as an input channel), and
    ``solid_codes`` says which of them are solid (never a sensor).
    """

    env_id: str = CUSTOM_ENV_ID
    coordinates: tuple[np.ndarray, ...] | None = field(default=None, compare=False, repr=False)
    cell_types: np.ndarray | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        where = f"custom benchmark {self.name!r}"
        if not NAME_PATTERN.fullmatch(self.name):
            raise ValueError(f"{where}: a benchmark name is lower-case letters, digits and underscores, starting "
                             "with a letter (it names the checkpoint files), e.g. 'heat_2d'")
        if not 1 <= len(self.grid) <= MAX_DIMENSIONS or any(int(n) != n or n < 1 for n in self.grid):
            raise ValueError(f"{where}: the grid must have 1 to {MAX_DIMENSIONS} axes of positive sizes, "
                             f"got {self.grid}")
        if not self.channels or len(set(self.channels)) != len(self.channels):
            raise ValueError(f"{where}: channels must be distinct names, at least one, got {self.channels}")
        if self.observed_channel not in self.channels:
            raise ValueError(f"{where}: the observed channel {self.observed_channel!r} is not one of {self.channels}")
        if not self.scored_channels or any(c not in self.channels for c in self.scored_channels):
            raise ValueError(f"{where}: scored channels {self.scored_channels} must be a non-empty subset of "
                             f"{self.channels}")
        low, high = (*self.param_range, np.nan, np.nan)[:2]
        if len(self.param_range) != 2 or not (np.isfinite(low) and np.isfinite(high) and high > low):
            raise ValueError(f"{where}: param_range must be finite (low, high) with high > low, got "
                             f"{self.param_range}")
        if not self.dt > 0:
            raise ValueError(f"{where}: dt must be positive, got {self.dt}")
        if self.coordinates is not None and tuple(len(c) for c in self.coordinates) != tuple(self.grid):
            raise ValueError(f"{where}: coordinates of lengths {[len(c) for c in self.coordinates]} do not match "
                             f"the grid {self.grid}")
        if self.cell_types is not None:
            if tuple(self.cell_types.shape) != tuple(self.grid):
                raise ValueError(f"{where}: cell types of shape {self.cell_types.shape}, not the grid {self.grid}")
            unnamed = sorted(set(np.unique(self.cell_types).tolist()) - set(self.cell_type_codes.values()))
            if unnamed:
                raise ValueError(f"{where}: cell-type codes {unnamed} have no name in cell_type_codes "
                                 f"{self.cell_type_codes}; name every code the grid uses")
        elif self.cell_type_codes:
            raise ValueError(f"{where}: cell_type_codes given without cell_types; pass the grid of codes too")

    def coords(self) -> tuple[np.ndarray, ...]:
        """Cell-centre coordinates, one 1D array per axis: the given ones, else i + 1/2 (unit cells)."""
        if self.coordinates is None:
            return tuple(np.arange(n) + 0.5 for n in self.grid)
        return tuple(np.asarray(c, dtype=np.float64) for c in self.coordinates)

    def cell_type(self) -> np.ndarray | None:
        """The cell-type codes on the grid (int8, read-only), or None where every cell is fluid."""
        if self.cell_types is None:
            return None
        ct = np.asarray(self.cell_types, dtype=np.int8).copy()
        ct.setflags(write=False)
        return ct

    def paper_layout(self, m: int = 16) -> np.ndarray:
        """The default layout of ``m`` sensors: an equidistant lattice over the fluid cells
        (:func:`~dks_gym.benchmarks.layout.lattice_layout`)."""
        return lattice_layout(self.fluid_mask(), m)


__all__ = ["CUSTOM_ENV_ID", "MAX_DIMENSIONS", "NAME_PATTERN", "CustomBenchmark"]
