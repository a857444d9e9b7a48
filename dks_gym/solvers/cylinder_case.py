"""The cylinder benchmark's OpenFOAM case (pimpleFoam) and its generator, :data:`generate_cylinder`.

Geometry (:mod:`dks_gym.benchmarks.cylinder`, paper Section III.B): x in [-8R, 16R], y in [-4R, 4R],
a cylinder of radius R = 1 at the origin; uniform inflow U = 1 at x = -8, p = 0 at the outlet x = 16,
no-slip walls at y = +-4 and on the cylinder. Re = U D / nu with D = 2R, so nu = 2 / Re. Lengths are in
R and times in R/U; u, v are in U and p is the kinematic pressure in U^2.

Mesh (written here by :func:`block_mesh_dict`; the other case files are the templates in
``templates/cylinder``): an O-grid of four blocks between the cylinder and the
square [-2, 2]^2, surrounded by eight rectilinear blocks. ``n_quarter`` cells span each quarter of the
circle and each side of the square (spacing h = 4 / n_quarter around and behind the body); radial
cells grow geometrically from ``wall_cell`` at the surface to about h at the square; upstream and
downstream the cells grow from h to ``3 h`` at the inlet and ``outlet_growth`` h at the outlet, and the
side blocks towards the walls are uniform with spacing h. ``refine`` multiplies every cell count
(and divides ``wall_cell``); the paper preset uses refine 1.15 (7,224 cells), which passes the mesh
study (``validation/cylinder_mesh_study.py``: St and mean drag within 3 % of refine 2.3 at Re 200 and 990;
refine 1 missed it at Re 990) and keeps the 101-run sweep within 45 minutes on 2 cores.

Run: the flow starts impulsively from U = (1, 0) everywhere plus a transverse kick
v = kick exp(-((x - 3)^2 + y^2)) behind the body (kick = 0.5) that breaks the symmetry; pimpleFoam (PISO,
backward Euler, linearUpwind, Courant <= ``max_co``) spins up for ``spin_up`` R/U and then, in steps
of ``spin_up_step``, until the shedding has saturated: the lift's peak-to-peak range over the last two
windows of 20 R/U agrees to 1 % (or the wake is steady), at most ``spin_up_max`` R/U. Periodicity is
thus detected from the lift, not assumed; near the onset of shedding (Re ~ 60 in this channel) the
growth is slow and the cap decides. It then records ``n_frames`` frames every ``frame_dt`` = 0.5 R/U
(binary output), resampled on the 64 x 64 grid (body cells 0); the dataset's time counts from the
first frame and the end of the spin-up is kept per run (``t_start``). The lift and drag coefficients
(forceCoeffs, reference length D and area D x depth, so C = F / (1/2 rho U^2 D) per unit depth) are
kept over the recording window, sampled every ``force_dt``.

:data:`generate_cylinder` (an :class:`~dks_gym.solvers.openfoam.SweepGenerator`) is the benchmark's
generator: ``CYLINDER.generate("paper")`` runs the 90 + 11 runs ("small": 3 + 2) and returns the lift
and drag series and the spin-up length as extras (``{split: {"lift", "drag": (n_traj, n_samples),
"t_start": (n_traj,)}}``, forces sampled every ``force_dt`` from the first frame).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..benchmarks.cylinder import EXTENT, RADIUS
from . import openfoam as of

GENERATOR_VERSION = "1"

DIAMETER = 2.0 * RADIUS
U_INF = 1.0
SQUARE = 2.0  # half side of the square around the O-grid
DEPTH = 1.0
INLET_GROWTH = 3.0  # largest / smallest cell upstream
KICK = {"x": 3.0, "width": 1.0}  # centre and width of the initial transverse kick (amplitude: settings["kick"])

CHANNEL_FIELDS = (("U", 0), ("U", 1), ("p", None))
PATCHES = ("inlet", "outlet", "walls", "cylinder")
_NO_SLIP = {"u": 0.0, "v": 0.0}
BOUNDARY_VALUES = {
    "inlet": {"u": U_INF, "v": 0.0},
    "outlet": {"p": 0.0},
    "walls": _NO_SLIP,
    "cylinder": _NO_SLIP,
}

#: Per-preset settings; every key enters the run cache key, so changing one reruns the affected runs.
PRESETS: dict[str, dict[str, Any]] = {
    "paper": {
        "n_train": 90, "n_test": 11, "n_quarter": 24, "wall_cell": 0.02, "outlet_growth": 2.5, "refine": 1.15,
        "spin_up": 60.0, "spin_up_step": 20.0, "spin_up_max": 400.0, "saturation_window": 20.0,
        "saturation_tol": 0.01, "steady_lift": 1e-3,
        "frame_dt": 0.5, "n_frames": 100, "force_dt": 0.1, "max_co": 0.9, "kick": 0.5, "non_orth_correctors": 0,
    },
    "small": {
        "n_train": 3, "n_test": 2, "n_quarter": 12, "wall_cell": 0.05, "outlet_growth": 2.5, "refine": 1.0,
        "spin_up": 40.0, "spin_up_step": 20.0, "spin_up_max": 40.0, "saturation_window": 20.0,
        "saturation_tol": 0.01, "steady_lift": 1e-3,
        "frame_dt": 0.5, "n_frames": 20, "force_dt": 0.1, "max_co": 0.9, "kick": 0.5, "non_orth_correctors": 0,
    },
}  # fmt: skip


def _graded(length: float, smallest: float, ratio: float) -> int:
    """Number of geometrically graded cells over ``length`` whose smallest cell is at most ``smallest``
    when the largest is ``ratio`` times the smallest."""
    n = 1
    while True:
        q = ratio ** (1.0 / max(n - 1, 1)) if n > 1 else 1.0
        first = length / n if n == 1 or q == 1 else length * (q - 1) / (q**n - 1)
        if first <= smallest or n > 10_000:
            return n
        n += 1


def check_settings(settings: Mapping[str, Any]) -> None:
    """Raise a ValueError naming the setting that cannot give a valid run."""
    spin_up, step, t_max = (float(settings[k]) for k in ("spin_up", "spin_up_step", "spin_up_max"))
    frame_dt = float(settings["frame_dt"])
    if not (spin_up > 0 and step > 0 and t_max >= spin_up):
        raise ValueError(
            f"need spin_up > 0, spin_up_step > 0 and spin_up_max >= spin_up, got {spin_up}, {step}, {t_max}"
        )
    # Every run segment must end on one of its own write times, or OpenFOAM would not write it.
    if abs((t_max - spin_up) / step - round((t_max - spin_up) / step)) > 1e-9:
        raise ValueError(f"spin_up_max - spin_up ({t_max - spin_up:g}) must be a multiple of spin_up_step ({step:g})")
    if frame_dt <= 0 or int(settings["n_frames"]) < 1 or float(settings["force_dt"]) <= 0:
        raise ValueError("frame_dt and force_dt must be > 0 and n_frames >= 1")
    mesh_counts(settings)


def mesh_counts(settings: Mapping[str, Any]) -> dict[str, Any]:
    """Cell counts and gradings of the block mesh for ``settings`` (see the module docstring)."""
    refine = float(settings.get("refine", 1.0))
    n_q = round(int(settings["n_quarter"]) * refine)
    wall = float(settings["wall_cell"]) / refine
    if n_q < 4 or not 0 < wall < 0.5:
        raise ValueError(f"need n_quarter * refine >= 4 and 0 < wall_cell / refine < 0.5, got {n_q}, {wall}")
    h = 2.0 * SQUARE / n_q
    # Radial: geometric from `wall` to about h over the axis length SQUARE - R (q solves the sum).
    length = SQUARE - RADIUS
    q = (length - wall) / (length - h) if h < length else 1.0
    n_r = max(2, round(1 + math.log(max(h / wall, 1.0)) / math.log(q))) if q > 1 else max(2, round(length / h))
    growth = float(settings["outlet_growth"])
    return {
        "n_quarter": n_q,
        "n_radial": n_r,
        "radial_grading": h / wall,
        "n_up": _graded(EXTENT[0][0] * -1 - SQUARE, h, INLET_GROWTH),
        "n_down": _graded(EXTENT[0][1] - SQUARE, h, growth),
        "outlet_grading": growth,
        "n_side": max(2, round((EXTENT[1][1] - SQUARE) / h)),
        "h": h,
        "wall_cell": wall,
    }


def block_mesh_dict(settings: Mapping[str, Any]) -> str:
    """``system/blockMeshDict``: O-grid around the cylinder inside eight rectilinear blocks."""
    m = mesh_counts(settings)
    xs = [EXTENT[0][0], -SQUARE, SQUARE, EXTENT[0][1]]
    ys = [EXTENT[1][0], -SQUARE, SQUARE, EXTENT[1][1]]
    c = RADIUS / math.sqrt(2.0)
    points = [(x, y) for y in ys for x in xs] + [(c, -c), (c, c), (-c, c), (-c, -c)]
    n2 = len(points)
    z0, z1 = -DEPTH / 2, DEPTH / 2
    vertices = [f"    ({x:.10g} {y:.10g} {z:.10g})" for z in (z0, z1) for x, y in points]

    def g(i: int, j: int) -> int:
        return j * 4 + i

    circle = [16, 17, 18, 19]  # 315, 45, 135, 225 degrees
    corners = [g(2, 1), g(2, 2), g(1, 2), g(1, 1)]  # the square's corners at the same angles
    n_q, n_r, e_r = m["n_quarter"], m["n_radial"], m["radial_grading"]
    blocks = []
    for k in range(4):  # right, top, left, bottom quarter: radial first, then counter-clockwise
        a, b = k, (k + 1) % 4
        hexa = [circle[a], corners[a], corners[b], circle[b]]
        hexa += [v + n2 for v in hexa]
        blocks.append(f"    hex ({' '.join(map(str, hexa))}) ({n_r} {n_q} 1) simpleGrading ({e_r:.10g} 1 1)")
    nx = [m["n_up"], n_q, m["n_down"]]
    gx = [1.0 / INLET_GROWTH, 1.0, m["outlet_grading"]]
    ny = [m["n_side"], n_q, m["n_side"]]
    for j in range(3):
        for i in range(3):
            if (i, j) == (1, 1):
                continue
            hexa = [g(i, j), g(i + 1, j), g(i + 1, j + 1), g(i, j + 1)]
            hexa += [v + n2 for v in hexa]
            blocks.append(f"    hex ({' '.join(map(str, hexa))}) ({nx[i]} {ny[j]} 1) simpleGrading ({gx[i]:.10g} 1 1)")
    edges = []
    for k in range(4):
        a, b = circle[k], circle[(k + 1) % 4]
        angle = math.radians(-45 + 90 * k + 45)
        mx, my = RADIUS * math.cos(angle), RADIUS * math.sin(angle)
        for dz, z in ((0, z0), (n2, z1)):
            edges.append(f"    arc {a + dz} {b + dz} ({mx:.10g} {my:.10g} {z:.10g})")

    def quad(a: int, b: int) -> str:
        return f"            ({a} {b} {b + n2} {a + n2})"

    walls = [quad(g(i, 0), g(i + 1, 0)) for i in range(3)] + [quad(g(i + 1, 3), g(i, 3)) for i in range(3)]
    patches = {  # in the order of PATCHES
        "inlet": ("patch", [quad(g(0, j + 1), g(0, j)) for j in range(3)]),
        "outlet": ("patch", [quad(g(3, j), g(3, j + 1)) for j in range(3)]),
        "walls": ("wall", walls),
        "cylinder": ("wall", [quad(circle[(k + 1) % 4], circle[k]) for k in range(4)]),
    }
    return of.block_mesh_dict(vertices, blocks, edges, patches)


def control_dict(settings: Mapping[str, Any], start: str, end: float, interval: float) -> str:
    """``system/controlDict`` of a pimpleFoam run from ``start`` ("startTime" or "latestTime") to ``end``,
    writing every ``interval`` R/U, with the force coefficients on the cylinder every time step."""
    return of.render(
        "cylinder/system/controlDict",
        start=start,
        end=f"{end:.10g}",
        delta_t=f"{0.2 * float(settings['wall_cell']) / float(settings.get('refine', 1.0)):.6g}",
        interval=f"{interval:.10g}",
        max_co=f"{float(settings['max_co']):.6g}",
        max_delta_t=f"{float(settings['frame_dt']):.10g}",
        u_inf=f"{U_INF:g}",
        l_ref=f"{DIAMETER:g}",
        a_ref=f"{DIAMETER * DEPTH:g}",
    )


def initial_velocity(cell_centres: np.ndarray, amplitude: float) -> np.ndarray:
    """U(t=0) = (1, v_kick, 0) with the symmetry-breaking kick v = A exp(-((x - x_k)^2 + y^2) / w^2)."""
    x, y = cell_centres[:, 0], cell_centres[:, 1]
    v = amplitude * np.exp(-((x - KICK["x"]) ** 2 + y**2) / KICK["width"] ** 2)
    return np.stack([np.full_like(x, U_INF), v, np.zeros_like(x)], axis=1)


def case_files(
    reynolds: float, settings: Mapping[str, Any], cell_centres: np.ndarray | None = None
) -> dict[str, str]:
    """Every file of a pimpleFoam cylinder case at Reynolds number ``reynolds`` = U D / nu.

    With ``cell_centres`` None the initial velocity is uniform (enough for meshing only).
    """
    reynolds = float(reynolds)
    if not (math.isfinite(reynolds) and reynolds > 0):
        raise ValueError(f"the Reynolds number must be finite and > 0, got {reynolds}")
    nu = U_INF * DIAMETER / reynolds
    if cell_centres is None:
        internal_u = f"uniform ({U_INF:g} 0 0)"
    else:
        u0 = initial_velocity(cell_centres, float(settings["kick"]))
        internal_u = (
            f"nonuniform List<vector>\n{len(u0)}\n(\n"
            + "\n".join(f"({a:.10g} {b:.10g} {c:.10g})" for a, b, c in u0)
            + "\n)"
        )
    spin_up = float(settings["spin_up"])
    return {
        "system/blockMeshDict": block_mesh_dict(settings),
        "system/controlDict": control_dict(settings, "startTime", spin_up, spin_up),
        "system/fvSchemes": of.render("cylinder/system/fvSchemes"),
        "system/fvSolution": of.render(
            "cylinder/system/fvSolution", non_orth_correctors=str(int(settings["non_orth_correctors"]))
        ),
        "constant/turbulenceProperties": of.render("shared/constant/turbulenceProperties"),
        "constant/transportProperties": of.render("cylinder/constant/transportProperties", nu=f"{nu:.17g}"),
        "0/U": of.render("cylinder/0/U", internal=internal_u, u_inf=f"{U_INF:g}"),
        "0/p": of.render("cylinder/0/p"),
    }


def read_force_coefficients(case_dir: Path) -> dict[str, np.ndarray]:
    """``{"time", "Cd", "Cl"}`` from every forceCoeffs record in ``case_dir`` (restarts concatenated)."""
    root = Path(case_dir) / "postProcessing" / "forceCoeffs"
    starts = sorted((d for d in root.iterdir() if d.is_dir()), key=lambda d: float(d.name)) if root.exists() else []
    chunks = []
    for start in starts:
        for dat in sorted(start.glob("*.dat")):
            header = None
            for line in dat.read_text().splitlines():
                if line.startswith("#") and "Time" in line:
                    header = line.lstrip("#").split()
            if header is None or "Cd" not in header or "Cl" not in header:
                continue
            table = np.loadtxt(dat, comments="#", ndmin=2)
            chunks.append(table[:, [header.index("Time"), header.index("Cd"), header.index("Cl")]])
    if not chunks:
        raise of.OpenFOAMError(f"no force coefficients (Time, Cd, Cl) found under {root}")
    table = np.concatenate(chunks)
    # A restart repeats no step, but keep the last value of any duplicated time to be safe.
    _, keep = np.unique(table[::-1, 0], return_index=True)
    table = table[::-1][keep]
    return {"time": table[:, 0], "Cd": table[:, 1], "Cl": table[:, 2]}


def lift_saturated(time: np.ndarray, lift: np.ndarray, end: float, settings: Mapping[str, Any]) -> bool:
    """Whether the shedding has settled by ``end``: the lift's peak-to-peak range over the last two windows
    of ``saturation_window`` R/U differs by less than ``saturation_tol`` (relative), or the wake is steady
    (range below ``steady_lift``)."""
    width = float(settings["saturation_window"])
    ranges = []
    for lo in (end - 2 * width, end - width):
        inside = (time >= lo) & (time <= lo + width)
        ranges.append(float(np.ptp(lift[inside])) if inside.any() else float("nan"))
    if ranges[1] < float(settings["steady_lift"]):
        return True
    return bool(abs(ranges[1] / ranges[0] - 1.0) < float(settings["saturation_tol"]))


def simulate(
    reynolds: float, case_dir: Path, settings: Mapping[str, Any], resampler: of.Resampler
) -> dict[str, np.ndarray]:
    """One pimpleFoam run, returning arrays for the run cache.

    Spin-up: run to ``spin_up``, then in steps of ``spin_up_step`` until :func:`lift_saturated` or
    ``spin_up_max``; its end t0 is returned as ``t_start``. Then ``fields`` (n_frames, 3, 64, 64)
    float32 at t0 + k frame_dt; ``drag`` and ``lift`` coefficients every ``force_dt`` over the same
    window (``force_time`` counts from t0); ``lift_spin_up`` the lift over the spin-up, for diagnostics.
    """
    mesh = resampler.mesh
    of.write_case(case_dir, case_files(reynolds, settings, mesh.cell_centres))
    of.run_tool(case_dir, "blockMesh")
    t0, step, t_max = float(settings["spin_up"]), float(settings["spin_up_step"]), float(settings["spin_up_max"])
    of.run_tool(case_dir, "pimpleFoam", log_name="pimpleFoam.spin_up")
    k = 0
    while t0 < t_max - 1e-9:
        forces = read_force_coefficients(case_dir)
        if lift_saturated(forces["time"], forces["Cl"], t0, settings):
            break
        k += 1
        t0 = min(t0 + step, t_max)
        of.write_case(case_dir, {"system/controlDict": control_dict(settings, "latestTime", t0, step)})
        of.run_tool(case_dir, "pimpleFoam", log_name=f"pimpleFoam.spin_up{k}")
    frame_dt, n_frames = float(settings["frame_dt"]), int(settings["n_frames"])
    times = t0 + frame_dt * np.arange(n_frames)
    of.write_case(case_dir, {"system/controlDict": control_dict(settings, "latestTime", times[-1], frame_dt)})
    log = of.run_tool(case_dir, "pimpleFoam", log_name="pimpleFoam.record")
    cells = of.read_frames(case_dir, of.select_times(case_dir, times), CHANNEL_FIELDS)
    if cells.shape[-1] != mesh.n_cells:
        raise of.OpenFOAMError(f"{case_dir} has {cells.shape[-1]} cells, the resampler's mesh {mesh.n_cells}")
    forces = read_force_coefficients(case_dir)
    force_dt = float(settings["force_dt"])
    window = np.arange(0.0, times[-1] - t0 + 0.5 * force_dt, force_dt)
    spin = np.arange(0.0, t0 + 0.5 * force_dt, force_dt)
    return {
        "fields": resampler(cells).astype(np.float32),
        "t_start": np.array(t0),
        "force_time": window,
        "drag": np.interp(t0 + window, forces["time"], forces["Cd"]),
        "lift": np.interp(t0 + window, forces["time"], forces["Cl"]),
        "lift_spin_up": np.interp(spin, forces["time"], forces["Cl"]),
        "build": np.array(of.solver_build(log) or ""),
    }


def strouhal(lift: np.ndarray, dt: float) -> float:
    """Strouhal number St = f D / U from a lift series sampled every ``dt`` R/U.

    f is the inverse of the mean period between upward zero crossings of the lift minus its mean
    (linearly interpolated), so the estimate resolves far below the 1/T spacing of an FFT. NaN if
    fewer than two periods are recorded.
    """
    s = np.asarray(lift, dtype=np.float64) - np.mean(lift)
    up = np.flatnonzero((s[:-1] < 0) & (s[1:] >= 0))
    if up.size < 3:
        return float("nan")
    t = (up + s[up] / (s[up] - s[up + 1])) * dt
    period = (t[-1] - t[0]) / (t.size - 1)  # in R/U
    return float(DIAMETER / (U_INF * period))


def _describe(conf: Mapping[str, Any]) -> dict[str, Any]:
    """The cylinder's own entries of the file's generator metadata."""
    return {
        "mesh": mesh_counts(conf),
        "units": "lengths in R, times in R/U, velocity in U, p kinematic in U^2",
        "time_origin": ("time counts from the first recorded frame; extras/t_start is when that was after the "
                        "impulsive start"),
        "initial_kick": {**KICK, "amplitude": float(conf["kick"])},
        "resampling": "linear on a Delaunay triangulation of cell and boundary-face centres; body cells 0",
        "extras": {"lift": "C_l = F_y / (0.5 rho U^2 D) per unit depth, every force_dt from the first frame",
                   "drag": "C_d = F_x / (0.5 rho U^2 D) per unit depth, every force_dt from the first frame",
                   "t_start": "R/U from the impulsive start to the first frame (end of the spin-up)"},
        "force_dt": float(conf["force_dt"]),
    }  # fmt: skip


#: The cylinder benchmark's generator: ``generate_cylinder(CYLINDER, preset, seed=..., workdir=..., ...)``.
generate_cylinder = of.SweepGenerator(
    name="cylinder",
    module=__name__,
    version=GENERATOR_VERSION,
    solver="OpenFOAM pimpleFoam (laminar, PISO, backward Euler, linearUpwind)",
    tools=("blockMesh", "pimpleFoam", "postProcess"),
    presets=PRESETS,
    check_settings=check_settings,
    case_files=case_files,
    mesh_param=100.0,
    boundary_values=BOUNDARY_VALUES,
    simulate=simulate,
    extras=("lift", "drag", "t_start"),
    first_frame=0,
    describe=_describe,
)
preset_settings = generate_cylinder.preset_settings
build_resampler = generate_cylinder.build_resampler
