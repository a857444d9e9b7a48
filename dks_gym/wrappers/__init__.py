"""Wrappers that put a latent model and a filter around sensing environments and reward reconstruction error."""

from .assimilator import (
    FILTERS,
    FilterConfig,
    LatentAssimilator,
    approximate_initial_latent,
    field_errors,
    model_dynamics,
    resolve_model,
)
from .latent_filter import LatentFilter
from .vector import LatentFilterVectorEnv, SB3VecEnv

__all__ = [
    "FILTERS",
    "FilterConfig",
    "LatentAssimilator",
    "LatentFilter",
    "LatentFilterVectorEnv",
    "SB3VecEnv",
    "approximate_initial_latent",
    "field_errors",
    "model_dynamics",
    "resolve_model",
]
