"""2D dambreak: geometry, cell types and the paper's sensor layout.

The geometry is OpenFOAM's canonical damBreak tutorial (paper Section III.C, Fig. 2b): a box
0.584 m x 0.584 m (x, y from 0) with a rectangular obstacle 0.024 m wide and 0.048 m high standing on
the bottom, its left edge at x = 0.292 m (tutorial vertices 2 .. 2.16438 and 0 .. 0.32876 times
convertToMeters = 0.146). The fields are resampled on a uniform 64 x 64 grid, dx = dy = 0.009125 m,
on which the obstacle covers 3 x 5 cells.

Cell types (SPEC section 1), decided on cell centres:

* 2 obstacle: the centre lies in the closed rectangle 0.292 <= x <= 0.316, y <= 0.048;
* 1 wall: the left and right columns and the bottom row, the two top corners included (the side
  walls span the full height, as in the tutorial's leftWall / rightWall patches);
* 3 atmosphere: the top row without its two corner cells (the tutorial's open "atmosphere" patch);
* 0 interior: everything else.

The sensor layout (SPEC section 2) is :meth:`DambreakBenchmark.layout_groups`. The data come from
OpenFOAM's interFoam, one run per water viscosity: ``DAMBREAK.generate(...)`` calls
:func:`dks_gym.solvers.dambreak_case.generate_dambreak` (case set-up and validation: docs/cfd.md).
"""

from __future__ import annotations

import numpy as np

from .base import GenerationCost
from .layout import (
    CellGridBenchmark,
    check_layout,
    check_sensor_count,
    equidistant_cells,
    snap_to_free_cells,
    surface_mask,
)

BOX = (0.584, 0.584)
EXTENT = ((0.0, BOX[0]), (0.0, BOX[1]))
OBSTACLE_X = (0.292, 0.316)  # left and right edge (m); width 0.024 m
OBSTACLE_HEIGHT = 0.048
CELL_TYPE_CODES = {"interior": 0, "wall": 1, "obstacle": 2, "atmosphere": 3}
# The layout rule is defined up to twice the paper's 16 sensors; pass explicit indices for more.
MAX_SENSORS = 32


class DambreakBenchmark(CellGridBenchmark):
    """2D two-phase dambreak, 64 x 64 cells over the 0.584 m damBreak box, nu_w in [1e-3, 9.9e-2] m^2/s.

    Cell centres (i + 1/2) 0.009125 m in x and y; cell types {0 interior, 1 wall, 2 obstacle, 3 atmosphere};
    the paper layout (Fig. 2b) is the bottom sensors by x, then the obstacle sensors.
    """

    extent = EXTENT

    def mark_cells(self, ct: np.ndarray) -> np.ndarray:
        """The open top row, then the side walls and the floor (top corners included), then the obstacle."""
        x, y = np.meshgrid(*self.coords(), indexing="ij")
        codes = self.cell_type_codes
        ct[:, -1] = codes["atmosphere"]
        ct[[0, -1], :] = codes["wall"]  # after the atmosphere: the top corners belong to the side walls
        ct[:, 0] = codes["wall"]
        ct[(x >= OBSTACLE_X[0]) & (x <= OBSTACLE_X[1]) & (y <= OBSTACLE_HEIGHT)] = codes["obstacle"]
        return ct

    def obstacle_columns(self) -> np.ndarray:
        """Grid columns the obstacle occupies (32, 33, 34)."""
        return np.flatnonzero(np.any(self.cell_type() == self.cell_type_codes["obstacle"], axis=1))

    def layout_groups(self, m: int = 16) -> dict[str, np.ndarray]:
        """The paper layout split into its parts: ``{"bottom": ..., "obstacle": ...}`` (flat indices).

        Both parts are mirror-symmetric about the obstacle's middle column c (33; the obstacle's three
        columns are symmetric about it, the box is not: the obstacle stands 0.012 m right of the box
        centre). Of m sensors, 2 floor(5 m / 16) go to the bottom (10 of 16) and the rest around the
        obstacle:

        * bottom: the bottom row from column c - 29 to c + 29 (as far as the right wall allows, wall
          columns excluded) is cut into equal bins, one sensor on the free fluid cell nearest each bin
          centre, so the sensors are equidistant along the bottom and skip the obstacle (for m = 16:
          every sixth column, 6, 12, ..., 60, the gap across the obstacle included);
        * obstacle: the 15 fluid cells touching the obstacle, walked from the bottom of its left face
          over the top to the bottom of its right face, carry equidistant sensors along that path
          (:func:`equidistant_cells`; an odd count puts one on the top centre).
        """
        m = check_sensor_count(m, MAX_SENSORS, self.name)
        n_bottom = 2 * ((5 * m) // 16)
        n_obstacle = m - n_bottom
        x, y = self.coords()
        nx = self.grid[0]
        columns = self.obstacle_columns()
        centre = int(columns[len(columns) // 2])
        if len(columns) % 2 == 0 or np.any(np.diff(columns) != 1):
            raise AssertionError(f"the obstacle must cover an odd run of columns to be mirrored, got {columns}")
        solid = self.cell_type() == self.cell_type_codes["obstacle"]
        taken: set[int] = set()

        obstacle = np.zeros(0, dtype=np.int64)
        if n_obstacle:
            path = np.flatnonzero(surface_mask(solid))
            i, j = np.unravel_index(path, self.grid)
            # Polar angle about the obstacle's base below column c orders the outline left -> top -> right.
            angle = np.arctan2(y[j] - EXTENT[1][0], x[centre] - x[i])
            path = path[np.argsort(angle, kind="stable")]
            obstacle = path[equidistant_cells(0, len(path) - 1, n_obstacle)]
            taken.update(obstacle.tolist())

        bottom = np.zeros(0, dtype=np.int64)
        if n_bottom:
            reach = min(nx - 2 - centre, centre - 1)
            n_bins = n_bottom
            # Bin centres of the symmetric bottom line c - reach .. c + reach, in cells from c; right half only.
            offsets = -reach - 0.5 + (2 * reach + 1) * (np.arange(n_bins // 2, n_bins) + 0.5) / n_bins
            targets = np.stack([x[centre] + offsets * (x[1] - x[0]), np.full(offsets.size, y[0])], axis=1)
            right = np.arange(centre + 1, centre + reach + 1)
            right = right[~solid[right, 0]]
            candidates = np.ravel_multi_index((right, np.zeros_like(right)), self.grid)
            points = np.stack([x[right], np.full(right.size, y[0])], axis=1)
            half = snap_to_free_cells(targets, points, candidates, taken)
            left = _mirror_about_column(half, self.grid, centre)
            bottom = np.concatenate([left[::-1], half])  # ordered by x

        groups = {"bottom": bottom, "obstacle": obstacle}
        check_layout(self, groups, m)
        return groups


def _mirror_about_column(flat: list[int], grid: tuple[int, ...], centre: int) -> np.ndarray:
    """Flat indices reflected across grid column ``centre`` (i -> 2 centre - i)."""
    i, j = np.unravel_index(np.asarray(flat, dtype=np.int64), grid)
    return np.ravel_multi_index((2 * centre - i, j), grid).astype(np.int64)


DAMBREAK = DambreakBenchmark(
    name="dambreak",
    env_id="DKS/Dambreak-v0",
    grid=(64, 64),
    channels=("Ux", "Uy", "p_rgh", "p", "alpha.water"),
    observed_channel="p",
    scored_channels=("Ux", "Uy", "p_rgh", "p", "alpha.water"),
    param_name="nu_w",
    param_range=(1.0e-3, 9.9e-2),
    dt=0.01,
    n_frames=100,
    n_train=90,
    n_test=11,
    cell_type_codes=dict(CELL_TYPE_CODES),
    solid_codes=(CELL_TYPE_CODES["obstacle"],),
    generator_entry_point="dks_gym.solvers.dambreak_case:generate_dambreak",
    generation_costs={
        "small": GenerationCost("6-26 s on a 2-core CPU", needs=("OpenFOAM",)),
        "paper": GenerationCost("2 min 30 s with --workers 2 on a 2-core CPU (7 min 27 s with the default 1)",
                                needs=("OpenFOAM",)),
    },
)
