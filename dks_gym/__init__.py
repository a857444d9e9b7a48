"""dks-gym: Gymnasium environments for sparse flow sensing from the paper *Deep Koopman Sensing*.

``import dks_gym`` registers ``DKS/Burgers-v0``, ``DKS/Cylinder-v0``, ``DKS/Dambreak-v0``, ``DKS/Sphere-v0`` and
``DKS/Custom-v0`` (your own flow, from a schema file: ``data_path=...``) by string entry points: it imports
neither torch nor the filter stack. ``LatentFilter``, ``FilterConfig``,
``load_model`` and ``ModelSpec`` are imported on first use; ``set_threads`` sets the torch CPU threads of dks-gym's
training and filtering (default 1: see :mod:`dks_gym.threads`).
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

from .threads import set_threads  # first: it sets MKL's reproducible mode before any product (dks_gym.threads)
from .envs import SensingEnv, register_envs
from .version import __version__

register_envs()

# Exported names that need torch, and the module that defines each: imported when first asked for.
_LAZY = {
    "LatentFilter": "dks_gym.wrappers.latent_filter",
    "FilterConfig": "dks_gym.assimilation.config",
    "load_model": "dks_gym.models.lookup",
    "ModelSpec": "dks_gym.models.spec",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        value = getattr(import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'dks_gym' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_LAZY])


__all__ = ["FilterConfig", "LatentFilter", "ModelSpec", "SensingEnv", "__version__", "load_model", "register_envs",
           "set_threads"]
