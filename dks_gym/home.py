"""Where dks-gym keeps its data: ``$DKS_GYM_HOME``, default ``~/.cache/dks_gym``."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


class DataHomeError(OSError):
    """The data home cannot be created or written."""


def data_home() -> Path:
    """The data home directory (not created)."""
    env = os.environ.get("DKS_GYM_HOME")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "dks_gym"


def dataset_path(benchmark: str, preset: str = "paper", home: str | Path | None = None) -> Path:
    """Default location of a benchmark's dataset file for ``preset`` in the data home (or in ``home``)."""
    return (data_home() if home is None else Path(home).expanduser()) / "data" / f"{benchmark}-{preset}.h5"


def ensure_writable(directory: Path) -> Path:
    """Create ``directory`` if needed and check that files can be written there."""
    try:
        directory.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=directory, prefix=".write-test-"):
            pass
    except OSError as exc:
        raise DataHomeError(
            f"cannot write to {directory} ({exc.strerror or exc}); set DKS_GYM_HOME to a writable directory "
            "or pass an explicit output path"
        ) from exc
    return directory
