"""Tasks over an executor (dks_gym.parallel): results in the tasks' order, the caller's data home and thread
count in the workers, errors raised in place, tasks that cannot travel refused clearly."""

from __future__ import annotations

import concurrent.futures as cf
import os
import threading
import time

import pytest

from dks_gym.parallel import map_tasks, open_executor
from dks_gym.threads import set_threads, threads_for

def settings_seen() -> tuple[str | None, int | None]:
    """A task: what dks-gym's settings are inside it."""
    return os.environ.get("DKS_GYM_HOME"), threads_for("assimilate")


def finished(tag: str, delay: float) -> tuple[str, float]:
    """A task: its tag and when it finished, ``delay`` seconds after it started."""
    time.sleep(delay)
    return tag, time.monotonic()


def square_or_fail(x: int) -> int:
    if x == 2:
        raise ValueError("two is refused")
    return x * x


class LastFirst(cf.Executor):
    """An executor that runs what was submitted when told to, the last task first."""

    def __init__(self) -> None:
        self.submitted: list[tuple[cf.Future, object, tuple]] = []

    def submit(self, fn, /, *args, **kwargs):
        future = cf.Future()
        self.submitted.append((future, fn, args))
        return future

    def run_backwards(self) -> None:
        for future, fn, args in reversed(self.submitted):
            future.set_result(fn(*args))


def test_results_come_in_the_tasks_order_whatever_finishes_first() -> None:
    executor = LastFirst()
    results = map_tasks(finished, [("first", 0.0), ("second", 0.0)], executor)
    executor.run_backwards()
    (first, t_first), (second, t_second) = results
    assert (first, second) == ("first", "second") and t_second < t_first


def test_tasks_run_with_the_callers_home_and_threads_and_restore_the_workers(tmp_path, monkeypatch) -> None:
    """Submitted in one data home with 3 threads, run after the worker's settings became others (the one worker
    is held until then): the tasks see the caller's, and the worker finds its own again afterwards."""
    gate = threading.Event()
    monkeypatch.setenv("DKS_GYM_HOME", str(tmp_path / "caller"))
    set_threads(3)
    try:
        with cf.ThreadPoolExecutor(1) as pool:
            pool.submit(gate.wait, 10)
            results = map_tasks(settings_seen, [(), ()], pool)
            monkeypatch.setenv("DKS_GYM_HOME", str(tmp_path / "worker"))
            set_threads(None)
            gate.set()
            assert list(results) == [(str(tmp_path / "caller"), 3)] * 2
    finally:
        set_threads(None)
    assert settings_seen() == (str(tmp_path / "worker"), 1)


def test_serial_runs_each_task_when_asked_and_errors_arrive_in_place() -> None:
    lazy = map_tasks(square_or_fail, [(1,), (2,), (3,)])
    assert next(lazy) == 1  # the failing task has not run yet
    with pytest.raises(ValueError, match="two is refused"):
        next(lazy)
    with cf.ThreadPoolExecutor(2) as pool:
        results = map_tasks(square_or_fail, [(1,), (2,), (3,)], pool)
        assert next(results) == 1
        with pytest.raises(ValueError, match="two is refused"):
            next(results)


def test_what_cannot_travel_is_refused_with_the_rule() -> None:
    with cf.ThreadPoolExecutor(1) as pool:
        with pytest.raises(TypeError, match="module-level function of picklable arguments"):
            map_tasks(lambda x: x, [(1,)], pool)
        with pytest.raises(TypeError, match="concurrent.futures.Executor"):
            map_tasks(square_or_fail, [(1,)], object())


def test_the_command_line_options_choose_the_executor() -> None:
    with open_executor() as executor:
        assert executor is None
    with open_executor(workers=1) as executor:
        assert executor is None  # one worker: this process, as without the option
    with pytest.raises(ValueError, match="not both"):
        with open_executor("tcp://127.0.0.1:8786", 2):
            pass
