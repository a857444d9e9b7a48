"""The installed dks-gym version, read from the package metadata (pyproject.toml is the one place it is set).

A module of its own so that any layer can record the version (checkpoints, results) without importing
the package root.
"""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("dks-gym")
except PackageNotFoundError:  # run from a source tree that was never installed
    __version__ = "0.1.0"

__all__ = ["__version__"]
