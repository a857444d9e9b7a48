"""Running OpenFOAM for the dks-gym benchmarks: checks, case files, a resumable pool of runs, resampling.

The CFD benchmarks (cylinder, dambreak) run one OpenFOAM case per parameter value. This package holds
everything those runs share, independent of the physics, one concern a module:

* :mod:`.tools`: :func:`check_openfoam` finds the solvers and says how to install them when they are
  missing; :func:`foam_env` is the environment they run in; :func:`run_tool` runs one utility or solver
  with its log in the case directory and raises :class:`OpenFOAMError` quoting the log on failure.
* :mod:`.case_files`: :func:`render` fills in a case-file template (``dks_gym/solvers/templates/``),
  :func:`block_mesh_dict` the one for a block mesh; :func:`write_case` writes a case's files (atomically).
* :mod:`.reader`: :func:`read_mesh` / :func:`read_frames` read cell centres, volumes, boundary faces and
  fields with fluidfoam (binary or ascii output).
* :mod:`.resampler`: :class:`Resampler` maps cell values to the benchmark's uniform grid (piecewise-linear
  interpolation on a Delaunay triangulation, weights computed once per mesh, applied as a sparse matrix).
* :mod:`.runs`: :func:`run_all` runs the cases through any :class:`concurrent.futures.Executor` and caches
  each run's resampled result, so that a rerun skips finished runs and a failed run keeps its logs.
* :mod:`.sweep`: :class:`SweepGenerator` is the data generator both CFD benchmarks share: a sweep of the
  benchmark's parameter, one cached run per value, streamed to the dataset layer.

The names below are the runner's API, as the case modules use it (``from . import openfoam as of``).
"""

from .case_files import block_mesh_dict, render, write_case
from .reader import MeshGeometry, read_frames, read_mesh, select_times, time_directories
from .resampler import OWNER, Resampler, build_resampler
from .runs import Run, Simulate, cache_path, collect_extras, execute_run, iter_cached, load_run, run_all, run_key
from .sweep import SweepGenerator, generated_data, merge_settings, sweep_runs
from .tools import (
    DEFAULT_PROJECT_DIR,
    INSTALL_HINT,
    TOOLS,
    OpenFOAMError,
    OpenFOAMMissing,
    check_openfoam,
    doctor,
    find_tools,
    foam_env,
    openfoam_version,
    run_tool,
    solver_build,
)

__all__ = [
    "DEFAULT_PROJECT_DIR",
    "INSTALL_HINT",
    "OWNER",
    "TOOLS",
    "MeshGeometry",
    "OpenFOAMError",
    "OpenFOAMMissing",
    "Resampler",
    "Run",
    "Simulate",
    "SweepGenerator",
    "block_mesh_dict",
    "build_resampler",
    "cache_path",
    "check_openfoam",
    "collect_extras",
    "doctor",
    "execute_run",
    "find_tools",
    "foam_env",
    "generated_data",
    "iter_cached",
    "load_run",
    "merge_settings",
    "openfoam_version",
    "read_frames",
    "read_mesh",
    "render",
    "run_all",
    "run_key",
    "run_tool",
    "select_times",
    "solver_build",
    "sweep_runs",
    "time_directories",
    "write_case",
]
