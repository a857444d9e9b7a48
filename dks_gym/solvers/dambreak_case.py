"""The dambreak benchmark's OpenFOAM case (interFoam) and its generator.

Geometry (the canonical damBreak, :mod:`dks_gym.benchmarks.dambreak`): a 0.584 m square box open at
the top, an obstacle 0.024 m wide and 0.048 m high on the floor at x = 0.292 m, and a water column
0.1461 m wide and 0.292 m high against the left wall, released at t = 0. Air: nu = 1.48e-5 m^2/s,
rho = 1 kg/m^3; water: rho = 1000 kg/m^3 and the swept viscosity nu_w; surface tension 0.07 N/m,
g = 9.81 m/s^2 downwards.

The case is written here from that geometry: a rectilinear block mesh whose block edges lie on the
obstacle and on the water column's edges, so ``setFields`` fills the column exactly (initial water
volume = 0.1461 x 0.292 x depth); cells are about ``cell_size`` wide and half that across the
obstacle and in the floor layer y < 0.048 m, where the surge front travels (``cell_size`` = 0.0127 m is
the tutorial's resolution, 2,368 cells). interFoam runs with an adjustable time step (Courant 1) that
lands exactly on the output times 0.01, 0.02, ... s; binary output is read back with fluidfoam and
resampled on the benchmark's 64 x 64 grid (:class:`~dks_gym.solvers.openfoam.Resampler`; obstacle
cells are 0 in every channel). Each run also records, on the solver's own mesh, the water volume
(integral of alpha.water) and the surge-front position along the floor at every frame, for the
validations in ``benchmarks/dambreak_validation.py``.
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Mapping
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np

from ..benchmarks.base import Benchmark, GeneratedData, check_preset
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


def _benchmark() -> Benchmark:
    from ..benchmarks.dambreak import DAMBREAK

    return DAMBREAK


def _geometry() -> tuple[list[float], list[float], tuple[int, int]]:
    """Block edges in x and y and the (i, j) index of the missing block (the obstacle)."""
    from ..benchmarks.dambreak import BOX, OBSTACLE_HEIGHT, OBSTACLE_X

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
    boundary = []
    for patch in PATCHES:
        kind = "patch" if patch == "atmosphere" else "wall"
        boundary.append(
            f"    {patch}\n    {{\n        type {kind};\n        faces\n        (\n"
            + "\n".join(faces[patch])
            + "\n        );\n    }"
        )
    boundary.append("    frontAndBack\n    {\n        type empty;\n        faces ();\n    }")
    body = (
        "convertToMeters 1;\n\nvertices\n(\n"
        + "\n".join(vertices)
        + "\n);\n\nblocks\n(\n"
        + "\n".join(blocks)
        + "\n);\n\nedges\n(\n);\n\ndefaultPatch\n{\n    name frontAndBack;\n    type empty;\n}\n\nboundary\n(\n"
        + "\n".join(boundary[:-1])
        + "\n);\n\nmergePatchPairs\n(\n);"
    )
    return of.foam_file("system/blockMeshDict", body)


def _field(path: str, cls: str, dims: str, internal: str, patches: Mapping[str, str]) -> str:
    entries = "\n".join(f"    {name}\n    {{\n        {spec}\n    }}" for name, spec in patches.items())
    body = f"dimensions      {dims};\n\ninternalField   {internal};\n\nboundaryField\n{{\n{entries}\n    frontAndBack\n    {{\n        type empty;\n    }}\n}}"
    return of.foam_file(path, body, cls=cls)


def case_files(nu_water: float, settings: Mapping[str, Any]) -> dict[str, str]:
    """Every file of an interFoam dambreak case with water viscosity ``nu_water`` (m^2/s)."""
    nu_water = float(nu_water)
    if not (np.isfinite(nu_water) and nu_water > 0):
        raise ValueError(f"the water viscosity nu_w must be finite and > 0 m^2/s, got {nu_water}")
    frame_dt, n_frames = float(settings["frame_dt"]), int(settings["n_frames"])
    end_time = frame_dt * n_frames
    wall_u = "type noSlip;"
    files = {
        "system/blockMeshDict": block_mesh_dict(float(settings["cell_size"])),
        "system/controlDict": of.foam_file(
            "system/controlDict",
            f"""
application     interFoam;
startFrom       startTime;
startTime       0;
stopAt          endTime;
endTime         {end_time:.10g};
deltaT          1e-4;
writeControl    adjustableRunTime;
writeInterval   {frame_dt:.10g};
purgeWrite      0;
writeFormat     binary;
writePrecision  10;
writeCompression off;
timeFormat      general;
timePrecision   8;
runTimeModifiable false;
adjustTimeStep  yes;
maxCo           {float(settings["max_co"]):.6g};
maxAlphaCo      {float(settings["max_co"]):.6g};
maxDeltaT       {frame_dt:.10g};

functions
{{
    // Water leaving through the open top, every time step: the conservation check accounts for it.
    atmosphereOutflow
    {{
        type            surfaceFieldValue;
        libs            ("libfieldFunctionObjects.so");
        writeControl    timeStep;
        writeInterval   1;
        log             false;
        writeFields     false;
        regionType      patch;
        name            atmosphere;
        operation       sum;
        fields          (alphaPhi0.water);
    }}
}}
""",
        ),
        "system/fvSchemes": of.foam_file(
            "system/fvSchemes",
            """
ddtSchemes { default Euler; }
gradSchemes { default Gauss linear; }
divSchemes
{
    div(rhoPhi,U)   Gauss linearUpwind grad(U);
    div(phi,alpha)  Gauss vanLeer;
    div(phirb,alpha) Gauss linear;
    div(((rho*nuEff)*dev2(T(grad(U))))) Gauss linear;
}
laplacianSchemes { default Gauss linear corrected; }
interpolationSchemes { default linear; }
snGradSchemes { default corrected; }
""",
        ),
        "system/fvSolution": of.foam_file(
            "system/fvSolution",
            """
solvers
{
    "alpha.water.*"
    {
        nAlphaCorr      2;
        nAlphaSubCycles 1;
        cAlpha          1;
        MULESCorr       yes;
        nLimiterIter    5;
        solver          smoothSolver;
        smoother        symGaussSeidel;
        tolerance       1e-8;
        relTol          0;
    }
    "pcorr.*" { solver PCG; preconditioner DIC; tolerance 1e-5; relTol 0; }
    p_rgh { solver PCG; preconditioner DIC; tolerance 1e-7; relTol 0.05; }
    p_rghFinal { solver PCG; preconditioner DIC; tolerance 1e-7; relTol 0; }
    U { solver smoothSolver; smoother symGaussSeidel; tolerance 1e-6; relTol 0; }
}
PIMPLE
{
    momentumPredictor no;
    nOuterCorrectors 1;
    nCorrectors     3;
    nNonOrthogonalCorrectors 0;
}
relaxationFactors { equations { ".*" 1; } }
""",
        ),
        "system/setFieldsDict": of.foam_file(
            "system/setFieldsDict",
            f"""
defaultFieldValues ( volScalarFieldValue alpha.water 0 );
regions
(
    boxToCell
    {{
        box (-1 -1 -1) ({WATER_COLUMN[0]:.6g} {WATER_COLUMN[1]:.6g} 1);
        fieldValues ( volScalarFieldValue alpha.water 1 );
    }}
);
""",
        ),
        "constant/g": of.foam_file(
            "constant/g",
            f"dimensions [0 1 -2 0 0 0 0];\nvalue (0 {-GRAVITY:.6g} 0);",
            cls="uniformDimensionedVectorField",
        ),
        "constant/turbulenceProperties": of.foam_file("constant/turbulenceProperties", "simulationType laminar;"),
        "constant/transportProperties": of.foam_file(
            "constant/transportProperties",
            f"""
phases (water air);
water {{ transportModel Newtonian; nu {nu_water:.17g}; rho {RHO_WATER:g}; }}
air {{ transportModel Newtonian; nu {NU_AIR:g}; rho {RHO_AIR:g}; }}
sigma {SIGMA:g};
""",
        ),
        "0/U": _field(
            "0/U",
            "volVectorField",
            "[0 1 -1 0 0 0 0]",
            "uniform (0 0 0)",
            {
                "leftWall": wall_u,
                "rightWall": wall_u,
                "lowerWall": wall_u,
                "atmosphere": "type pressureInletOutletVelocity;\n        value uniform (0 0 0);",
            },
        ),
        "0/p_rgh": _field(
            "0/p_rgh",
            "volScalarField",
            "[1 -1 -2 0 0 0 0]",
            "uniform 0",
            {
                "leftWall": "type fixedFluxPressure;\n        value uniform 0;",
                "rightWall": "type fixedFluxPressure;\n        value uniform 0;",
                "lowerWall": "type fixedFluxPressure;\n        value uniform 0;",
                "atmosphere": "type totalPressure;\n        p0 uniform 0;",
            },
        ),
        "0/alpha.water": _field(
            "0/alpha.water",
            "volScalarField",
            "[0 0 0 0 0 0 0]",
            "uniform 0",
            {
                "leftWall": "type zeroGradient;",
                "rightWall": "type zeroGradient;",
                "lowerWall": "type zeroGradient;",
                "atmosphere": "type inletOutlet;\n        inletValue uniform 0;\n        value uniform 0;",
            },
        ),
    }
    return files


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


def preset_settings(preset: str) -> dict[str, Any]:
    """The solver settings of ``preset`` ("paper" or "small"), a copy."""
    return dict(PRESETS[check_preset(preset)])


def build_resampler(settings: Mapping[str, Any], workdir: Path, benchmark: Benchmark | None = None) -> of.Resampler:
    """Mesh the case once (in ``workdir/mesh``) and compute the interpolation weights to the benchmark grid."""
    bench = benchmark or _benchmark()
    mesh_dir = Path(workdir) / "mesh"
    shutil.rmtree(mesh_dir, ignore_errors=True)
    mesh_dir.mkdir(parents=True)
    of.write_case(mesh_dir, case_files(1e-6, settings))
    of.run_tool(mesh_dir, "blockMesh")
    mesh = of.read_mesh(mesh_dir)
    solid = np.isin(bench.cell_type(), bench.solid_codes)
    return of.build_resampler(mesh, bench.coords(), solid, bench.channels, BOUNDARY_VALUES)


def generate_dambreak(
    preset: str = "paper",
    seed: int = 0,
    workdir: Path | None = None,
    progress: bool = True,
    *,
    workers: int = 1,
    executor: Any = None,
    benchmark: Benchmark | None = None,
    settings: Mapping[str, Any] | None = None,
    keep_cases: bool = False,
) -> GeneratedData:
    """Run the dambreak sweep for ``preset`` with interFoam and return it for the dataset layer.

    nu_w comes from :func:`interleaved_sweep` over the benchmark range with ``default_rng(seed)``.
    Runs are cached under ``workdir`` (a temporary directory if None), so an interrupted generation
    resumes; ``workers`` / ``executor`` as in :func:`~dks_gym.solvers.openfoam.run_all`. ``settings``
    overrides the preset's solver settings (validation studies); ``keep_cases`` keeps every OpenFOAM
    case directory. The per-run water volume, outflow and surge front are returned in ``extras``.
    """
    of.check_openfoam(("blockMesh", "setFields", "interFoam", "postProcess"))
    bench = benchmark or _benchmark()
    conf = of.merge_settings("dambreak", preset_settings(preset), settings)
    if not (float(conf["frame_dt"]) > 0 and int(conf["n_frames"]) >= 1 and 0 < float(conf["max_co"]) <= 5):
        raise ValueError(f"need frame_dt > 0, n_frames >= 1 and 0 < max_co <= 5, got {conf}")
    cell_counts(float(conf["cell_size"]))
    train, test, runs = of.sweep_runs(bench, conf, seed)
    temporary = workdir is None
    workdir = Path(tempfile.mkdtemp(prefix="dks-dambreak-")) if temporary else Path(workdir)
    resampler = build_resampler(conf, workdir, bench)
    paths = of.run_all(
        simulate, runs, name="dambreak", settings=conf, resampler=resampler, workdir=workdir,
        workers=workers, executor=executor, progress=progress, keep_cases=keep_cases,
    )  # fmt: skip
    extras = of.collect_extras(paths, runs, ("water_volume", "water_outflow", "surge_front"))
    build = str(of.load_run(paths[(runs[0].split, runs[0].index)])["build"])
    time = float(conf["frame_dt"]) * np.arange(1, int(conf["n_frames"]) + 1)
    nx, ny = cell_counts(float(conf["cell_size"]))
    generator = {
        "name": __name__,
        "version": GENERATOR_VERSION,
        "preset": preset,
        "seed": int(seed),
        "solver": "OpenFOAM interFoam (laminar, VOF with MULES)",
        "openfoam_build": build,
        "settings": conf,
        "mesh_cells": resampler.n_cells,
        "mesh_counts": {"x": nx, "y": ny},
        "water_column": list(WATER_COLUMN),
        "rho_water": RHO_WATER, "rho_air": RHO_AIR, "nu_air": NU_AIR, "sigma": SIGMA, "g": GRAVITY,
        "resampling": "linear on a Delaunay triangulation of cell and boundary-face centres; obstacle cells 0",
        "depth": DEPTH,
        "extras": {"water_volume": "m^3 in the box (depth DEPTH), initial then at every frame",
                   "water_outflow": "m^3 that left through the open top by every frame",
                   "surge_front": "m, where alpha.water crosses 0.5 on the floor row of the solver mesh"},
    }  # fmt: skip
    return of.generated_data(
        bench,
        time,
        {"train": train, "test": test},
        paths,
        runs,
        generator,
        extras,
        cleanup=workdir if temporary else None,
    )
