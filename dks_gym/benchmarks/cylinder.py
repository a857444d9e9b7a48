"""2D flow past a circular cylinder: geometry, cell types and the paper's sensor layout.

The domain is the paper's (Section III.B, SPEC section 1): x in [-8R, 16R], y in [-4R, 4R], a cylinder
of radius R = 1 centred at the origin, resampled on a uniform 64 x 64 grid (dx = 0.375, dy = 0.125,
so the cells are three times longer than high). The top and bottom boundaries are no-slip walls
(paper Fig. 2 caption), the left boundary is the inlet and the right one the outlet.

Cell types (SPEC section 1), decided on cell centres:

* 2 body: the centre lies strictly inside the circle x^2 + y^2 < R^2;
* 1 wall: the first and last rows in y, corners included (the walls span the whole channel, so a
  corner cell touches the wall and takes its no-slip condition);
* 3 inlet / 4 outlet: the first / last column in x without the two corner cells;
* 0 interior: everything else.

The sensor layout (SPEC section 2, paper Fig. 2a) follows from the geometry, see
:meth:`CylinderBenchmark.layout_groups`. The geometry helpers live in :mod:`dks_gym.benchmarks.layout`.

The data come from OpenFOAM's pimpleFoam, one run per Reynolds number: ``CYLINDER.generate(...)`` calls
:func:`dks_gym.solvers.cylinder_case.generate_cylinder` (case set-up, spin-up detection, mesh study:
docs/cfd.md).
"""

from __future__ import annotations

import math

import numpy as np

from .base import GenerationCost
from .layout import (
    CellGridBenchmark,
    check_layout,
    check_sensor_count,
    equidistant_cells,
    interleave,
    mirror,
    snap_to_free_cells,
    surface_mask,
)

RADIUS = 1.0
EXTENT = ((-8.0, 16.0), (-4.0, 4.0))
CELL_TYPE_CODES = {"interior": 0, "wall": 1, "body": 2, "inlet": 3, "outlet": 4}
# Wake sensors sit in R < x <= R + NEAR_WAKE_LENGTH (two diameters behind the body) on the rows
# nearest to y = +-WAKE_OFFSET, where the shed vortices pass (units of R).
NEAR_WAKE_LENGTH = 4.0
WAKE_OFFSET = 0.5
# The layout rule is defined up to twice the paper's 16 sensors; pass explicit indices for more.
MAX_SENSORS = 32


# The benchmark ----------------------------------------------------------------------------------------
class CylinderBenchmark(CellGridBenchmark):
    """2D flow past a cylinder, 64 x 64 cells over [-8, 16] x [-4, 4], Re in [59.5, 990.5].

    Cell centres x_i = -8 + (i + 1/2) 0.375, y_j = -4 + (j + 1/2) 0.125; cell types {0 interior, 1 wall,
    2 body, 3 inlet, 4 outlet}; the paper layout (Fig. 2a) is the surface sensors, then the wake sensors.
    """

    extent = EXTENT

    def mark_cells(self, ct: np.ndarray) -> np.ndarray:
        """Inlet and outlet columns, then the wall rows (corners included), then the body."""
        x, y = np.meshgrid(*self.coords(), indexing="ij")
        codes = self.cell_type_codes
        ct[0, :] = codes["inlet"]
        ct[-1, :] = codes["outlet"]
        ct[:, [0, -1]] = codes["wall"]  # after inlet/outlet: the corners belong to the walls
        ct[x**2 + y**2 < RADIUS**2] = codes["body"]
        return ct

    def layout_groups(self, m: int = 16) -> dict[str, np.ndarray]:
        """The paper layout split into its parts: ``{"surface": ..., "wake": ...}`` (flat indices).

        The m // 2 mirror pairs (y -> -y) are split between the body surface (the larger half) and the
        near wake:

        * surface: pair k sits on the fluid cells nearest to the rear-surface points at angles
          +-90 (k + 1/2) / n_surface degrees from the downstream axis (equally spaced over the rear
          half), restricted to cells touching the body;
        * wake: pairs on the two rows nearest to y = +-R/2, at equidistant columns over
          R < x <= 5R (:func:`equidistant_cells`).

        An odd m adds one wake sensor on the first row above the axis (no cell centre lies on y = 0),
        the only sensor without a mirror image. Pairs are listed upper then lower.
        """
        m = check_sensor_count(m, MAX_SENSORS, self.name)
        n_pairs, n_single = divmod(m, 2)
        n_surface = (n_pairs + 1) // 2
        n_wake = n_pairs - n_surface
        x, y = self.coords()
        ny = self.grid[1]
        upper = np.zeros(self.grid, dtype=bool)
        upper[:, ny // 2 :] = True  # y > 0: the grid is symmetric and no row sits on the axis
        taken: set[int] = set()

        first = int(np.searchsorted(x, RADIUS, side="right"))
        last = int(np.searchsorted(x, RADIUS * (1.0 + NEAR_WAKE_LENGTH), side="right")) - 1
        row = int(np.argmin(np.abs(y - WAKE_OFFSET * RADIUS)))  # ties to the row nearer the axis
        wake: list[int] = []
        if n_wake:
            columns = equidistant_cells(first, last, n_wake)
            top = np.ravel_multi_index((columns, np.full(n_wake, row)), self.grid)
            wake.extend(interleave(top, mirror(top, self.grid, axis=1)).tolist())
        if n_single:
            (column,) = equidistant_cells(first, last, 1)
            wake.append(int(np.ravel_multi_index((column, ny // 2), self.grid)))
        taken.update(wake)  # the surface rule snaps around the wake cells

        surface: np.ndarray = np.zeros(0, dtype=np.int64)
        if n_surface:
            theta = 0.5 * math.pi * (np.arange(n_surface) + 0.5) / n_surface
            targets = RADIUS * np.stack([np.cos(theta), np.sin(theta)], axis=1)
            candidates = np.flatnonzero(surface_mask(self.cell_type() == self.cell_type_codes["body"]) & upper)
            points = np.stack([c[i] for c, i in zip((x, y), np.unravel_index(candidates, self.grid))], axis=1)
            top = snap_to_free_cells(targets, points, candidates, taken)
            surface = interleave(top, mirror(top, self.grid, axis=1))

        groups = {"surface": surface, "wake": np.asarray(wake, dtype=np.int64)}
        check_layout(self, groups, m)
        return groups


CYLINDER = CylinderBenchmark(
    name="cylinder",
    env_id="DKS/Cylinder-v0",
    grid=(64, 64),
    channels=("u", "v", "p"),
    observed_channel="p",
    scored_channels=("u", "v", "p"),
    param_name="Re",
    param_range=(59.5, 990.5),
    dt=0.5,
    n_frames=100,
    n_train=90,
    n_test=11,
    cell_type_codes=dict(CELL_TYPE_CODES),
    solid_codes=(CELL_TYPE_CODES["body"],),
    generator_entry_point="dks_gym.solvers.cylinder_case:generate_cylinder",
    generation_costs={
        "small": GenerationCost("6-26 s on a 2-core CPU", needs=("OpenFOAM",)),
        "paper": GenerationCost("43 min with --workers 2 on a 2-core CPU (the default --workers 1 is slower)",
                                needs=("OpenFOAM",)),
    },
)
