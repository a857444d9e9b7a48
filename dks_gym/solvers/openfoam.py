"""Running OpenFOAM for the dks-gym benchmarks: checks, case files, a resumable pool of runs, resampling.

The CFD benchmarks (cylinder, dambreak) run one OpenFOAM case per parameter value. This module holds
everything those runs share, independent of the physics:

* :func:`check_openfoam` finds the solvers and says how to install them when they are missing;
  :func:`foam_env` is the environment they run in (Debian's ``openfoam`` package only needs
  ``WM_PROJECT_DIR``; its ``etc/bashrc`` is never sourced).
* :func:`render` fills in a case-file template (``templates/``: every dictionary of the two cases as it
  is written, with ``$name`` placeholders), :func:`block_mesh_dict` the one for a block mesh;
  :func:`write_case` writes a case's files (atomically); :func:`run_tool` runs one utility or solver
  with its log in the case directory and raises :class:`OpenFOAMError` quoting the log on failure.
* :func:`read_mesh` / :func:`read_frames` read cell centres, volumes, boundary faces and fields with
  fluidfoam (binary or ascii output).
* :class:`Resampler` maps cell values to the benchmark's uniform grid: piecewise-linear interpolation on
  a Delaunay triangulation of the cell centres plus the boundary-face centres, whose weights are
  computed once per mesh and then applied to every frame of every run as a sparse matrix.
* :func:`run_all` runs the cases through any :class:`concurrent.futures.Executor` (a process pool by
  default, ``dask.distributed.Client.get_executor()`` for a cluster), caches each run's resampled
  result as ``.npz`` under the work directory (a rerun skips finished runs; a killed run leaves no
  partial file), keeps the case directory and its logs of a failed run and reports every failure at
  the end with a tqdm progress bar over runs meanwhile.
* :class:`SweepGenerator` is the data generator both CFD benchmarks share: a sweep of the benchmark's
  parameter, one cached run per value, streamed to the dataset layer; each case module gives it its
  case files, its solver run and its metadata.
"""

from __future__ import annotations

import concurrent.futures as cf
import hashlib
import json
import os
import re
import shutil
import string
import subprocess
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from scipy import sparse
from scipy.spatial import Delaunay, cKDTree

from ..atomic import atomic_path, atomic_write_text
from ..benchmarks.base import Benchmark, GeneratedData, GeneratorUnavailable, check_preset, interleaved_sweep

#: Where Debian's ``openfoam`` package installs its data files; override with ``$WM_PROJECT_DIR``.
DEFAULT_PROJECT_DIR = "/usr/share/openfoam"
#: The executables the dks-gym CFD generators call.
TOOLS = ("blockMesh", "setFields", "interFoam", "pimpleFoam", "foamDictionary", "postProcess")
INSTALL_HINT = (
    "install OpenFOAM so that blockMesh, setFields, interFoam, pimpleFoam, foamDictionary and postProcess "
    "are on PATH: on Debian or Ubuntu run `apt-get install -y openfoam` (v1912 is the tested version; "
    "no bashrc needs sourcing), elsewhere see https://www.openfoam.com/download"
)
#: A value in a boundary specification meaning "take the value of the face's owner cell" (zero gradient).
OWNER = None


class OpenFOAMMissing(GeneratorUnavailable):
    """OpenFOAM's executables are not on PATH; the message says how to install them."""


class OpenFOAMError(RuntimeError):
    """An OpenFOAM utility or solver failed; the message names the case and quotes its log."""


# Environment --------------------------------------------------------------------------------------------


def find_tools(tools: Sequence[str] = TOOLS) -> dict[str, str | None]:
    """Path of every tool in ``tools`` on PATH, None where missing."""
    return {tool: shutil.which(tool) for tool in tools}


def check_openfoam(tools: Sequence[str] = TOOLS) -> None:
    """Raise :class:`OpenFOAMMissing` naming the missing tools and how to install them."""
    missing = [tool for tool, path in find_tools(tools).items() if path is None]
    if missing:
        raise OpenFOAMMissing(f"OpenFOAM is not installed (missing {', '.join(missing)}); {INSTALL_HINT}")


def foam_env() -> dict[str, str]:
    """Environment for OpenFOAM processes: ``WM_PROJECT_DIR`` set, one thread, no colour codes."""
    env = dict(os.environ)
    env.setdefault("WM_PROJECT_DIR", DEFAULT_PROJECT_DIR)
    env["OMP_NUM_THREADS"] = "1"
    # Floating-point exceptions abort the run instead of propagating NaNs into the data.
    env.setdefault("FOAM_SIGFPE", "true")
    return env


def doctor() -> dict[str, str | None]:
    """What the CFD generators need and where it is: each tool's path, OpenFOAM's version, fluidfoam's."""
    report: dict[str, str | None] = dict(find_tools())
    report["OpenFOAM version"] = openfoam_version()
    report["WM_PROJECT_DIR"] = foam_env()["WM_PROJECT_DIR"]
    try:
        import fluidfoam

        report["fluidfoam"] = getattr(fluidfoam, "__version__", "installed")
    except ImportError:
        report["fluidfoam"] = None
    return report


def openfoam_version() -> str | None:
    """OpenFOAM's version string as its tools report it (e.g. ``"OpenFOAM v1912 patch=200626"``), or None."""
    if shutil.which("foamDictionary") is None:
        return None
    try:
        out = subprocess.run(
            ["foamDictionary", "-help-full"], capture_output=True, text=True, env=foam_env(), timeout=30, check=False
        ).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    version = re.search(r"Using:\s*OpenFOAM\S*\s*\((\w+)\)", out)
    patch = re.search(r"Build:\s*\((patch=\w+)\)", out)
    if version is None:
        return None
    return f"OpenFOAM v{version.group(1)}" + (f" {patch.group(1)}" if patch else "")


# Case files ---------------------------------------------------------------------------------------------

def render(template: str, **values: str) -> str:
    """The case file ``templates/<template>`` (e.g. ``"cylinder/system/controlDict"``) with every ``$name``
    placeholder replaced by ``values[name]``; the values must match the placeholders exactly."""
    node = resources.files(__package__) / "templates"
    for part in template.split("/"):
        node = node / part
    text = node.read_text(encoding="utf-8")
    pattern = string.Template.pattern
    wanted = {m.group("named") or m.group("braced") for m in pattern.finditer(text)} - {None}
    if wanted != set(values):
        raise ValueError(
            f"template {template} takes {sorted(wanted)}, got {sorted(values)}: missing "
            f"{sorted(wanted - set(values))}, unknown {sorted(set(values) - wanted)}"
        )
    return string.Template(text).substitute(values)


def block_mesh_dict(
    vertices: Sequence[str],
    blocks: Sequence[str],
    edges: Sequence[str],
    patches: Mapping[str, tuple[str, Sequence[str]]],
) -> str:
    """``system/blockMeshDict`` from its entry lines: vertices, blocks, curved edges (may be empty) and
    ``{patch: (type, face lines)}`` in the order they are written; the front and back are one empty patch."""
    boundary = "\n".join(
        f"    {name}\n    {{\n        type {kind};\n        faces\n        (\n"
        + "\n".join(faces)
        + "\n        );\n    }"
        for name, (kind, faces) in patches.items()
    )
    # The template's edge list ends right after the placeholder, so no edges leave no blank line.
    return render(
        "shared/system/blockMeshDict",
        vertices="\n".join(vertices),
        blocks="\n".join(blocks),
        edges="".join(f"{edge}\n" for edge in edges),
        boundary=boundary,
    )


def write_case(case_dir: Path, files: Mapping[str, str]) -> None:
    """Write ``{case-relative path: text}`` under ``case_dir``, creating directories; each file atomically,
    so a solver never reads a half-written dictionary."""
    for rel, text in files.items():
        target = Path(case_dir) / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(target, text)


def run_tool(case_dir: Path, tool: str, *args: str, log_name: str | None = None, timeout: float | None = None) -> Path:
    """Run ``tool -case case_dir *args`` with its output in ``case_dir/log.<name>``; return the log path.

    Raises :class:`OpenFOAMMissing` if the tool is not installed and :class:`OpenFOAMError` (quoting the
    end of the log) if it exits with an error or runs past ``timeout`` seconds.
    """
    if shutil.which(tool) is None:
        check_openfoam((tool,))
    case_dir = Path(case_dir)
    log = case_dir / f"log.{log_name or tool}"
    with open(log, "w") as out:
        try:
            proc = subprocess.run(
                [tool, "-case", str(case_dir), *args],
                stdout=out,
                stderr=subprocess.STDOUT,
                env={**foam_env(), "PWD": str(case_dir.resolve())},
                cwd=case_dir,
                timeout=timeout,
                check=False,
            )
        except subprocess.TimeoutExpired as exc:
            raise OpenFOAMError(f"{tool} ran past {timeout} s in {case_dir}; see {log}") from exc
    if proc.returncode != 0:
        tail = "".join(log.read_text(errors="replace").splitlines(keepends=True)[-25:])
        raise OpenFOAMError(f"{tool} failed with exit code {proc.returncode} in {case_dir}; log {log} ends:\n{tail}")
    return log


def solver_build(log: Path) -> str | None:
    """The ``Build`` line of an OpenFOAM log header (e.g. ``"OPENFOAM=1912 patch=200626"``)."""
    match = re.search(r"^Build\s*:\s*(.+)$", Path(log).read_text(errors="replace"), flags=re.MULTILINE)
    return match.group(1).strip() if match else None


# Reading ------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MeshGeometry:
    """The 2D geometry of an OpenFOAM mesh as the resampler needs it (x, y only; z is the empty direction).

    ``boundary`` maps each non-empty patch to ``(face_centres (k, 2), owner_cells (k,))``.
    """

    cell_centres: np.ndarray
    cell_volumes: np.ndarray
    boundary: dict[str, tuple[np.ndarray, np.ndarray]]

    @property
    def n_cells(self) -> int:
        return int(self.cell_centres.shape[0])


def read_mesh(case_dir: Path) -> MeshGeometry:
    """Cell centres, cell volumes and boundary faces of the mesh in ``case_dir`` (blockMesh already run).

    Centres and volumes are OpenFOAM's own (``postProcess -func writeCellCentres / writeCellVolumes``),
    so the resampling uses the same geometry as the solver, curved edges included.
    """
    from fluidfoam import readscalar, readvector
    from fluidfoam.readof import OpenFoamFile

    case_dir = Path(case_dir)
    run_tool(case_dir, "postProcess", "-func", "writeCellCentres", "-time", "0", log_name="writeCellCentres")
    run_tool(case_dir, "postProcess", "-func", "writeCellVolumes", "-time", "0", log_name="writeCellVolumes")
    case = str(case_dir)
    centres = np.asarray(readvector(case, "0", "C", verbose=False), dtype=np.float64)[:2].T.copy()
    volumes = np.asarray(readscalar(case, "0", "V", verbose=False), dtype=np.float64)
    mesh_dir = case + "/constant/polyMesh/"
    owner = np.asarray(OpenFoamFile(mesh_dir, name="owner", verbose=False).values, dtype=np.int64)
    patches = OpenFoamFile(mesh_dir, name="boundary", verbose=False).boundaryface
    boundary: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for raw_name, entry in patches.items():
        name = raw_name.decode() if isinstance(raw_name, bytes) else str(raw_name)
        kind = entry.get(b"type", b"").decode() if isinstance(entry.get(b"type", b""), bytes) else ""
        n_faces = int(entry[b"nFaces"])
        if kind == "empty" or n_faces == 0:
            continue
        start = int(entry[b"startFace"])
        faces = np.asarray(readvector(case, "0", "C", boundary=name, verbose=False), dtype=np.float64)
        boundary[name] = (faces.reshape(3, -1)[:2].T.copy(), owner[start : start + n_faces].copy())
    return MeshGeometry(centres, volumes, boundary)


def time_directories(case_dir: Path) -> list[tuple[float, str]]:
    """``(time, directory name)`` of every written time in ``case_dir`` (0 included), sorted by time."""
    out = []
    for entry in Path(case_dir).iterdir():
        if not entry.is_dir():
            continue
        try:
            out.append((float(entry.name), entry.name))
        except ValueError:
            continue
    return sorted(out)


def select_times(case_dir: Path, times: Sequence[float], tol: float = 1e-6) -> list[str]:
    """Directory names of the written times matching ``times`` (within ``tol``); raise if one is missing."""
    written = time_directories(case_dir)
    values = np.array([t for t, _ in written])
    names = []
    for t in times:
        k = int(np.argmin(np.abs(values - t))) if values.size else -1
        if k < 0 or abs(values[k] - t) > tol * max(1.0, abs(t)):
            raise OpenFOAMError(
                f"{case_dir} has no output at t = {t:g} (written: {', '.join(n for _, n in written[:8])}...); "
                "check the solver log for an early stop"
            )
        names.append(written[k][1])
    return names


def read_frames(case_dir: Path, time_names: Sequence[str], fields: Sequence[tuple[str, int | None]]) -> np.ndarray:
    """Cell values (n_t, C, n_cells) float64 of ``fields`` = ``[(file, component or None), ...]``."""
    from fluidfoam import readfield

    case = str(case_dir)
    out = None
    for k, name in enumerate(time_names):
        cache: dict[str, np.ndarray] = {}
        for c, (field, component) in enumerate(fields):
            if field not in cache:
                cache[field] = np.asarray(readfield(case, name, field, verbose=False), dtype=np.float64)
            values = cache[field] if component is None else cache[field][component]
            if out is None:
                out = np.empty((len(time_names), len(fields), values.shape[-1]))
            out[k, c] = values
    if out is None:
        raise ValueError("read_frames needs at least one time and one field")
    return out


# Resampling ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Resampler:
    """Linear map from OpenFOAM cell values to the uniform grid, one sparse matrix and offset per channel.

    ``grid_value[c] = matrices[c] @ cell_value[c] + offsets[c]``; solid grid cells (inside a body or an
    obstacle) get 0 in every channel. Build it with :func:`build_resampler`.
    """

    grid: tuple[int, ...]
    channels: tuple[str, ...]
    matrices: tuple[sparse.csr_matrix, ...]
    offsets: np.ndarray  # (C, n_grid_cells)
    mesh: MeshGeometry

    @property
    def n_cells(self) -> int:
        return self.mesh.n_cells

    def __call__(self, values: np.ndarray) -> np.ndarray:
        """Resample cell values (n_t, C, n_cells) to (n_t, C, *grid) float64."""
        values = np.asarray(values, dtype=np.float64)
        if values.ndim != 3 or values.shape[1:] != (len(self.channels), self.n_cells):
            raise ValueError(
                f"expected cell values of shape (n_t, {len(self.channels)}, {self.n_cells}), got {values.shape}; "
                "was the run's mesh built with the same settings as the resampler's?"
            )
        out = np.empty((values.shape[0], len(self.channels), int(np.prod(self.grid))))
        for c, matrix in enumerate(self.matrices):
            out[:, c] = (matrix @ values[:, c].T).T + self.offsets[c]
        return out.reshape(values.shape[0], len(self.channels), *self.grid)


def build_resampler(
    mesh: MeshGeometry,
    coords: tuple[np.ndarray, np.ndarray],
    solid: np.ndarray,
    channels: Sequence[str],
    boundary_values: Mapping[str, Mapping[str, float | None]],
) -> Resampler:
    """Interpolation weights from ``mesh`` to the grid of cell centres ``coords`` (x, y), computed once.

    The nodes are the cell centres plus the centres of the boundary faces of every patch in
    ``boundary_values``, which maps patch -> channel -> the fixed boundary value, or :data:`OWNER` to
    take the value of the face's owner cell (zero-gradient patches). Including the boundary faces keeps
    grid points near walls and bodies inside the triangulation, and no-slip walls pull the velocity to
    zero there. Grid cells with ``solid`` True are set to 0. A grid point outside every triangle (only
    possible if a patch is left out) takes its nearest node's value.
    """
    channels = tuple(channels)
    missing = [p for p in mesh.boundary if p not in boundary_values]
    if missing:
        raise ValueError(f"boundary_values lacks patch(es) {missing}; give every non-empty patch its values")
    x, y = (np.asarray(c, dtype=np.float64) for c in coords)
    grid = (x.size, y.size)
    solid = np.asarray(solid, dtype=bool)
    if solid.shape != grid:
        raise ValueError(f"solid mask has shape {solid.shape}, expected the grid shape {grid}")
    targets = np.stack([a.ravel() for a in np.meshgrid(x, y, indexing="ij")], axis=1)
    fluid = np.flatnonzero(~solid.ravel())

    patch_names = list(mesh.boundary)
    face_xy = [mesh.boundary[p][0] for p in patch_names]
    face_owner = [mesh.boundary[p][1] for p in patch_names]
    nodes = np.concatenate([mesh.cell_centres, *face_xy])
    n_cells = mesh.n_cells
    n_nodes = nodes.shape[0]
    # Node -> owner cell (cells own themselves) and node -> fixed value per channel (NaN: use the cell).
    node_cell = np.concatenate([np.arange(n_cells), *face_owner])
    node_fixed = np.full((len(channels), n_nodes), np.nan)
    start = n_cells
    for p, xy in zip(patch_names, face_xy):
        spec = boundary_values[p]
        unknown = set(spec) - set(channels)
        if unknown:
            raise ValueError(f"boundary_values[{p!r}] names unknown channel(s) {sorted(unknown)}; channels: {channels}")
        for c, ch in enumerate(channels):
            value = spec.get(ch, OWNER)
            if value is not OWNER:
                node_fixed[c, start : start + len(xy)] = float(value)
        start += len(xy)

    tri = Delaunay(nodes)
    pts = targets[fluid]
    simplex = tri.find_simplex(pts)
    rows, cols, weights = [], [], []
    inside = simplex >= 0
    if np.any(inside):
        s = simplex[inside]
        transform = tri.transform[s]
        bary = np.einsum("nij,nj->ni", transform[:, :2], pts[inside] - transform[:, 2])
        bary = np.concatenate([bary, 1.0 - bary.sum(axis=1, keepdims=True)], axis=1)
        rows.append(np.repeat(fluid[inside], 3))
        cols.append(tri.simplices[s].ravel())
        weights.append(bary.ravel())
    if np.any(~inside):
        _, nearest = cKDTree(nodes).query(pts[~inside])
        rows.append(fluid[~inside])
        cols.append(np.asarray(nearest, dtype=np.int64))
        weights.append(np.ones(int((~inside).sum())))
    rows_a, nodes_a, w_a = np.concatenate(rows), np.concatenate(cols), np.concatenate(weights)
    # Tiny negative barycentric weights come from points on an edge; they are rounding, not extrapolation.
    w_a = np.where(np.abs(w_a) < 1e-12, 0.0, w_a)

    n_grid = targets.shape[0]
    matrices, offsets = [], np.zeros((len(channels), n_grid))
    for c in range(len(channels)):
        fixed = node_fixed[c, nodes_a]
        is_fixed = ~np.isnan(fixed)
        np.add.at(offsets[c], rows_a[is_fixed], w_a[is_fixed] * fixed[is_fixed])
        keep = ~is_fixed
        matrix = sparse.csr_matrix((w_a[keep], (rows_a[keep], node_cell[nodes_a[keep]])), shape=(n_grid, n_cells))
        matrix.sum_duplicates()
        matrices.append(matrix)
    return Resampler(grid=grid, channels=channels, matrices=tuple(matrices), offsets=offsets, mesh=mesh)


# Runs: pool, cache, logs --------------------------------------------------------------------------------


@dataclass(frozen=True)
class Run:
    """One simulation of a sweep: its place in the dataset and its parameter value."""

    split: str
    index: int
    param: float


#: ``simulate(param, case_dir, settings, resampler) -> {"fields": (n_t, C, *grid), other arrays...}``
Simulate = Callable[[float, Path, Mapping[str, Any], Resampler], dict[str, np.ndarray]]


def merge_settings(name: str, defaults: Mapping[str, Any], overrides: Mapping[str, Any] | None) -> dict[str, Any]:
    """A preset's solver settings with ``overrides`` applied; unknown keys are an error naming the known ones."""
    conf = dict(defaults)
    if overrides:
        unknown = set(overrides) - set(conf)
        if unknown:
            raise ValueError(f"unknown {name} setting(s) {sorted(unknown)}; known: {sorted(conf)}")
        conf.update(overrides)
    return conf


def sweep_runs(benchmark: Any, conf: Mapping[str, Any], seed: int) -> tuple[np.ndarray, np.ndarray, list[Run]]:
    """The train and test parameters of a sweep (``interleaved_sweep`` over the benchmark's range with
    ``default_rng(seed)``, ``conf["n_train"]`` / ``conf["n_test"]`` values) and its runs, train first."""
    low, high = benchmark.param_range
    train, test = interleaved_sweep(low, high, int(conf["n_train"]), int(conf["n_test"]), np.random.default_rng(seed))
    runs = [Run("train", i, float(p)) for i, p in enumerate(train)] + [
        Run("test", i, float(p)) for i, p in enumerate(test)
    ]
    return train, test, runs


def run_key(name: str, settings: Mapping[str, Any], param: float) -> str:
    """Cache key of a run: hash of the generator name, its settings and the exact parameter value."""
    payload = json.dumps({"name": name, "settings": settings, "param": float(param).hex()}, sort_keys=True, default=str)
    return hashlib.sha256(payload.encode()).hexdigest()[:16]


def cache_path(workdir: Path, name: str, settings: Mapping[str, Any], run: Run) -> Path:
    """Where the resampled result of ``run`` is cached: ``workdir/runs/<split>-<index>-<key>.npz``."""
    return Path(workdir) / "runs" / f"{run.split}-{run.index:03d}-{run_key(name, settings, run.param)}.npz"


def execute_run(
    simulate: Simulate,
    param: float,
    settings: Mapping[str, Any],
    resampler: Resampler,
    case_dir: str,
    result_path: str,
    keep_case: bool = False,
) -> str:
    """Run one case in a fresh ``case_dir`` and store its result atomically at ``result_path``.

    Executed in the pool's workers. The case directory is removed after success unless ``keep_case``
    and kept, with every log, after a failure.
    """
    case = Path(case_dir)
    shutil.rmtree(case, ignore_errors=True)  # leftovers of an interrupted attempt
    case.mkdir(parents=True)
    start = time.perf_counter()
    try:
        result = simulate(param, case, settings, resampler)
    except Exception as exc:  # noqa: BLE001 - any failure of a run becomes a report naming its case
        raise OpenFOAMError(
            f"run with parameter {param!r} failed; its case and logs are kept in {case}:\n{type(exc).__name__}: {exc}"
        ) from None
    result = {**result, "wall_s": np.array(time.perf_counter() - start)}
    target = Path(result_path)
    target.parent.mkdir(parents=True, exist_ok=True)
    # A run killed before the rename leaves no result, so it is redone.
    with atomic_path(target, suffix=".npz") as tmp:  # np.savez would append .npz to any other name
        np.savez(tmp, **result)
    if not keep_case:
        shutil.rmtree(case, ignore_errors=True)
    return str(target)


def run_all(
    simulate: Simulate,
    runs: Sequence[Run],
    *,
    name: str,
    settings: Mapping[str, Any],
    resampler: Resampler,
    workdir: Path,
    workers: int = 1,
    executor: cf.Executor | None = None,
    progress: bool = True,
    keep_cases: bool = False,
) -> dict[tuple[str, int], Path]:
    """Run every case not yet cached and return ``{(split, index): cached result path}``.

    ``executor`` is any :class:`concurrent.futures.Executor` whose workers see ``workdir`` (a
    ``ProcessPoolExecutor``, or ``dask.distributed.Client.get_executor()`` on a shared file system);
    without one, ``workers`` > 1 starts a process pool of that size and 1 runs the cases in this process.
    Every run is attempted even if some fail; the failures are then raised together, each naming the
    case directory that keeps its logs. Rerunning after an interruption or a failure skips finished runs.
    ``keep_cases`` keeps the OpenFOAM case directories of successful runs too (under ``workdir/cases``).
    """
    if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    if executor is not None and not isinstance(executor, cf.Executor):
        raise TypeError(
            f"executor must be a concurrent.futures.Executor, got {type(executor).__name__}; "
            "for dask use client.get_executor()"
        )
    workdir = Path(workdir)
    paths = {(r.split, r.index): cache_path(workdir, name, settings, r) for r in runs}
    todo = [r for r in runs if not paths[(r.split, r.index)].exists()]
    bar = _progress(len(runs), len(runs) - len(todo), name, progress)
    failures: list[str] = []

    def job_args(r: Run) -> tuple:
        case = workdir / "cases" / f"{r.split}-{r.index:03d}"
        return (simulate, r.param, dict(settings), resampler, str(case), str(paths[(r.split, r.index)]), keep_cases)

    try:
        if executor is None and workers == 1:
            for r in todo:
                try:
                    execute_run(*job_args(r))
                except OpenFOAMError as exc:
                    failures.append(f"{r.split}[{r.index}]: {exc}")
                bar.update(1)
        else:
            own = executor is None
            pool = cf.ProcessPoolExecutor(max_workers=int(workers)) if own else executor
            try:
                futures = {pool.submit(execute_run, *job_args(r)): r for r in todo}
                for future in cf.as_completed(futures):
                    r = futures[future]
                    try:
                        future.result()
                    except Exception as exc:  # noqa: BLE001 - every failure is collected and re-raised below
                        failures.append(f"{r.split}[{r.index}]: {exc}")
                    bar.update(1)
            finally:
                if own:
                    pool.shutdown(wait=True, cancel_futures=True)
    finally:
        bar.close()
    cases = workdir / "cases"
    if cases.is_dir() and not any(cases.iterdir()):
        cases.rmdir()
    if failures:
        raise OpenFOAMError(
            f"{len(failures)} of {len(runs)} {name} runs failed (finished runs are cached in {workdir / 'runs'}; "
            "rerunning the generation redoes only the failed ones):\n" + "\n".join(failures)
        )
    return paths


class _NoBar:
    def update(self, n: int) -> None:
        pass

    def close(self) -> None:
        pass


def _progress(total: int, done: int, name: str, enabled: bool) -> Any:
    if not enabled:
        return _NoBar()
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=done, desc=f"{name} runs", unit="run")


def load_run(path: Path) -> dict[str, np.ndarray]:
    """Every array of a cached run result."""
    with np.load(path) as data:
        return {k: data[k] for k in data.files}


def collect_extras(
    paths: Mapping[tuple[str, int], Path], runs: Sequence[Run], names: Sequence[str]
) -> dict[str, dict[str, np.ndarray]]:
    """``{split: {name: (n_traj, ...) array}}`` of per-run series from the cache, stacked in index order."""
    out: dict[str, dict[str, list[np.ndarray]]] = {}
    for r in sorted(runs, key=lambda r: (r.split, r.index)):
        with np.load(paths[(r.split, r.index)]) as data:
            for name in names:
                out.setdefault(r.split, {}).setdefault(name, []).append(data[name])
    return {split: {k: np.stack(v) for k, v in d.items()} for split, d in out.items()}


def generated_data(
    benchmark: Any,
    time: np.ndarray,
    params: dict[str, np.ndarray],
    paths: Mapping[tuple[str, int], Path],
    runs: Sequence[Run],
    generator: dict[str, Any],
    extras: dict[str, dict[str, np.ndarray]],
    cleanup: Path | None = None,
) -> GeneratedData:
    """The :class:`GeneratedData` of a finished sweep; trajectories stream from the cache in ``runs`` order.

    ``extras`` (``{split: {name: (n_traj, ...)}}``, per-run series such as lift and drag) is stored by the
    dataset layer under ``/{split}/extras/NAME``. ``cleanup`` (a temporary work directory) is removed once
    every trajectory has been read.
    """
    return GeneratedData(
        time=np.asarray(time, dtype=np.float64),
        params=params,
        trajectories=iter_cached(paths, runs, cleanup=cleanup),
        generator=generator,
        coords=benchmark.coords(),
        cell_type=benchmark.cell_type(),
        extras=extras,
    )


def iter_cached(
    paths: Mapping[tuple[str, int], Path], runs: Iterable[Run], key: str = "fields", cleanup: Path | None = None
) -> Iterator[tuple[str, int, np.ndarray]]:
    """Yield ``(split, index, array)`` from the cache in the order of ``runs`` (a fixed order keeps the
    dataset's float64 statistics bit-identical between an interrupted and an uninterrupted generation);
    remove the directory ``cleanup`` afterwards, if given."""
    for r in runs:
        with np.load(paths[(r.split, r.index)]) as data:
            yield r.split, r.index, data[key]
    if cleanup is not None:
        shutil.rmtree(cleanup, ignore_errors=True)


# The generator ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SweepGenerator:
    """The data generator of an OpenFOAM benchmark: one run per parameter value, cached, resampled, streamed.

    A case module (:mod:`~dks_gym.solvers.cylinder_case`, :mod:`~dks_gym.solvers.dambreak_case`) builds
    one from what is its own, and the benchmark names it as its generator entry point. Calling it as
    ``generator(benchmark, preset, ...)`` runs the sweep (see :meth:`__call__`).
    """

    name: str  # the benchmark's name: settings errors, run cache keys, temporary directory
    module: str  # the case module, recorded as the generator's name in the file
    version: str  # the case's GENERATOR_VERSION, recorded in the file
    solver: str  # how the case is solved, recorded in the file
    tools: tuple[str, ...]  # the OpenFOAM executables the runs need
    presets: Mapping[str, Mapping[str, Any]]  # solver settings per preset; every key enters the run cache key
    check_settings: Callable[[Mapping[str, Any]], None]  # raises a ValueError naming a setting that cannot work
    case_files: Callable[[float, Mapping[str, Any]], dict[str, str]]  # case files at a parameter value
    mesh_param: float  # a parameter value to mesh the case at for the resampler (the mesh does not depend on it)
    boundary_values: Mapping[str, Mapping[str, float | None]]  # patch -> channel -> value, see build_resampler
    simulate: Simulate  # one run; a module-level function, so that process pools can pickle it
    extras: tuple[str, ...]  # per-run series of the run results returned as the dataset's extras
    first_frame: int  # the first frame's time in frames: time = frame_dt * (first_frame + arange(n_frames))
    describe: Callable[[Mapping[str, Any]], dict[str, Any]]  # the case's own metadata for the settings

    def preset_settings(self, preset: str) -> dict[str, Any]:
        """The solver settings of ``preset`` ("paper" or "small"), a copy."""
        return dict(self.presets[check_preset(preset)])

    def build_resampler(self, settings: Mapping[str, Any], workdir: Path, benchmark: Benchmark) -> Resampler:
        """Mesh the case once (in ``workdir/mesh``) and compute the interpolation weights to ``benchmark``'s grid."""
        mesh_dir = Path(workdir) / "mesh"
        shutil.rmtree(mesh_dir, ignore_errors=True)
        mesh_dir.mkdir(parents=True)
        write_case(mesh_dir, self.case_files(self.mesh_param, settings))
        run_tool(mesh_dir, "blockMesh")
        mesh = read_mesh(mesh_dir)
        solid = np.isin(benchmark.cell_type(), benchmark.solid_codes)
        return build_resampler(mesh, benchmark.coords(), solid, benchmark.channels, self.boundary_values)

    def __call__(
        self,
        benchmark: Benchmark,
        preset: str = "paper",
        *,
        seed: int = 0,
        workdir: Path | None = None,
        progress: bool = True,
        workers: int = 1,
        executor: cf.Executor | None = None,
        settings: Mapping[str, Any] | None = None,
        keep_cases: bool = False,
        **options: Any,
    ) -> GeneratedData:
        """Run ``benchmark``'s sweep for ``preset`` with OpenFOAM and return it for the dataset layer.

        OpenFOAM must be installed (otherwise :class:`OpenFOAMMissing`, a GeneratorUnavailable, says how).
        The parameter values come from :func:`interleaved_sweep` over the benchmark's range with
        ``default_rng(seed)`` (:func:`sweep_runs`). Runs are cached under ``workdir`` (a temporary
        directory if None), so an interrupted generation resumes; ``workers`` is the size of the process
        pool (1 runs in this process), ``executor`` any :class:`concurrent.futures.Executor` instead
        (e.g. ``dask.distributed.Client.get_executor()``, whose workers must see ``workdir``), as in
        :func:`run_all`. ``settings`` overrides solver settings of the preset (mesh and validation
        studies); ``keep_cases`` keeps every OpenFOAM case directory. The per-run series named by
        :attr:`extras` come back in ``extras`` (``{split: {name: (n_traj, ...)}}``).
        """
        if options:
            raise ValueError(
                f"unknown option(s) for the {benchmark.name} generator: {', '.join(sorted(options))}; "
                "it accepts preset, seed, workdir, progress, workers, executor, settings and keep_cases"
            )
        check_openfoam(self.tools)
        conf = merge_settings(self.name, self.preset_settings(preset), settings)
        self.check_settings(conf)
        train, test, runs = sweep_runs(benchmark, conf, seed)
        temporary = workdir is None
        workdir = Path(tempfile.mkdtemp(prefix=f"dks-{self.name}-")) if temporary else Path(workdir)
        resampler = self.build_resampler(conf, workdir, benchmark)
        paths = run_all(
            self.simulate, runs, name=self.name, settings=conf, resampler=resampler, workdir=workdir,
            workers=workers, executor=executor, progress=progress, keep_cases=keep_cases,
        )  # fmt: skip
        extras = collect_extras(paths, runs, self.extras)
        build = str(load_run(paths[(runs[0].split, runs[0].index)])["build"])
        times = float(conf["frame_dt"]) * np.arange(self.first_frame, self.first_frame + int(conf["n_frames"]))
        generator = {
            "name": self.module,
            "version": self.version,
            "preset": preset,
            "seed": int(seed),
            "solver": self.solver,
            "openfoam_build": build,
            "settings": conf,
            "mesh_cells": resampler.n_cells,
            **self.describe(conf),
        }
        cleanup = workdir if temporary else None
        return generated_data(benchmark, times, {"train": train, "test": test}, paths, runs, generator, extras, cleanup)
