"""3D flow past a sphere: geometry, cell types and the paper's sensor layout.

The paper gives the grid (64^3) but not the domain; dks-gym extends the cylinder's domain by a z axis
of the same height: x in [-8R, 16R], y in [-4R, 4R], z in [-4R, 4R], a sphere of radius R = 1 at the
origin (dx = 0.375, dy = dz = 0.125). The blockage (frontal area over cross-section) is
pi R^2 / (8R x 8R) = pi / 64 = 4.9 %.

Cell types (SPEC section 1), decided on cell centres:

* 2 body: the centre lies strictly inside the sphere x^2 + y^2 + z^2 < R^2;
* 1 wall: the two faces in y (the no-slip top and bottom walls of the paper's Fig. 2c), edges included;
* 3 inlet / 4 outlet: the x-min / x-max face without the cells on the walls;
* 0 interior: everything else, including the two z faces, which are not walls (the solver makes them
  slip or periodic) and so carry no code of their own.

The sensor layout (SPEC section 2, paper Fig. 2c) is :meth:`SphereBenchmark.layout_groups`. The data
come from the batched lattice Boltzmann solver (:mod:`dks_gym.solvers.lbm`, case setup and generator in
:mod:`dks_gym.solvers.sphere_case`): velocity inlet at x = -8R, no-slip walls at y = +-4R, periodic
z faces, pressure outlet behind a 4R absorbing layer beyond x = 16R; see
:func:`dks_gym.solvers.sphere_case.generate_sphere` and docs/sphere.md.
"""

from __future__ import annotations

import math

import numpy as np

from .cylinder import CELL_TYPE_CODES, MAX_SENSORS, NEAR_WAKE_LENGTH, RADIUS, WAKE_OFFSET
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

# The body radius, cell-type codes and sensor-count limit are the cylinder's, and so is the near wake:
# wake sensors sit in R < x <= R + NEAR_WAKE_LENGTH on the lines nearest y, z = +-WAKE_OFFSET (units of
# R), so the two benchmarks read alike.
EXTENT = ((-8.0, 16.0), (-4.0, 4.0), (-4.0, 4.0))
BLOCKAGE = math.pi * RADIUS**2 / ((EXTENT[1][1] - EXTENT[1][0]) * (EXTENT[2][1] - EXTENT[2][0]))


class SphereBenchmark(CellGridBenchmark):
    """3D flow past a sphere, 64^3 cells over [-8, 16] x [-4, 4] x [-4, 4], Re in [59.5, 990.5].

    Cell centres x_i = -8 + (i + 1/2) 0.375, y_j and z_k = -4 + (j + 1/2) 0.125; cell types {0 interior,
    1 wall, 2 body, 3 inlet, 4 outlet}; the paper layout (Fig. 2c) is the surface sensors, then the wake
    sensors.
    """

    extent = EXTENT

    def mark_cells(self, ct: np.ndarray) -> np.ndarray:
        """Inlet and outlet faces, then the two y walls (shared edges included), then the body."""
        x, y, z = self.coords()
        codes = self.cell_type_codes
        ct[0] = codes["inlet"]
        ct[-1] = codes["outlet"]
        ct[:, [0, -1], :] = codes["wall"]  # after inlet/outlet: the shared edges belong to the walls
        body = x[:, None, None] ** 2 + y[None, :, None] ** 2 + z[None, None, :] ** 2 < RADIUS**2
        ct[body] = codes["body"]
        return ct

    def layout_groups(self, m: int = 16) -> dict[str, np.ndarray]:
        """The paper layout split into its parts: ``{"surface": ..., "wake": ...}`` (flat indices).

        The sensors come in quadruples symmetric under y -> -y and z -> -z (no cell centre lies on
        y = 0 or z = 0, so every cell has four distinct images). The m // 4 quadruples are split between
        the body surface (the larger half) and the near wake, as on the cylinder:

        * surface: quadruple k sits on the fluid cells touching the body nearest to the points of the
          diagonal meridians (|y| = |z|) at polar angle 90 (k + 1/2) / n_surface degrees from the
          downstream axis (equally spaced over the rear hemisphere);
        * wake: quadruples at (x_k, +-R/2, +-R/2) (nearest rows), x_k equidistant columns over
          R < x <= 5R.

        The m % 4 remaining sensors go to the middle wake column on the first layer above z = 0: a pair
        at y = +-R/2 when two or three remain, one cell next to the axis when one or three remain;
        these break the z -> -z symmetry (and the single one also y -> -y), which no cell can avoid.
        Quadruples are listed (+y +z), (-y +z), (+y -z), (-y -z).
        """
        m = check_sensor_count(m, MAX_SENSORS, self.name)
        n_quads, n_rest = divmod(m, 4)
        n_surface = (n_quads + 1) // 2
        n_wake = n_quads - n_surface
        x, y, z = self.coords()
        ny, nz = self.grid[1], self.grid[2]
        octant = np.zeros(self.grid, dtype=bool)
        octant[:, ny // 2 :, nz // 2 :] = True  # y > 0 and z > 0
        taken: set[int] = set()

        first = int(np.searchsorted(x, RADIUS, side="right"))
        last = int(np.searchsorted(x, RADIUS * (1.0 + NEAR_WAKE_LENGTH), side="right")) - 1
        row = int(np.argmin(np.abs(y - WAKE_OFFSET * RADIUS)))  # ties to the row nearer the axis
        layer = int(np.argmin(np.abs(z - WAKE_OFFSET * RADIUS)))
        wake: list[int] = []
        if n_wake:
            columns = equidistant_cells(first, last, n_wake)
            corner = np.ravel_multi_index((columns, np.full(n_wake, row), np.full(n_wake, layer)), self.grid)
            wake.extend(self._quadruples(corner).tolist())
        (middle,) = equidistant_cells(first, last, 1)
        if n_rest >= 2:
            top = np.ravel_multi_index(([middle], [row], [nz // 2]), self.grid)
            wake.extend(interleave(top, mirror(top, self.grid, axis=1)).tolist())
        if n_rest % 2:
            wake.append(int(np.ravel_multi_index((middle, ny // 2, nz // 2), self.grid)))
        taken.update(wake)  # the surface rule snaps around the wake cells

        surface = np.zeros(0, dtype=np.int64)
        if n_surface:
            alpha = 0.5 * math.pi * (np.arange(n_surface) + 0.5) / n_surface
            off_axis = RADIUS * np.sin(alpha) / math.sqrt(2.0)
            targets = np.stack([RADIUS * np.cos(alpha), off_axis, off_axis], axis=1)
            candidates = np.flatnonzero(surface_mask(self.cell_type() == self.cell_type_codes["body"]) & octant)
            ijk = np.unravel_index(candidates, self.grid)
            points = np.stack([c[i] for c, i in zip((x, y, z), ijk)], axis=1)
            surface = self._quadruples(snap_to_free_cells(targets, points, candidates, taken))

        groups = {"surface": surface, "wake": np.asarray(wake, dtype=np.int64)}
        check_layout(self, groups, m)
        return groups

    def _quadruples(self, octant_cells: list[int] | np.ndarray) -> np.ndarray:
        """Each cell of the (+y, +z) octant followed by its images under y -> -y, z -> -z and both."""
        flip_y = mirror(octant_cells, self.grid, axis=1)
        flip_z = mirror(octant_cells, self.grid, axis=2)
        return interleave(octant_cells, flip_y, flip_z, mirror(flip_y, self.grid, axis=2))


SPHERE = SphereBenchmark(
    name="sphere",
    env_id="DKS/Sphere-v0",
    grid=(64, 64, 64),
    channels=("u", "v", "w", "p"),
    observed_channel="p",
    scored_channels=("u", "v", "w", "p"),
    param_name="Re",
    param_range=(59.5, 990.5),
    dt=0.5,
    n_frames=100,
    n_train=90,
    n_test=11,
    cell_type_codes=dict(CELL_TYPE_CODES),
    solid_codes=(CELL_TYPE_CODES["body"],),
    generator_entry_point="dks_gym.solvers.sphere_case:generate_sphere",
    generation_costs={
        "small": GenerationCost("16-30 s on one CPU core"),
        # 1.5e12 lattice updates (docs/sphere.md): 40 h at the ~10 MLUPS measured on a CPU; on an H200 the
        # compiled batch ran at 1.4-1.7 GLUPS, and 4 of the 101 runs took 57 s (benchmarks/results/gpu/).
        "paper": GenerationCost("about 16-19 min on one NVIDIA H200 (extrapolated from 4 of its 101 runs); "
                                "about 40 h on a CPU", needs=("a CUDA GPU",), gpu=True),
    },
)
