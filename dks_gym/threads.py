"""How many CPU threads torch uses inside dks-gym's heavy calls: chosen per task, overridable.

torch starts with one thread per core. On small CPUs that is a trap for this package's work (batches of
a few hundred kilobytes, one after another): measured side by side with ``python benchmarks/threads.py``
on a 2-core machine (benchmarks/results/threads_cpu*.json), two threads trained 15-28 % faster than one
on an idle machine but 1.8-3.6x slower beside one busy process, and the filter steps gained nothing
(0.85-1.09 idle, 0.83-1.23 beside a busy process; an earlier demo's EKF step went from 14-17 ms to 399 ms
under a test run). So training and data assimilation run on one thread by default; the torch solvers
(large grids) keep torch's own count.

Which count a task gets, first match wins:

1. :func:`set_threads` (the CLI's ``--threads``);
2. the environment variable ``DKS_GYM_THREADS``, then ``OMP_NUM_THREADS`` (the usual one);
3. the task's measured default, :data:`TASK_THREADS`.

:func:`torch_threads` applies it for the duration of a call and restores the previous count afterwards,
so a caller's own ``torch.set_num_threads`` holds outside dks-gym's calls (inside them, use
:func:`set_threads` or ``DKS_GYM_THREADS``).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

#: MKL's strict conditional numerical reproducibility: its matrix products give the same bits whatever the
#: thread count. By default MKL splits a product's rows by thread and sends the remainder rows through
#: another kernel, so one row of a (10 x 64) @ (64 x 32) product differs in its last bit between one thread
#: and two, and a free rollout through an expanding map (the xLSTM's) grows that to a few per mille of its
#: MSE in 100 steps. Strict mode cost no measurable time on a 2-core AMD EPYC (docs/performance.md). MKL reads
#: the variable at its first call, so it is set when dks_gym is imported (``import dks_gym`` before your first
#: torch product); a value of your own is kept.
BLAS_REPRODUCIBILITY = ("MKL_CBWR", "AUTO,STRICT")
os.environ.setdefault(*BLAS_REPRODUCIBILITY)

#: Per task, the torch thread count used when nothing overrides it; None keeps torch's own count.
TASK_THREADS: dict[str, int | None] = {
    "train": 1,  # Adam steps of the latent models
    "assimilate": 1,  # forecast / update / decode / score of the EKF, EnKF and forward runs
    "simulate": None,  # the batched torch solvers (Burgers, lattice Boltzmann): large arrays, all cores
}
ENV_VARS = ("DKS_GYM_THREADS", "OMP_NUM_THREADS")

_override: int | None = None


def set_threads(n: int | None) -> None:
    """Use ``n`` torch threads in every dks-gym task from now on (None: back to the defaults)."""
    global _override
    if n is not None and (not isinstance(n, int) or isinstance(n, bool) or n < 1):
        raise ValueError(f"the thread count must be a positive integer or None, got {n!r}")
    _override = n


def thread_override() -> int | None:
    """The count :func:`set_threads` fixed, or None (a worker of :mod:`dks_gym.parallel` gets the caller's)."""
    return _override


def threads_for(task: str) -> int | None:
    """The torch thread count ``task`` runs with (None: torch's current count); see the module docstring."""
    if task not in TASK_THREADS:
        raise ValueError(f"unknown task {task!r}; choose one of {', '.join(TASK_THREADS)}")
    if _override is not None:
        return _override
    for var in ENV_VARS:
        value = os.environ.get(var, "").strip()
        if value:
            try:
                n = int(value)
            except ValueError:
                raise ValueError(f"{var}={value!r} is not a thread count; set it to a positive integer "
                                 f"or unset it") from None
            if n < 1:
                raise ValueError(f"{var}={value!r}: the thread count must be at least 1")
            return n
    return TASK_THREADS[task]


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """Run the body with numpy's and scipy's BLAS and LAPACK (the OpenBLAS they bundle, or an MKL) on one
    thread, then restore their counts.

    MKL's strict mode (above) pins torch's products, not these libraries: OpenBLAS splits a product's sums by
    thread. Where a solve is ill-conditioned that shows: the pDMD interpolant of the dambreak's 90
    viscosities moved by up to 5e-4 of its largest coefficient between one BLAS thread and two, and its
    EnKF's final coverage from 0.78 to 0.85 (``dks-gym expected dambreak --check`` under
    ``OMP_NUM_THREADS=2``). That algebra is small: on one thread the dambreak's pDMD fit and its 11 test
    operators took 126 ms against 139 ms on two. Entering the context takes about 0.3 ms, so it wraps work
    that is cached, not every filter step.
    """
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        yield


@contextmanager
def torch_threads(task: str) -> Iterator[None]:
    """Run the body with :func:`threads_for` ``(task)`` torch threads, then restore the previous count."""
    import torch

    n = threads_for(task)
    previous = torch.get_num_threads()
    if n is None or n == previous:  # nothing to change (set_num_threads costs ~65 us)
        yield
        return
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(previous)
