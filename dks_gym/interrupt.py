"""SIGTERM and SIGHUP end a write as cleanly as Ctrl-C does.

Ctrl-C raises ``KeyboardInterrupt``, so the ``finally`` blocks of the writers run: :func:`~dks_gym.atomic.atomic_path`
removes its temporary file, locks are released. SIGTERM (``kill``, ``timeout``, a batch scheduler) and
SIGHUP (a closed terminal) kill a Python process at once by default, and a half-written temporary file stays
behind. :func:`exit_on_signals` turns them into a :class:`Terminated` exception for the duration of a block,
so the same cleanup runs; if nothing catches it, the process exits with status ``128 + signal number`` (143
for SIGTERM, 129 for SIGHUP: what a shell reports for a process killed by that signal).

A handler is installed only in the main thread and only for a signal whose handler is the default
(``SIG_DFL``): a program that handles SIGTERM itself, or runs under ``nohup`` (SIGHUP ignored), keeps its
own behaviour. The previous handlers are restored when the block ends.
"""

from __future__ import annotations

import signal
import sys
import threading
from types import FrameType, TracebackType

#: The signals converted: terminate and hang up (SIGHUP does not exist on Windows).
SIGNALS: tuple[signal.Signals, ...] = tuple(
    getattr(signal, name) for name in ("SIGTERM", "SIGHUP") if hasattr(signal, name)
)


class Terminated(SystemExit):
    """SIGTERM or SIGHUP arrived inside :func:`exit_on_signals`; ``code`` is 128 + ``signum``.

    A ``SystemExit``: ``except Exception`` does not catch it, ``finally`` blocks run, and uncaught it ends the
    process with that exit status and no traceback.
    """

    def __init__(self, signum: int) -> None:
        super().__init__(128 + int(signum))
        self.signum = int(signum)

    def __str__(self) -> str:
        return f"{signal.Signals(self.signum).name} received: stopping with exit status {self.code}"


class exit_on_signals:  # noqa: N801 - used like a function: ``with exit_on_signals(): ...``
    """Context manager: inside it, SIGTERM and SIGHUP raise :class:`Terminated` (see the module docstring).

    Nested uses are free: an inner block finds the outer handler installed and leaves it alone. The handler
    raises once; a repeated signal while the cleanup runs is ignored so that it cannot interrupt it. A signal
    that arrives as the block ends (its work done) is raised again once the previous handler is back, which
    then acts on it as it would have without the block.
    """

    def __init__(self, signals: tuple[int, ...] = SIGNALS) -> None:
        self.signals = signals
        self._previous: dict[int, object] = {}
        self._received: int | None = None
        self._raised = False
        self._closing = False

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self._received is not None:  # the first one is being handled: let its cleanup finish
            return
        self._received = signum
        if not self._closing:
            self._raised = True
            raise Terminated(signum)

    def _restore(self) -> None:
        self._closing = True
        while self._previous:
            signum, handler = self._previous.popitem()
            signal.signal(signum, handler)

    def __enter__(self) -> "exit_on_signals":
        self._previous, self._received, self._raised, self._closing = {}, None, False, False
        if threading.current_thread() is not threading.main_thread():
            return self  # signal handlers can only be set from the main thread; its own handlers apply
        try:
            for signum in self.signals:
                if signal.getsignal(signum) == signal.SIG_DFL:
                    self._previous[signum] = signal.SIG_DFL  # first: a signal right after the next line is undone
                    signal.signal(signum, self._handle)
        except BaseException:
            self._restore()  # the handler raises at most once, so this cannot be interrupted again
            raise
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        try:
            self._closing = True  # from here on a signal is recorded, not raised
        finally:
            self._restore()  # the handler raises at most once: this runs to the end
        if self._raised:
            if isinstance(exc, Terminated):
                print(f"dks-gym: {exc}", file=sys.stderr, flush=True)
        elif self._received is not None:
            signal.raise_signal(self._received)  # arrived as the block ended: the restored handler decides
