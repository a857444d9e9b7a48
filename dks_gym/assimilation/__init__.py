"""Assimilation: a latent model inside an EKF, an EnKF or a forward run, over B sensing episodes.

* :class:`FilterConfig`: how to filter (the one filter configuration); :data:`FILTERS` its kinds;
* :class:`Assimilation`: the batched core (forecast, update, decode, score) the wrappers step;
* :func:`resolve_model`: a kind name, a :class:`~dks_gym.models.ModelSpec` or a model object as the model object;
* :func:`run_episodes`: the one loop over whole episodes (the envs' layouts, a fixed layout per episode
  or a layout chosen per step), and :func:`run_assimilation` over a dataset split;
* :class:`AssimilationConfig`, :class:`AssimilationResult`: an evaluation run's settings and measurements;
* :mod:`~dks_gym.assimilation.errors`: the errors of an estimate (:func:`field_errors`, Eq. 18's MSE;
  :func:`relative_l2_errors`, ||x^ - x|| / ||x||; :func:`ctf_score`, 100 (1 - relative L2));
* :mod:`~dks_gym.assimilation.tuning`: the scale of the calibrated process noise (:func:`calibrate_process_noise`);
* :mod:`~dks_gym.assimilation.uncertainty`: the predictive std of the decoded estimate (``estimate_std``),
  :func:`reconstruction_variance` and the scores (:func:`gaussian_scores`, :func:`gaussian_crps`).
* :mod:`~dks_gym.assimilation.spread`: the spread diagnostics (the spread-skill ratio, the EnKF's rank
  histograms of the truth among its decoded members).
"""

from .config import (
    DIVERGENCE_POLICIES,
    FILTERS,
    INITIAL_CONDITIONS,
    AssimilationConfig,
    FilterConfig,
    process_noise_scale,
)
from .core import Assimilation, Snapshot, approximate_initial_latent
from .episodes import (
    AssimilationResult,
    close_envs,
    episode_envs,
    run_assimilation,
    run_dataset,
    run_episodes,
)
from .errors import ctf_score, field_errors, relative_l2_errors
from .parameter_scores import parameter_summary
from .resolve import ModelLike, resolve_model
from .tuning import calibrate_process_noise, held_out_coverage, tune_if_missing, tune_process_noise
from .uncertainty import (
    ensemble_variance,
    gaussian_crps,
    gaussian_scores,
    jacobian_variance,
    reconstruction_variance,
)

__all__ = [
    "parameter_summary",
    "DIVERGENCE_POLICIES",
    "FILTERS",
    "INITIAL_CONDITIONS",
    "Assimilation",
    "AssimilationConfig",
    "AssimilationResult",
    "FilterConfig",
    "ModelLike",
    "Snapshot",
    "approximate_initial_latent",
    "calibrate_process_noise",
    "close_envs",
    "ctf_score",
    "ensemble_variance",
    "episode_envs",
    "field_errors",
    "gaussian_crps",
    "gaussian_scores",
    "held_out_coverage",
    "jacobian_variance",
    "process_noise_scale",
    "reconstruction_variance",
    "relative_l2_errors",
    "resolve_model",
    "run_assimilation",
    "run_dataset",
    "run_episodes",
    "tune_if_missing",
    "tune_process_noise",
]
