"""Wrappers that put a latent model and a filter around sensing environments and reward reconstruction error.

``TorchRLEnv`` (the TorchRL adapter, in :mod:`.torchrl_env`) is imported on first use, so that importing this
package never imports torchrl, an optional extra.
"""

from typing import Any

from .building import REWARDS, Uncertainty, belief_space, build_assimilation
from .latent_filter import LatentFilter
from .vector import LatentFilterVectorEnv, SB3VecEnv

# TorchRLEnv is left out of __all__: a star import would import torchrl.
__all__ = ["REWARDS", "LatentFilter", "LatentFilterVectorEnv", "SB3VecEnv", "Uncertainty", "belief_space",
           "build_assimilation"]


def __getattr__(name: str) -> Any:
    """``TorchRLEnv`` from :mod:`.torchrl_env` (which needs torchrl), imported when first asked for."""
    if name == "TorchRLEnv":
        from .torchrl_env import TorchRLEnv

        return TorchRLEnv
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
