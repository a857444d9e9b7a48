"""Atomic file writing: a file appears complete under its name, or not at all.

Every writer of dks-gym (datasets, results, checkpoints, the OpenFOAM case files and run cache) writes
to a temporary name beside the target, flushes it to disk and renames it into place, so a crash, an
error, Ctrl-C, SIGTERM or SIGHUP in the middle never leaves a truncated file that looks valid. The
temporary name is ``.<name>.tmp-<pid>-<random>`` (hidden, unique per process and call; ``.*.tmp-*`` in
.gitignore). An interruption removes it too; only a hard kill (SIGKILL, a power cut) can leave one behind,
and that one never takes the target's name.
"""

from __future__ import annotations

import os
import shutil
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from .interrupt import exit_on_signals


def temporary_name(target: str | Path, suffix: str = "") -> Path:
    """A fresh temporary path beside ``target``: ``.<name>.tmp-<pid>-<8 hex digits><suffix>``."""
    target = Path(target)
    return target.with_name(f".{target.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}{suffix}")


@contextmanager
def atomic_path(target: str | Path, suffix: str = "", *, directory: bool = False) -> Iterator[Path]:
    """Yield a temporary path beside ``target`` to write; on success move it onto ``target`` atomically.

    The body writes the file at the yielded path (with any library: h5py, numpy, safetensors, plain
    ``open``) and closes it. On leaving normally the file is fsynced and renamed over ``target``
    (``os.replace``, atomic on POSIX and Windows). On any exception, KeyboardInterrupt included, the
    temporary file is removed and ``target`` is left as it was. SIGTERM and SIGHUP do the same: while the
    body runs they raise :class:`~dks_gym.interrupt.Terminated` (exit status 128 + signal number), when
    their handler is the default one (:func:`~dks_gym.interrupt.exit_on_signals`). ``suffix`` ends the
    temporary name, for writers that insist on an extension (``np.savez`` appends ``.npz`` otherwise).

    With ``directory=True`` the yielded path is a fresh, empty folder that the body fills (a set of files
    that is only usable whole, e.g. an export in another collection's layout); every file in it is fsynced
    and the folder renamed onto ``target``, which must not exist or be an empty folder.
    """
    target = Path(target)
    with exit_on_signals():
        tmp = temporary_name(target, suffix)
        try:
            if directory:
                tmp.mkdir()
            yield tmp
            # Data first, then the rename: after a power cut the target holds the old or the new file, never
            # a renamed but empty one.
            for path in sorted(p for p in tmp.rglob("*") if p.is_file()) if directory else [tmp]:
                with open(path, "rb") as f:
                    os.fsync(f.fileno())
            os.replace(tmp, target)
        finally:
            if directory:
                shutil.rmtree(tmp, ignore_errors=True)
            else:
                tmp.unlink(missing_ok=True)


def atomic_write_text(target: str | Path, text: str) -> Path:
    """Write ``text`` to ``target`` atomically (see :func:`atomic_path`); return ``target`` as a Path."""
    target = Path(target)
    with atomic_path(target) as tmp:
        tmp.write_text(text)
    return target
