"""The file locks of dks-gym's writers, kept out of sight in ``$DKS_GYM_HOME/.locks``.

Writing a dataset, generating one and training a checkpoint each hold an OS file lock on the target, so
two processes never write the same file at once (the second waits). The lock files live in one hidden
folder of the data home, named after the absolute path of the target (symbolic links resolved), so every
process with the same data home uses the same lock for the same file and nothing but the outputs appears
beside them. When the data home cannot be written, the lock goes to a hidden ``.locks`` folder beside the
target instead.

The lock is ``fcntl``/``msvcrt`` based (``filelock.FileLock``): the OS releases it when its holder exits,
however it exits, so a leftover lock file is harmless and never blocks anyone. The files are empty and are
not deleted (deleting a lock file another process is about to open would break the exclusion).
"""

from __future__ import annotations

import hashlib
import os
import re
from pathlib import Path

from filelock import FileLock

from .home import data_home

#: What a lock guards: writing a dataset file, generating one (solver runs and write), training a checkpoint.
LOCK_KINDS = ("write", "generate", "train")


def lock_dir() -> Path:
    """The folder of the lock files: ``$DKS_GYM_HOME/.locks`` (not created)."""
    return data_home() / ".locks"


def lock_path(target: str | Path, kind: str = "write") -> Path:
    """Where the ``kind`` lock of ``target`` lives: ``<lock dir>/<name>-<16 hex digits of the path>.<kind>.lock``.

    The name of the target starts the file's name so that a person can tell which lock is whose; the hash
    of the absolute path makes it unique. The lock folder is created here.
    """
    if kind not in LOCK_KINDS:
        raise ValueError(f"unknown lock kind {kind!r}; choose one of {', '.join(LOCK_KINDS)}")
    target = Path(os.path.realpath(Path(target).expanduser()))
    digest = hashlib.sha256(os.fsencode(target)).hexdigest()[:16]
    name = f"{re.sub(r'[^A-Za-z0-9._-]', '_', target.name)[:80]}-{digest}.{kind}.lock"
    for folder in (lock_dir(), target.parent / ".locks"):
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError:
            continue
        if os.access(folder, os.W_OK):
            return folder / name
    return target.parent / ".locks" / name  # neither is writable: acquiring the lock reports the error


def file_lock(target: str | Path, kind: str = "write", timeout: float = -1) -> FileLock:
    """An (unacquired) inter-process lock on ``target`` for ``kind`` work; ``timeout`` in seconds, -1 waits forever.

    Use it as ``with file_lock(path, "write"):``, or call ``acquire()`` and catch ``filelock.Timeout``;
    ``lock.lock_file`` names the lock file for error messages.
    """
    return FileLock(str(lock_path(target, kind)), timeout=timeout)
