"""The dambreak benchmark's OpenFOAM case (interFoam) and its generator, :data:`generate_dambreak`.

Geometry (the canonical damBreak, :mod:`dks_gym.benchmarks.dambreak`): a 0.584 m square box open at
the top, an obstacle 0.024 m wide and 0.048 m high on the floor at x = 0.292 m, and a water column
0.1461 m wide and 0.292 m high against the left wall, released at t = 0. Air: nu = 1.48e-5 m^2/s,
rho = 1 kg/m^3; water: rho = 1000 kg/m^3 and the swept viscosity nu_w; surface tension 0.07 N/m,
g = 9.81 m/s^2 downwards.

The case is written here from that geometry (the other case files are the templates in
``templates/dambreak``): a rectilinear block mesh whose block edges lie on the
obstacle and on the water column's edges, so ``setFields`` fills the column exactly (initial water
volume = 0.1461 x 0.292 x depth); cells are about ``cell_size`` wide and half that across the
obstacle and in the floor layer y < 0.048 m, where the surge front travels (``cell_size`` = 0.0127 m is
the tutorial's resolution, 2,368 cells). interFoam runs with an adjustable time step (Courant 1) that
lands exactly on the output times 0.01, 0.02, ... s; binary output is read back with fluidfoam and
resampled on the benchmark's 64 x 64 grid (:class:`~dks_gym.solvers.openfoam.Resampler`; obstacle
cells are 0 in every channel). Each run also records, on the solver's own mesh, the water volume
(integral of alpha.water) and the surge-front position along the floor at every frame, for the
validations in ``validation/dambreak_validation.py``.

:data:`generate_dambreak` (an :class:`~dks_gym.solvers.openfoam.SweepGenerator`) is the benchmark's
generator: ``DAMBREAK.generate("paper")`` runs the 90 + 11 runs ("small": 3 + 2) and returns the water
volume, outflow and surge front of every run as extras.
"""

from __future__ import annotations

from collections.abc import Mapping
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np

from ..benchmarks.dambreak import BOX, OBSTACLE_HEIGHT, OBSTACLE_X
from . import openfoam as of

GENERATOR_VERSION = "1"

WATER_COLUMN = (0.1461, 0.292)  # width a and height 2a (m), against the left wall
DEPTH = 0.0146  # thickness of the one-cell-deep 2D mesh (m), as in the tutorial
GRAVITY = 9.81
RHO_WATER, RHO_AIR = 1000.0, 1.0
NU_AIR = 1.48e-5
SIGMA = 0.07

CHANNEL_FIELDS = (("U", 0), ("U", 1), ("p_rgh", None), ("p", None), ("alpha.water", None))
PATCHES = ("leftWall", "rightWall", "lowerWall", "atmosphere")
# Grid values near the boundary (SPEC channel order Ux, Uy, p_rgh, p, alpha.water): no slip on the walls,
# the cell's own value elsewhere (zero-gradient, fixedFluxPressure, open top).
_WALL = {"Ux": 0.0, "Uy": 0.0}
BOUNDARY_VALUES = {"leftWall": _WALL, "rightWall": _WALL, "lowerWall": _WALL, "atmosphere": {}}

#: Per-preset settings; every key enters the run cache key, so changing one reruns the affected runs.
PRESETS: dict[str, dict[str, Any]] = {
    "paper": {"n_train": 90, "n_test": 11, "cell_size": 0.0127, "frame_dt": 0.01, "n_frames": 100, "max_co": 1.0},
    "small": {"n_train": 3, "n_test": 2, "cell_size": 0.025, "frame_dt": 0.01, "n_frames": 100, "max_co": 1.0},
}


def _geometry() -> tuple[list[float], list[float], tuple[int, int]]:
    """Block edges in x and y and the (i, j) index of the missing block (the obstacle)."""
    xs = [0.0, WATER_COLUMN[0], OBSTACLE_X[0], OBSTACLE_X[1], BOX[0]]
    ys = [0.0, OBSTACLE_HEIGHT, WATER_COLUMN[1], BOX[1]]
    return xs, ys, (2, 0)


def cell_counts(cell_size: float) -> tuple[list[int], list[int]]:
    """Cells per block edge in x and y: about ``cell_size``, half that over the obstacle and the floor layer."""
    if not 0 < cell_size <= 0.05:
        raise ValueError(f"cell_size must be in (0, 0.05] m, got {cell_size}")
    xs, ys, (io, jo) = _geometry()
    nx = [max(2, round((b - a) / (cell_size / 2 if i == io else cell_size))) for i, (a, b) in enumerate(pairwise(xs))]
    ny = [max(2, round((b - a) / (cell_size / 2 if j == jo else cell_size))) for j, (a, b) in enumerate(pairwise(ys))]
    return nx, ny


def block_mesh_dict(cell_size: float) -> str:
    """``system/blockMeshDict`` of the box with the obstacle cut out, patches named as in :data:`PATCHES`."""
    xs, ys, hole = _geometry()
    nx, ny = cell_counts(cell_size)
    n_x, n_y = len(xs), len(ys)

    def v(i: int, j: int, k: int) -> int:
        return k * n_x * n_y + j * n_x + i

    vertices = [
        f"    ({xs[i]:.6g} {ys[j]:.6g} {k * DEPTH:.6g})" for k in (0, 1) for j in range(n_y) for i in range(n_x)
    ]
    present = {(i, j) for i in range(n_x - 1) for j in range(n_y - 1)} - {hole}
    blocks, faces = [], {p: [] for p in PATCHES}
    for j in range(n_y - 1):
        for i in range(n_x - 1):
            if (i, j) not in present:
                continue
            corners = (v(i, j, 0), v(i + 1, j, 0), v(i + 1, j + 1, 0), v(i, j + 1, 0))
            hexa = " ".join(str(c) for c in corners + tuple(c + n_x * n_y for c in corners))
            blocks.append(f"    hex ({hexa}) ({nx[i]} {ny[j]} 1) simpleGrading (1 1 1)")
            sides = {
                "x-": ((i - 1, j), [v(i, j, 0), v(i, j, 1), v(i, j + 1, 1), v(i, j + 1, 0)]),
                "x+": ((i + 1, j), [v(i + 1, j + 1, 0), v(i + 1, j + 1, 1), v(i + 1, j, 1), v(i + 1, j, 0)]),
                "y-": ((i, j - 1), [v(i, j, 0), v(i + 1, j, 0), v(i + 1, j, 1), v(i, j, 1)]),
                "y+": ((i, j + 1), [v(i, j + 1, 0), v(i, j + 1, 1), v(i + 1, j + 1, 1), v(i + 1, j + 1, 0)]),
            }
            for side, (neighbour, face) in sides.items():
                if neighbour in present:
                    continue
                if neighbour == hole or side == "y-":
                    patch = "lowerWall"  # the floor and the obstacle's three faces
                elif side == "y+":
                    patch = "atmosphere"
                else:
                    patch = "leftWall" if neighbour[0] < 0 else "rightWall"
                faces[patch].append("            (" + " ".join(map(str, face)) + ")")
    patches = {patch: ("patch" if patch == "atmosphere" else "wall", faces[patch]) for patch in PATCHES}
    return of.block_mesh_dict(vertices, blocks, [], patches)


def check_settings(settings: Mapping[str, Any]) -> None:
    """Raise a ValueError naming the setting that cannot give a valid run."""
    if not (float(settings["frame_dt"]) > 0 and int(settings["n_frames"]) >= 1 and 0 < float(settings["max_co"]) <= 5):
        raise ValueError(f"need frame_dt > 0, n_frames >= 1 and 0 < max_co <= 5, got {settings}")
    cell_counts(float(settings["cell_size"]))


def case_files(nu_water: float, settings: Mapping[str, Any]) -> dict[str, str]:
    """Every file of an interFoam dambreak case with water viscosity ``nu_water`` (m^2/s)."""
    nu_water = float(nu_water)
    if not (np.isfinite(nu_water) and nu_water > 0):
        raise ValueError(f"the water viscosity nu_w must be finite and > 0 m^2/s, got {nu_water}")
    frame_dt, n_frames = float(settings["frame_dt"]), int(settings["n_frames"])
    max_co = f"{float(settings['max_co']):.6g}"
    return {
        "system/blockMeshDict": block_mesh_dict(float(settings["cell_size"])),
        "system/controlDict": of.render(
            "dambreak/system/controlDict",
            end=f"{frame_dt * n_frames:.10g}",
            interval=f"{frame_dt:.10g}",
            max_co=max_co,
            max_delta_t=f"{frame_dt:.10g}",
        ),
        "system/fvSchemes": of.render("dambreak/system/fvSchemes"),
        "system/fvSolution": of.render("dambreak/system/fvSolution"),
        "system/setFieldsDict": of.render(
            "dambreak/system/setFieldsDict",
            column_width=f"{WATER_COLUMN[0]:.6g}",
            column_height=f"{WATER_COLUMN[1]:.6g}",
        ),
        "constant/g": of.render("dambreak/constant/g", g_y=f"{-GRAVITY:.6g}"),
        "constant/turbulenceProperties": of.render("shared/constant/turbulenceProperties"),
        "constant/transportProperties": of.render(
            "dambreak/constant/transportProperties",
            nu_water=f"{nu_water:.17g}",
            rho_water=f"{RHO_WATER:g}",
            nu_air=f"{NU_AIR:g}",
            rho_air=f"{RHO_AIR:g}",
            sigma=f"{SIGMA:g}",
        ),
        "0/U": of.render("dambreak/0/U"),
        "0/p_rgh": of.render("dambreak/0/p_rgh"),
        "0/alpha.water": of.render("dambreak/0/alpha.water"),
    }


def surge_front(cell_centres: np.ndarray, alpha: np.ndarray, threshold: float = 0.5) -> float:
    """Surge-front position on the floor (m): where alpha.water first drops below ``threshold``, going right
    from the left wall along the cells of the lowest row, linearly interpolated between cell centres."""
    y = cell_centres[:, 1]
    row = np.flatnonzero(np.isclose(y, y.min(), rtol=0, atol=1e-9))
    row = row[np.argsort(cell_centres[row, 0])]
    x, a = cell_centres[row, 0], alpha[row]
    below = np.flatnonzero(a < threshold)
    if below.size == 0:
        return float(x[-1])
    k = int(below[0])
    if k == 0:
        return float(x[0])
    # Crossing between cell k-1 (wet) and k (dry).
    return float(x[k - 1] + (a[k - 1] - threshold) / (a[k - 1] - a[k]) * (x[k] - x[k - 1]))


def water_outflow(case_dir: Path, times: np.ndarray) -> np.ndarray:
    """Cumulative volume of water (m^3) that left through the open top by each of ``times``.

    Sums dt_n * sum(alphaPhi0.water) over the atmosphere patch, step by step, as interFoam's explicit
    alpha update does, so initial volume = volume inside + outflow holds to the solver's tolerance.
    """
    table = np.loadtxt(Path(case_dir) / "postProcessing" / "atmosphereOutflow" / "0" / "surfaceFieldValue.dat", ndmin=2)
    t, flux = table[:, 0], table[:, 1]
    cumulative = np.cumsum(flux * np.diff(t, prepend=0.0))
    k = np.searchsorted(t, np.asarray(times) - 1e-9)
    if np.any(k >= t.size) or np.any(np.abs(t[np.minimum(k, t.size - 1)] - times) > 1e-6):
        raise of.OpenFOAMError(f"the outflow record in {case_dir} does not reach every frame time")
    return cumulative[k]


def simulate(
    nu_water: float, case_dir: Path, settings: Mapping[str, Any], resampler: of.Resampler
) -> dict[str, np.ndarray]:
    """One interFoam run, returning arrays for the run cache.

    ``fields`` (n_t, 5, 64, 64) float32 on the benchmark grid at t = frame_dt, 2 frame_dt, ...;
    ``water_volume`` (n_t + 1,) m^3 inside the box, the initial volume first; ``water_outflow`` (n_t,)
    m^3 that left through the top by each frame; ``surge_front`` (n_t,) m along the floor.
    """
    from fluidfoam import readscalar

    of.write_case(case_dir, case_files(nu_water, settings))
    of.run_tool(case_dir, "blockMesh")
    of.run_tool(case_dir, "setFields")
    log = of.run_tool(case_dir, "interFoam")
    n_frames, frame_dt = int(settings["n_frames"]), float(settings["frame_dt"])
    times = frame_dt * np.arange(1, n_frames + 1)
    cells = of.read_frames(case_dir, of.select_times(case_dir, times), CHANNEL_FIELDS)
    mesh = resampler.mesh  # built from the same blockMeshDict: the same cells in the same order
    if cells.shape[-1] != mesh.n_cells:
        raise of.OpenFOAMError(f"{case_dir} has {cells.shape[-1]} cells, the resampler's mesh {mesh.n_cells}")
    alpha0 = np.asarray(readscalar(str(case_dir), "0", "alpha.water", verbose=False), dtype=np.float64)
    alpha = cells[:, 4]
    return {
        "fields": resampler(cells).astype(np.float32),
        "water_volume": np.concatenate([[alpha0 @ mesh.cell_volumes], alpha @ mesh.cell_volumes]),
        "water_outflow": water_outflow(case_dir, times),
        "surge_front": np.array([surge_front(mesh.cell_centres, a) for a in alpha]),
        "build": np.array(of.solver_build(log) or ""),
    }


def _describe(conf: Mapping[str, Any]) -> dict[str, Any]:
    """The dambreak's own entries of the file's generator metadata."""
    nx, ny = cell_counts(float(conf["cell_size"]))
    return {
        "mesh_counts": {"x": nx, "y": ny},
        "water_column": list(WATER_COLUMN),
        "rho_water": RHO_WATER, "rho_air": RHO_AIR, "nu_air": NU_AIR, "sigma": SIGMA, "g": GRAVITY,
        "resampling": "linear on a Delaunay triangulation of cell and boundary-face centres; obstacle cells 0",
        "depth": DEPTH,
        "extras": {"water_volume": "m^3 in the box (depth DEPTH), initial then at every frame",
                   "water_outflow": "m^3 that left through the open top by every frame",
                   "surge_front": "m, where alpha.water crosses 0.5 on the floor row of the solver mesh"},
    }  # fmt: skip


#: The dambreak benchmark's generator: ``generate_dambreak(DAMBREAK, preset, seed=..., workdir=..., ...)``.
generate_dambreak = of.SweepGenerator(
    name="dambreak",
    module=__name__,
    version=GENERATOR_VERSION,
    solver="OpenFOAM interFoam (laminar, VOF with MULES)",
    tools=("blockMesh", "setFields", "interFoam", "postProcess"),
    presets=PRESETS,
    check_settings=check_settings,
    case_files=case_files,
    mesh_param=1e-6,
    boundary_values=BOUNDARY_VALUES,
    simulate=simulate,
    extras=("water_volume", "water_outflow", "surge_front"),
    first_frame=1,
    describe=_describe,
)
preset_settings = generate_dambreak.preset_settings
build_resampler = generate_dambreak.build_resampler
