"""Wrappers that put a latent model and a filter around sensing environments and reward reconstruction error."""

from .latent_filter import REWARDS, LatentFilter, belief_space, build_assimilation
from .vector import LatentFilterVectorEnv, SB3VecEnv

__all__ = ["REWARDS", "LatentFilter", "LatentFilterVectorEnv", "SB3VecEnv", "belief_space", "build_assimilation"]
