"""Assimilation: a latent model inside an EKF, an EnKF or a forward run, over B sensing episodes.

* :class:`FilterConfig`: how to filter (the one filter configuration); :data:`FILTERS` its kinds;
* :class:`Assimilation`: the batched core (forecast, update, decode, score) the wrappers step;
* :func:`run_episodes`: the one loop over whole episodes (the envs' layouts, a fixed layout per episode
  or a layout chosen per step), and :func:`run_assimilation` over a dataset split;
* :class:`AssimilationConfig`, :class:`AssimilationResult`: an evaluation run's settings and measurements;
* :mod:`~dks_gym.assimilation.uncertainty`: the predictive std of the decoded estimate (``estimate_std``),
  :func:`reconstruction_variance` and the scores (:func:`gaussian_scores`, :func:`gaussian_crps`).
"""

from .config import DIVERGENCE_POLICIES, FILTERS, INITIAL_CONDITIONS, AssimilationConfig, FilterConfig
from .core import Assimilation, Snapshot, approximate_initial_latent, field_errors, resolve_model
from .episodes import (
    AssimilationResult,
    close_envs,
    ensure_process_noise_scale,
    episode_envs,
    held_out_coverage,
    run_assimilation,
    run_dataset,
    run_episodes,
    tune_process_noise,
)
from .uncertainty import (
    ensemble_variance,
    gaussian_crps,
    gaussian_scores,
    jacobian_variance,
    reconstruction_variance,
)

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
    "ensemble_variance",
    "ensure_process_noise_scale",
    "episode_envs",
    "field_errors",
    "gaussian_crps",
    "gaussian_scores",
    "held_out_coverage",
    "jacobian_variance",
    "reconstruction_variance",
    "resolve_model",
    "run_assimilation",
    "run_dataset",
    "run_episodes",
    "tune_process_noise",
]
