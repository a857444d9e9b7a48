"""The CFD benchmarks' common ground: a box of uniform cells with cell types, and the layout helpers.

:class:`CellGridBenchmark` is what the cylinder, dambreak and sphere share (cell-centre coordinates over
a box, cell-type codes computed once, a paper layout made of named groups); the functions (equidistant
cells, snapping, mirroring) are the pieces each benchmark module states its own layout rule with, and
:func:`lattice_layout` is the rule of a custom benchmark's grid (equidistant over the fluid cells, any grid).
"""

from __future__ import annotations

import itertools
import math
from functools import cached_property
from typing import ClassVar

import numpy as np

from .base import Benchmark


class CellGridBenchmark(Benchmark):
    """A benchmark on a uniform grid of cells over the box :attr:`extent`, with cell types and a layout rule.

    A subclass sets :attr:`extent` (``((x0, x1), (y0, y1)[, (z0, z1)])`` in physical units) and defines
    :meth:`mark_cells` (its cell-type codes) and :meth:`layout_groups` (its paper layout, in named parts).
    """

    extent: ClassVar[tuple[tuple[float, float], ...]] = ()

    def coords(self) -> tuple[np.ndarray, ...]:
        """Cell-centre coordinates x0 + (i + 1/2) dx over :attr:`extent`, one 1D array per axis."""
        return cell_centres(self.extent, self.grid)

    def cell_type(self) -> np.ndarray:
        """Cell-type codes (:attr:`cell_type_codes`, see :meth:`mark_cells`), int8 on the grid, read-only."""
        return self._cell_type

    @cached_property
    def _cell_type(self) -> np.ndarray:
        ct = self.mark_cells(np.full(self.grid, self.cell_type_codes["interior"], dtype=np.int8))
        ct.setflags(write=False)
        return ct

    def mark_cells(self, ct: np.ndarray) -> np.ndarray:
        """Write the non-interior cell-type codes into ``ct`` (all "interior" on entry) and return it."""
        raise NotImplementedError

    def layout_groups(self, m: int = 16) -> dict[str, np.ndarray]:
        """The paper layout of ``m`` sensors split into its named parts (flat indices)."""
        raise NotImplementedError

    def paper_layout(self, m: int = 16) -> np.ndarray:
        """The paper's layout: the parts of :meth:`layout_groups`, concatenated in their order."""
        return np.concatenate(list(self.layout_groups(m).values()))


def cell_centres(extent: tuple[tuple[float, float], ...], grid: tuple[int, ...]) -> tuple[np.ndarray, ...]:
    """Cell-centre coordinates x0 + (i + 1/2) dx of a uniform grid over ``extent``, one array per axis."""
    return tuple(lo + (np.arange(n) + 0.5) * (hi - lo) / n for (lo, hi), n in zip(extent, grid))


def check_sensor_count(m: int, max_sensors: int, name: str) -> int:
    """Return ``m`` as an int, or raise a ValueError saying which sensor counts the layout supports."""
    if isinstance(m, bool) or not isinstance(m, (int, np.integer)):
        raise ValueError(f"m (number of sensors) must be an integer, got {m!r} of type {type(m).__name__}")
    if not 1 <= m <= max_sensors:
        raise ValueError(
            f"the {name} paper layout places 1 to {max_sensors} sensors, got m={m}; "
            "for other counts pass explicit flat grid indices (sensors=...)"
        )
    return int(m)


def equidistant_cells(first: int, last: int, n: int) -> np.ndarray:
    """Indices of ``n`` equidistant cells on the cell range first..last (both included).

    The range is cut into ``n`` equal bins and each bin centre is rounded to a cell, halves away from
    the middle of the range, so a range symmetric about a cell gives a symmetric result. Neighbouring
    indices differ by floor or ceil of the bin width, hence are distinct while n <= last - first + 1.
    """
    if not 1 <= n <= last - first + 1:
        raise ValueError(f"cannot place {n} distinct cells on the range {first}..{last}")
    width = (last - first + 1) / n
    centres = first - 0.5 + width * (np.arange(n) + 0.5)
    middle = 0.5 * (first + last)
    rounded = np.where(centres >= middle, np.floor(centres + 0.5), np.ceil(centres - 0.5))
    return rounded.astype(np.int64)


def snap_to_free_cells(targets: np.ndarray, points: np.ndarray, candidates: np.ndarray, taken: set[int]) -> list[int]:
    """For each target point in turn, the nearest candidate cell not yet taken (greedy, so all distinct).

    ``points`` are the candidates' cell centres (n, ndim), ``candidates`` their flat indices; ``taken``
    is updated in place. Ties go to the lower flat index, so the result is a pure function of the input.
    """
    order = np.argsort(candidates, kind="stable")
    points, candidates = points[order], candidates[order]
    free = np.array([c not in taken for c in candidates.tolist()], dtype=bool)
    chosen = []
    for target in np.atleast_2d(targets):
        d2 = np.sum((points - target) ** 2, axis=1)
        d2[~free] = np.inf
        k = int(np.argmin(d2))
        if not np.isfinite(d2[k]):
            raise ValueError("not enough free candidate cells for the requested sensors")
        free[k] = False
        chosen.append(int(candidates[k]))
        taken.add(int(candidates[k]))
    return chosen


def mirror(flat: list[int] | np.ndarray, grid: tuple[int, ...], axis: int) -> np.ndarray:
    """Flat indices reflected across the middle of ``axis`` (index i -> n - 1 - i)."""
    idx = list(np.unravel_index(np.asarray(flat, dtype=np.int64), grid))
    idx[axis] = grid[axis] - 1 - idx[axis]
    return np.ravel_multi_index(tuple(idx), grid).astype(np.int64)


def surface_mask(solid: np.ndarray, faces_only: bool = False) -> np.ndarray:
    """Non-solid cells that share a face, edge or corner with a solid cell (one cell diagonal away), or with
    ``faces_only`` a face. Cells beyond the grid's edge count as not solid."""
    from scipy import ndimage  # here, not at module level: `import dks_gym` stays free of scipy

    structure = ndimage.generate_binary_structure(solid.ndim, 1 if faces_only else solid.ndim)
    return ndimage.binary_dilation(solid, structure=structure) & ~solid


def interleave(*groups: list[int] | np.ndarray) -> np.ndarray:
    """Element-wise interleaving of equally long index lists: a0, b0, ..., a1, b1, ..."""
    return np.stack([np.asarray(g, dtype=np.int64) for g in groups], axis=1).reshape(-1)


def check_layout(bench: Benchmark, groups: dict[str, np.ndarray], m: int) -> None:
    """Invariant of every layout rule: m distinct cells, none solid."""
    flat = np.concatenate(list(groups.values()))
    if flat.size != m or np.unique(flat).size != m or not np.all(bench.fluid_mask().ravel()[flat]):
        raise AssertionError(f"{bench.name} layout rule produced an invalid layout for m={m}: {flat.tolist()}")


def lattice_counts(grid: tuple[int, ...], m: int) -> tuple[int, ...]:
    """Sensors per axis of :func:`lattice_layout`'s lattice: the counts c_i <= n_i whose product is the least one
    >= ``m``; among those, the most even spacing (the smallest ratio of the largest n_i / c_i to the smallest),
    then the larger counts on the earlier axes."""
    best: tuple[tuple[float, ...], tuple[int, ...]] | None = None
    for head in itertools.product(*(range(1, min(n, m) + 1) for n in grid[:-1])):
        last = -(-m // math.prod(head))  # ceil
        if last > grid[-1]:
            continue
        counts = (*head, last)
        spacing = [n / c for n, c in zip(grid, counts)]
        key = (math.prod(counts), max(spacing) / min(spacing), *(-c for c in counts))
        if best is None or key < best[0]:
            best = (key, counts)
    if best is None:
        raise ValueError(f"cannot place {m} sensors on the grid {grid}")
    return best[1]


def lattice_layout(fluid: np.ndarray, m: int) -> np.ndarray:
    """``m`` sensors equidistant over the fluid cells of a grid of any dimension: flat (C-order) indices.

    The rule (SPEC section 2's "equidistant" for any grid): along each axis, :func:`lattice_counts` cells
    placed by :func:`equidistant_cells`; their product, in C order, is a lattice of at least ``m`` points, of
    which ``m`` are kept, equidistant along that order (all of them when the product is ``m``). Each point
    then goes to the nearest fluid cell not yet taken (distance in cells; ties to the lower flat index), so
    on a grid without solid cells the sensors are the lattice points themselves. On a 1D grid of n cells
    this is ``m`` equidistant cells, as the Burgers layout; on 64 x 64 cells, m = 16 is a 4 x 4 lattice.
    """
    fluid = np.asarray(fluid, dtype=bool)
    n_fluid = int(fluid.sum())
    if isinstance(m, bool) or not isinstance(m, (int, np.integer)) or not 1 <= m <= n_fluid:
        raise ValueError(f"m (number of sensors) must be an integer from 1 to {n_fluid} (the fluid cells), got {m!r}")
    grid = fluid.shape
    axes = [equidistant_cells(0, n - 1, c) for n, c in zip(grid, lattice_counts(grid, int(m)))]
    points = np.stack([a.reshape(-1) for a in np.meshgrid(*axes, indexing="ij")], axis=1)
    if len(points) > m:
        points = points[equidistant_cells(0, len(points) - 1, int(m))]
    free = np.flatnonzero(fluid.reshape(-1))
    chosen = snap_to_free_cells(points.astype(np.float64), np.stack(np.unravel_index(free, grid), axis=1), free,
                                set())
    return np.asarray(chosen, dtype=np.int64)
