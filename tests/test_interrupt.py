"""SIGTERM, SIGHUP and Ctrl-C in the middle of a write leave no temporary file, in real processes.

Each test starts a Python process that stops at a known point inside a write (it prints ``ready`` and
sleeps), sends it the signal and checks what is left on disk and the exit status: 143 for SIGTERM and 129
for SIGHUP (128 + the signal number); Ctrl-C is Python's KeyboardInterrupt (a script dies of SIGINT, the
dks-gym command prints "Aborted!" and exits 1, as click does).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from dks_gym.interrupt import Terminated, exit_on_signals

pytestmark = pytest.mark.skipif(not hasattr(signal, "SIGHUP"), reason="POSIX signals")

ROOT = Path(__file__).resolve().parents[1]

# The child starts with the dispositions of an interactive shell's foreground job, whatever the test runner
# inherited (under nohup SIGHUP is ignored, in a background job SIGINT may be).
PREAMBLE = """\
import signal, sys, time
from pathlib import Path
signal.signal(signal.SIGTERM, signal.SIG_DFL)
signal.signal(signal.SIGHUP, signal.SIG_DFL)
signal.signal(signal.SIGINT, signal.default_int_handler)
"""

SIGNALS = [signal.SIGTERM, signal.SIGHUP, signal.SIGINT]


def _start(script: str, *args: str, home: Path | None = None) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    if home is not None:
        env["DKS_GYM_HOME"] = str(home)
    return subprocess.Popen([sys.executable, "-c", PREAMBLE + script, *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)


def _interrupt(proc: subprocess.Popen, sig: int, at_ready=None) -> tuple[int, str]:
    """Wait for the child's ``ready`` line, run ``at_ready``, send ``sig``; return (exit status, stderr)."""
    try:
        line = proc.stdout.readline()
        if not line.startswith("ready"):
            proc.kill()
            pytest.fail(f"the child did not get ready: {line!r}\n{proc.communicate(timeout=30)[1][-3000:]}")
        if at_ready is not None:
            at_ready(line.split()[1:])
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return proc.returncode, err


def _expected_status(sig: int, cli: bool) -> int:
    if sig == signal.SIGINT:
        return 1 if cli else -signal.SIGINT
    return 128 + sig


def _leftovers(root: Path) -> list[str]:
    """Temporary files and lock files anywhere below ``root``, except the data home's own lock folder."""
    return sorted(str(p.relative_to(root)) for p in root.rglob("*")
                  if ".tmp-" in p.name or (p.name.endswith(".lock") and p.parent.name != ".locks"))


@pytest.mark.parametrize("sig", SIGNALS, ids=lambda s: signal.Signals(s).name)
def test_signal_inside_atomic_path_removes_the_temporary_file(tmp_path: Path, sig: int) -> None:
    """A library user writing through atomic_path: the old file stays, the temporary one goes."""
    target = tmp_path / "results.json"
    proc = _start("""
from dks_gym.atomic import atomic_path, atomic_write_text
target = Path(sys.argv[1])
atomic_write_text(target, "old")
with atomic_path(target) as tmp:
    tmp.write_text("half")
    print("ready", tmp, flush=True)
    time.sleep(60)
""", str(target), home=tmp_path / "home")

    def check(words: list[str]) -> None:
        assert Path(words[0]).exists() and Path(words[0]).parent == tmp_path

    status, err = _interrupt(proc, sig, check)
    assert status == _expected_status(sig, cli=False), err
    assert [p.name for p in tmp_path.iterdir() if p.name != "home"] == ["results.json"]
    assert target.read_text() == "old"
    if sig != signal.SIGINT:
        assert f"{signal.Signals(sig).name} received: stopping with exit status {128 + sig}" in err


@pytest.mark.parametrize("sig", SIGNALS, ids=lambda s: signal.Signals(s).name)
def test_signal_while_the_cli_writes_a_dataset_leaves_nothing(tmp_path: Path, sig: int) -> None:
    """`dks-gym data generate burgers --preset small` stopped after the first trajectory is in the temporary
    file (the Burgers solve runs lazily, inside the write, which is where a long generation spends its time)."""
    home = tmp_path / "home"
    proc = _start("""
import dks_gym.dataset.writer as writer
write = writer._write

def paced_write(data, bench, tmp, extra_attrs):
    trajectories = data.trajectories

    def paced():
        for n, item in enumerate(trajectories):
            yield item
            if n == 0:  # the first trajectory is in the temporary file
                print("ready", tmp, flush=True)
                time.sleep(60)

    data.trajectories = paced()
    return write(data, bench, tmp, extra_attrs)

writer._write = paced_write
from dks_gym.cli import main
sys.argv = ["dks-gym", "data", "generate", "burgers", "--preset", "small"]
main()
""", home=home)

    def check(words: list[str]) -> None:
        tmp = Path(words[0])
        assert tmp.exists() and tmp.parent == home / "data" and tmp.name.startswith(".burgers-small.h5.tmp-")

    status, err = _interrupt(proc, sig, check)
    assert status == _expected_status(sig, cli=True), err
    assert list((home / "data").iterdir()) == []  # no dataset, no temporary file, no lock file
    assert _leftovers(tmp_path) == []
    assert ("Aborted!" if sig == signal.SIGINT else f"{signal.Signals(sig).name} received") in err


@pytest.mark.parametrize("sig", SIGNALS, ids=lambda s: signal.Signals(s).name)
def test_signal_during_the_solver_runs_keeps_the_work_folder_for_a_resume(tmp_path: Path, sig: int) -> None:
    """A generator that caches its runs (the OpenFOAM benchmarks) stopped before the write: the cache stays,
    so a rerun resumes; no file, no temporary file, no lock beside them."""
    home = tmp_path / "home"
    proc = _start("""
from dks_gym.atomic import atomic_write_text
from dks_gym.benchmarks.burgers import BurgersBenchmark

def generate(self, preset="paper", *, seed=0, workdir=None, progress=True, **options):
    Path(workdir, "runs").mkdir(parents=True)
    atomic_write_text(Path(workdir, "runs", "train-000.txt"), "a finished run")
    print("ready", workdir, flush=True)
    time.sleep(60)

BurgersBenchmark.generate = generate
from dks_gym.cli import main
sys.argv = ["dks-gym", "data", "generate", "burgers", "--preset", "small"]
main()
""", home=home)
    status, err = _interrupt(proc, sig)
    assert status == _expected_status(sig, cli=True), err
    work = home / "data" / "burgers-small.work"
    assert sorted(p.name for p in (home / "data").iterdir()) == ["burgers-small.work"]
    assert (work / "runs" / "train-000.txt").read_text() == "a finished run"
    assert _leftovers(tmp_path) == []


def test_handlers_of_the_program_are_left_alone(tmp_path: Path) -> None:
    """Only default dispositions are replaced: a program's own SIGTERM handler runs, an ignored SIGHUP (nohup)
    stays ignored, and the write completes."""
    target = tmp_path / "out.txt"
    proc = _start("""
from dks_gym.atomic import atomic_path
got = []
signal.signal(signal.SIGTERM, lambda signum, frame: got.append(signum))
signal.signal(signal.SIGHUP, signal.SIG_IGN)
with atomic_path(Path(sys.argv[1])) as tmp:
    tmp.write_text("new")
    print("ready", flush=True)
    for _ in range(6000):
        if got:
            break
        time.sleep(0.01)
assert signal.getsignal(signal.SIGHUP) == signal.SIG_IGN
print("handled", got, flush=True)
""", str(target))

    def hang_up(words: list[str]) -> None:
        proc.send_signal(signal.SIGHUP)  # ignored: the kernel drops it at once

    status, err = _interrupt(proc, signal.SIGTERM, hang_up)
    assert status == 0, err
    assert target.read_text() == "new" and [p.name for p in tmp_path.iterdir()] == ["out.txt"]


def test_guard_installs_over_default_handlers_only_restores_them_and_nests() -> None:
    before = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGHUP)}
    try:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        signal.signal(signal.SIGHUP, signal.SIG_IGN)
        with exit_on_signals() as outer:
            assert set(outer._previous) == {signal.SIGTERM}  # SIGHUP ignored: left alone
            assert signal.getsignal(signal.SIGHUP) == signal.SIG_IGN
            with exit_on_signals() as inner:
                assert inner._previous == {}  # the outer handler is not the default: nothing to do
            assert signal.getsignal(signal.SIGTERM) not in (signal.SIG_DFL, None)
        assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL
        assert signal.getsignal(signal.SIGHUP) == signal.SIG_IGN
        # Outside the main thread no handler can be set: the guard does nothing and says nothing.
        seen = []
        thread = threading.Thread(target=lambda: seen.append(exit_on_signals().__enter__()._previous))
        thread.start()
        thread.join()
        assert seen == [{}]
    finally:
        for s, handler in before.items():
            signal.signal(s, handler)


def test_terminated_is_a_system_exit_with_the_shell_status() -> None:
    exc = Terminated(signal.SIGTERM)
    assert isinstance(exc, SystemExit) and not isinstance(exc, Exception)
    assert exc.code == 143 and exc.signum == signal.SIGTERM
    assert str(exc) == "SIGTERM received: stopping with exit status 143"
    assert Terminated(signal.SIGHUP).code == 129
