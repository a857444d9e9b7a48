"""Sensor-placement policies for dks-gym and the harness that ranks them with a latent filter in the loop.

* :mod:`dks_gym_agents.policies`: the interface (:class:`PlacementTask`, :class:`StaticPolicy`,
  :class:`AdaptivePolicy`);
* :mod:`dks_gym_agents.baselines`: paper layout, random layouts, QR or CCQR pivoting on POD modes, greedy;
* :mod:`dks_gym_agents.sequential`: placement as an MDP (place m sensors one by one), PPO;
* :mod:`dks_gym_agents.adaptive`: adaptive sensing, PPO on the filter's belief (``sensor_mode="select"``);
* :mod:`dks_gym_agents.scoring`: batched filter runs of many layouts, the linearized covariance objective;
* :mod:`dks_gym_agents.evaluate`: :func:`evaluate_placement`, the harness: a task, its policies and a scenario;
* :mod:`dks_gym_agents.scenario` (noise seeds, faults, constraint, SHRED baselines), :mod:`dks_gym_agents.registry`
  (the named policies), :mod:`dks_gym_agents.records`, :mod:`dks_gym_agents.paired`, :mod:`dks_gym_agents.tables`,
  :mod:`dks_gym_agents.figures`: the results JSON, the paired comparison, the tables and figures of a ranking;
* :mod:`dks_gym_agents.budgets`: :func:`evaluate_budgets`, one ranking per sensor budget;
* :mod:`dks_gym_agents.shred_baseline`: SHRED trained on a policy's layout, ranked beside the filter;
* :mod:`dks_gym_agents.summary`: the placement benchmark's summary page;
* :mod:`dks_gym_agents.cli`: the ``dks-gym evaluate-placement`` click command.
"""

from .baselines import GreedyLayout, PaperLayout, QRLayout, RandomLayout
from .policies import (
    AdaptivePolicy,
    PlacementPolicy,
    PlacementTask,
    StaticPolicy,
    candidate_lattice,
    check_layout,
    distinct_picks,
)

__all__ = [
    "AdaptivePolicy",
    "GreedyLayout",
    "PaperLayout",
    "PlacementPolicy",
    "PlacementTask",
    "QRLayout",
    "RandomLayout",
    "StaticPolicy",
    "candidate_lattice",
    "check_layout",
    "distinct_picks",
]
