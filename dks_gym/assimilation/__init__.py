"""Assimilation: a latent model inside an EKF, an EnKF or a forward run, over B sensing episodes.

* :class:`FilterConfig`: how to filter (the one filter configuration); :data:`FILTERS` its kinds;
* :class:`Assimilation`: the batched core (forecast, update, decode, score) the wrappers step;
* :func:`run_episodes`: the one loop over whole episodes (the envs' layouts, a fixed layout per episode
  or a layout chosen per step), and :func:`run_assimilation` over a dataset split;
* :class:`AssimilationConfig`, :class:`AssimilationResult`: an evaluation run's settings and measurements.
"""

from .config import DIVERGENCE_POLICIES, FILTERS, INITIAL_CONDITIONS, AssimilationConfig, FilterConfig
from .core import Assimilation, Snapshot, approximate_initial_latent, field_errors, resolve_model
from .episodes import AssimilationResult, close_envs, episode_envs, run_assimilation, run_dataset, run_episodes

__all__ = [
    "DIVERGENCE_POLICIES",
    "FILTERS",
    "INITIAL_CONDITIONS",
    "Assimilation",
    "AssimilationConfig",
    "AssimilationResult",
    "FilterConfig",
    "Snapshot",
    "approximate_initial_latent",
    "close_envs",
    "episode_envs",
    "field_errors",
    "resolve_model",
    "run_assimilation",
    "run_dataset",
    "run_episodes",
]
