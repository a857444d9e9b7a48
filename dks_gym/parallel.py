"""Independent tasks spread over an optional executor: one after the other in this process by default, on a
pool of local worker processes or on a Dask cluster when given one.

:func:`map_tasks` is the one way dks-gym spreads independent work: ``dks-gym reproduce``'s trainings and
filter runs, ``dks-gym evaluate-placement``'s policy fits and runs. It calls ``fn(*args)`` for every task and
yields the results in the order of the tasks, whatever order the workers finish them in, so that everything
the caller writes from them is the same, byte for byte, as in a serial run. The rules that keep it so:

* a task is a module-level function with picklable arguments (a :class:`~dks_gym.dataset.Dataset` travels as
  its path and is reopened by the worker, a model as its weights), seeded like everything in dks-gym;
* a task computes and returns; the caller alone writes results and tables (:mod:`dks_gym.atomic`), after
  each result in order, so an interrupted run keeps what it finished. Only trainings write in the workers,
  their checkpoints, under the checkpoint's lock (:mod:`dks_gym.locks`), so two never write one file;
* every task runs with the caller's data home (``DKS_GYM_HOME``) and torch thread count
  (:func:`~dks_gym.threads.set_threads`), whatever the worker was started with; the data home's path must
  exist on the worker (the same machine, or a shared file system);
* the tasks of one worker process run one at a time, whatever its thread count: a training seeds torch's
  global random generator, which two tasks at once would share. A Dask worker should have one thread and
  the cluster more processes (``dask worker ADDRESS --nworkers N --nthreads 1``).

:func:`open_executor` makes the executor of the command-line options: ``--scheduler ADDRESS`` connects to a
running Dask scheduler (``distributed.Client(ADDRESS).get_executor()``, the ``cluster`` extra) and
``--workers N`` starts N local worker processes (a process pool, as ``dks-gym data generate --workers``).
"""

from __future__ import annotations

import concurrent.futures as cf
import os
import pickle
import threading
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

from .home import data_home
from .threads import set_threads, thread_override

R = TypeVar("R")

F = TypeVar("F", bound=Callable[..., Any])


def executor_options(work: str) -> Callable[[F], F]:
    """Decorator: the options ``--scheduler ADDRESS`` and ``--workers N`` of a click command that spreads
    ``work`` (e.g. "the independent trainings and filter runs"); the command opens them with
    :func:`open_executor`."""
    import click

    def decorate(command: F) -> F:
        command = click.option(
            "--workers", type=click.IntRange(min=1), default=None, metavar="N",
            help=f"Run {work} on N local worker processes (default: one after the other in this process).")(command)
        return click.option(
            "--scheduler", default=None, metavar="ADDRESS",
            help=f"Run {work} on the Dask cluster of this scheduler (e.g. tcp://host:8786; pip install "
                 "'dks-gym[cluster]'); its workers must see DKS_GYM_HOME's path.")(command)

    return decorate


def map_tasks(fn: Callable[..., R], tasks: Iterable[tuple], executor: cf.Executor | None = None) -> Iterator[R]:
    """``fn(*args)`` for every ``args`` of ``tasks``, yielded in the order of ``tasks``.

    Without ``executor`` each task runs in this process when its result is asked for. With one (any
    :class:`concurrent.futures.Executor`: ``distributed.Client.get_executor()``, a process pool), every task
    is submitted at once, in the caller's data home and thread count (see the module docstring); a task's
    exception is raised when its result is reached, and the tasks not yet run are then cancelled.
    """
    if executor is None:
        return (fn(*args) for args in tasks)
    check_executor(executor)
    context = (str(data_home()), thread_override())
    return _in_order([executor.submit(_in_context, _packed(fn, (context, fn, args))) for args in tasks])


def check_executor(executor: Any) -> None:
    """Raise TypeError unless ``executor`` is a :class:`concurrent.futures.Executor` (or None)."""
    if executor is not None and not isinstance(executor, cf.Executor):
        raise TypeError(f"executor must be a concurrent.futures.Executor, got {type(executor).__name__}; for Dask "
                        "pass client.get_executor()")


def _packed(fn: Callable, payload: Any, what: str = "a task") -> bytes:
    """``payload`` pickled here, with the standard pickler. The executor then moves plain bytes: a process pool's
    own pickler would move every tensor of a model to shared memory in place, which frees the memory of
    any numpy view of it (a fitted PyDMD's arrays) in this process."""
    try:
        return pickle.dumps(payload, protocol=pickle.HIGHEST_PROTOCOL)
    except (pickle.PicklingError, AttributeError, TypeError) as exc:
        raise TypeError(f"{what} of {getattr(fn, '__qualname__', fn)!r} cannot be pickled ({exc}): a task "
                        "is a module-level function of picklable arguments; define classes and functions at a "
                        "module's top level, or run without an executor") from exc


def _in_order(futures: list[cf.Future]) -> Iterator[Any]:
    try:
        for future in futures:
            yield pickle.loads(future.result())
    finally:  # an error, an interruption or a caller that stops early: nothing more is computed
        for future in futures:
            future.cancel()


#: Held by the task a worker process runs: the tasks of one process run one after the other, whatever the
#: worker's thread count, because they set process-wide state (a training seeds torch's global random
#: generator; the data home and the thread count are the process's), which two at once would mix.
_ONE_AT_A_TIME = threading.Lock()


def _in_context(payload: bytes) -> bytes:
    """Run a packed task in a worker with the caller's data home and torch thread count (then restore the
    worker's), one task per process at a time; return its result pickled (see :func:`_packed`)."""
    (home, threads), fn, args = pickle.loads(payload)
    with _ONE_AT_A_TIME:
        previous_home, previous_threads = os.environ.get("DKS_GYM_HOME"), thread_override()
        os.environ["DKS_GYM_HOME"] = home
        set_threads(threads)
        try:
            return _packed(fn, fn(*args), "the result")
        finally:
            set_threads(previous_threads)
            if previous_home is None:
                os.environ.pop("DKS_GYM_HOME", None)
            else:
                os.environ["DKS_GYM_HOME"] = previous_home


@contextmanager
def open_executor(scheduler: str | None = None, workers: int | None = None) -> Iterator[cf.Executor | None]:
    """The executor of the command-line options ``--scheduler ADDRESS`` or ``--workers N``, closed on leaving.

    None (serial, in this process) when neither is given or ``workers`` is 1. ``scheduler``: a client of the
    running Dask scheduler at that address (``dask scheduler``, with ``dask worker ADDRESS`` on each
    machine). ``workers``: a pool of N local processes, started fresh (``spawn``) so that they do not inherit
    this process's torch state.
    """
    if scheduler is not None and workers is not None:
        raise ValueError("give --scheduler (a Dask cluster) or --workers (local processes), not both")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    if scheduler is not None:
        with _dask_client(scheduler) as client:
            executor = client.get_executor(pure=False)  # pure=False: no hashing of the arguments (models, data)
            try:
                yield executor
            finally:
                executor.shutdown(wait=False)
    elif workers is not None and workers > 1:
        import multiprocessing

        pool = cf.ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"))
        try:
            yield pool
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
    else:
        yield None


@contextmanager
def _dask_client(address: str) -> Iterator[Any]:
    try:
        from distributed import Client
    except ImportError as exc:
        raise ImportError("--scheduler runs the tasks on a Dask cluster, which needs dask.distributed: "
                          "pip install 'dks-gym[cluster]'") from exc
    try:
        client = Client(address, timeout="20s")
    except OSError as exc:
        raise ValueError(f"cannot reach the Dask scheduler at {address!r} ({exc}); start one with `dask scheduler` "
                         "and its workers with `dask worker ADDRESS`, or leave out --scheduler") from exc
    try:
        yield client
    finally:
        client.close()


__all__ = ["check_executor", "executor_options", "map_tasks", "open_executor"]
