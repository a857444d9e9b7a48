"""Wrappers that put a latent model and a filter around a SensingEnv and reward reconstruction error."""

from .latent_filter import FILTERS, LatentFilter, approximate_initial_latent, model_dynamics

__all__ = ["FILTERS", "LatentFilter", "approximate_initial_latent", "model_dynamics"]
