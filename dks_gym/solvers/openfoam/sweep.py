"""The data generator both CFD benchmarks share: a sweep of the benchmark's parameter, one cached OpenFOAM
run per value, streamed to the dataset layer.

Each case module (:mod:`~dks_gym.solvers.cylinder_case`, :mod:`~dks_gym.solvers.dambreak_case`) gives a
:class:`SweepGenerator` its case files, its solver run and its metadata.
"""

from __future__ import annotations

import concurrent.futures as cf
import shutil
import tempfile
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ...benchmarks.base import Benchmark, GeneratedData, check_preset, interleaved_sweep
from .case_files import write_case
from .reader import read_mesh
from .resampler import Resampler, build_resampler
from .runs import Run, Simulate, collect_extras, iter_cached, load_run, run_all
from .tools import check_openfoam, run_tool


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
