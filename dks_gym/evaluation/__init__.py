"""Evaluation: the paper's Section IV experiments as code (batched assimilation runs, results files, figures).

* :func:`run_assimilation` (from :mod:`dks_gym.assimilation`): forward run / EKF / EnKF of one model over a
  whole test split as one batch;
* :mod:`~dks_gym.evaluation.results`: the versioned results JSON (``save_results``, ``load_results``, ``compare``);
* :func:`reproduce`: ``dks-gym reproduce BENCHMARK`` (every experiment, tables and figures);
* :func:`run_demo`: ``dks-gym demo``;
* :func:`~dks_gym.evaluation.estimators.score_estimator`: a user's estimator under the protocol, and
  :mod:`~dks_gym.evaluation.leaderboard`: ``dks-gym leaderboard``.
"""

from ..assimilation import AssimilationConfig, AssimilationResult, run_assimilation
from .demo import run_demo
from .reproduce import EXPERIMENTS, reproduce
from .comparison import compare
from .results import load_results, save_results, validate

__all__ = [
    "EXPERIMENTS",
    "AssimilationConfig",
    "AssimilationResult",
    "compare",
    "load_results",
    "reproduce",
    "run_assimilation",
    "run_demo",
    "save_results",
    "validate",
]
