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
come from the batched lattice Boltzmann solver (:mod:`dks_gym.solvers.lbm`, case setup in
:mod:`dks_gym.solvers.sphere_case`): velocity inlet at x = -8R, no-slip walls at y = +-4R, periodic
z faces, pressure outlet behind a 4R absorbing layer beyond x = 16R; see :meth:`SphereBenchmark.generate` and
docs/sphere.md.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from .base import Benchmark, GeneratedData, check_preset, interleaved_sweep
from .layout import (
    cell_centres,
    check_layout,
    check_sensor_count,
    equidistant_cells,
    interleave,
    mirror,
    snap_to_free_cells,
    surface_mask,
)

RADIUS = 1.0
EXTENT = ((-8.0, 16.0), (-4.0, 4.0), (-4.0, 4.0))
CELL_TYPE_CODES = {"interior": 0, "wall": 1, "body": 2, "inlet": 3, "outlet": 4}
# Wake sensors sit in R < x <= R + NEAR_WAKE_LENGTH on the lines nearest y, z = +-WAKE_OFFSET (units of R),
# the same near wake as the cylinder's so the two benchmarks read alike.
NEAR_WAKE_LENGTH = 4.0
WAKE_OFFSET = 0.5
BLOCKAGE = math.pi * RADIUS**2 / ((EXTENT[1][1] - EXTENT[1][0]) * (EXTENT[2][1] - EXTENT[2][0]))
# The layout rule is defined up to twice the paper's 16 sensors; pass explicit indices for more.
MAX_SENSORS = 32

GENERATOR_VERSION = "1"
# Solver settings per preset (see dks_gym.solvers.sphere_case): lattice nodes per R, lattice inflow speed,
# spin-up (R/U) before the first frame, frames; trajectory counts (n_train, n_test).
PRESET_SETTINGS: dict[str, dict[str, Any]] = {
    "paper": {"resolution": 8, "u_lattice": 0.05, "spin_up": 50.0, "n_frames": 100},
    "small": {"resolution": 2, "u_lattice": 0.1, "spin_up": 10.0, "n_frames": 10},
}
PRESET_COUNTS = {"paper": (90, 11), "small": (4, 2)}


class SphereBenchmark(Benchmark):
    """3D flow past a sphere, 64^3 cells over [-8, 16] x [-4, 4] x [-4, 4], Re in [59.5, 990.5]."""

    def coords(self) -> tuple[np.ndarray, ...]:
        """(x, y, z) cell centres: x_i = -8 + (i + 1/2) 0.375, y_j and z_k = -4 + (j + 1/2) 0.125."""
        return cell_centres(EXTENT, self.grid)

    def cell_type(self) -> np.ndarray:
        """Cell-type codes {0 interior, 1 wall, 2 body, 3 inlet, 4 outlet}, int8 (64, 64, 64), read-only."""
        return self._cell_type

    @cached_property
    def _cell_type(self) -> np.ndarray:
        x, y, z = self.coords()
        codes = self.cell_type_codes
        ct = np.full(self.grid, codes["interior"], dtype=np.int8)
        ct[0] = codes["inlet"]
        ct[-1] = codes["outlet"]
        ct[:, [0, -1], :] = codes["wall"]  # after inlet/outlet: the shared edges belong to the walls
        body = x[:, None, None] ** 2 + y[None, :, None] ** 2 + z[None, None, :] ** 2 < RADIUS**2
        ct[body] = codes["body"]
        ct.setflags(write=False)
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

    def paper_layout(self, m: int = 16) -> np.ndarray:
        """The paper's layout (Fig. 2c): surface sensors, then wake sensors; see :meth:`layout_groups`."""
        return np.concatenate(list(self.layout_groups(m).values()))

    def generate(
        self,
        preset: str = "paper",
        *,
        seed: int = 0,
        workdir: Path | None = None,
        progress: bool = True,
        device: str = "cpu",
        compile: bool | None = None,
        max_batch: int | None = None,
        **options: Any,
    ) -> GeneratedData:
        """Run the lattice Boltzmann sphere for the preset's Reynolds numbers ("paper": 90 / 11; "small": 4 / 2).

        Re comes from :func:`interleaved_sweep` over [59.5, 990.5] with ``np.random.default_rng(seed)``.
        All runs of a split advance together as one batch on ``device`` ("cpu", "cuda", "cuda:1" ...),
        split into batches that fit its memory (or at most ``max_batch``). ``compile`` (default: on for
        CUDA, off on the CPU) wraps the step in torch.compile. Solver settings can be overridden by
        keyword: resolution (nodes per R), u_lattice, spin_up (R/U), n_frames, frame_dt is fixed at
        0.5 R/U, smagorinsky, perturbation, sponge (R), sponge_strength; see :mod:`dks_gym.solvers.sphere_case`.
        ``time`` counts from the first frame (taken after ``spin_up``). Drag and lift coefficients at
        every frame are kept in the file as extras ``drag``, ``lift`` (y, wall-normal) and ``lift_z``.
        The runs happen when ``trajectories`` is iterated; ``workdir`` is unused (nothing is cached, so
        an interrupted generation starts again).
        """
        check_preset(preset)
        from ..solvers import sphere_case

        allowed = set(sphere_case.SETTING_KEYS) - {"frame_dt", "walls", "half_width"}
        unknown = set(options) - allowed
        if unknown:
            raise ValueError(
                f"unknown option(s) for the sphere generator: {', '.join(sorted(unknown))}; it accepts preset, "
                f"seed, workdir, progress, device, compile, max_batch and the solver settings {', '.join(sorted(allowed))}"
            )
        settings = {**sphere_case.DEFAULTS, **PRESET_SETTINGS[preset], **options, "frame_dt": self.dt}
        n_train, n_test = PRESET_COUNTS[preset]
        low, high = self.param_range
        re_train, re_test = interleaved_sweep(low, high, n_train, n_test, np.random.default_rng(seed))
        n_frames = int(settings["n_frames"])
        if n_frames < 2:
            raise ValueError(f"n_frames must be at least 2, got {n_frames}")
        time = self.dt * np.arange(n_frames)
        coords, cell_type = self.coords(), self.cell_type()
        re_all = np.concatenate([re_train, re_test])
        extras: dict[str, dict[str, np.ndarray]] = {
            split: {k: np.zeros((n, n_frames)) for k in ("drag", "lift", "lift_z")}
            for split, n in (("train", n_train), ("test", n_test))
        }
        info: dict[str, Any] = {}

        def trajectories() -> Iterator[tuple[str, int, np.ndarray]]:
            batches = sphere_case.run_batches(
                re_all, settings, coords=coords, cell_type=cell_type, device=device, compile=compile,
                max_batch=max_batch, progress=progress, info=info,
            )
            for part, res in batches:
                for j, i in enumerate(range(part.start, part.stop)):
                    split, index = ("train", i) if i < n_train else ("test", i - n_train)
                    for key in ("drag", "lift", "lift_z"):
                        extras[split][key][index] = res[key][j]
                    yield split, index, res["fields"][j]

        generator: dict[str, Any] = {
            "name": __name__,
            "version": GENERATOR_VERSION,
            "preset": preset,
            "seed": int(seed),
            "solver": "batched lattice Boltzmann D3Q19, BGK + Smagorinsky, float32 (dks_gym.solvers.lbm)",
            "boundaries": "x=-8R velocity inlet (NEE), y=+-4R no-slip walls (half-way bounce-back), z periodic, "
            "pressure outlet (NEE) behind an absorbing layer in 16R < x < 16R + sponge; sphere by half-way bounce-back",
            "settings": {k: settings[k] for k in sphere_case.SETTING_KEYS},
            "device": str(device),
            "lattice": sphere_case.describe(settings),
            "units": "lengths R, velocity U, time R/U, p kinematic in U^2 relative to the outlet; Re = U 2R / nu",
            "time": "time counts from the first frame, taken after spin_up R/U from an impulsive start",
            "extras": "drag, lift (y), lift_z: force coefficients F / (0.5 U^2 pi R^2) at every frame",
        }
        return GeneratedData(
            time=time,
            params={"train": re_train, "test": re_test},
            trajectories=trajectories(),
            generator=generator,
            coords=coords,
            cell_type=cell_type,
            extras=extras,
        )


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
)
