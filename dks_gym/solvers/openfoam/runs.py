"""A resumable pool of OpenFOAM runs: each run's resampled result cached as ``.npz``, read back in order.

:func:`run_all` runs the cases through any :class:`concurrent.futures.Executor` (a process pool by default,
``dask.distributed.Client.get_executor()`` for a cluster), caches each run's result under the work directory
(a rerun skips finished runs; a killed run leaves no partial file), keeps the case directory and its logs of
a failed run and reports every failure at the end, with a tqdm progress bar over runs meanwhile.
"""

from __future__ import annotations

import concurrent.futures as cf
import hashlib
import json
import shutil
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ...atomic import atomic_path
from ...parallel import check_executor
from .resampler import Resampler
from .tools import OpenFOAMError


@dataclass(frozen=True)
class Run:
    """One simulation of a sweep: its place in the dataset and its parameter value."""

    split: str
    index: int
    param: float


#: ``simulate(param, case_dir, settings, resampler) -> {"fields": (n_t, C, *grid), other arrays...}``
Simulate = Callable[[float, Path, Mapping[str, Any], Resampler], dict[str, np.ndarray]]


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
    check_executor(executor)
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
            # Unlike map_tasks (results in order, the first failure stops the rest), every run is attempted and
            # the bar moves as runs finish: each worker caches its own result, so the order does not matter. The
            # own pool forks (open_executor's spawns), so that generate_dataset(workers=N) also runs from a
            # script without a __main__ guard.
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
