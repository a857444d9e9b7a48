"""Wrappers that put a latent model and a filter around sensing environments and reward reconstruction error."""

from .building import REWARDS, Uncertainty, belief_space, build_assimilation
from .latent_filter import LatentFilter
from .vector import LatentFilterVectorEnv, SB3VecEnv

__all__ = ["REWARDS", "LatentFilter", "LatentFilterVectorEnv", "SB3VecEnv", "Uncertainty", "belief_space",
           "build_assimilation"]
