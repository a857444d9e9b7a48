"""The scenario a placement ranking runs under: the noise realizations, the sensors' faults, where sensors may
go and the estimators ranked beside the filter.

The task (:class:`~dks_gym_agents.policies.PlacementTask`) holds what the policies learn from and are judged
with: the data, the model and the filter settings (filter kind, noise level, sensor budget ``n_sensors``, the
first noise seed). The :class:`Scenario` holds what only the test episodes see, so every policy of a ranking
is fitted on the same clean training split and judged on the same episodes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from collections.abc import Sequence
from typing import Any

import numpy as np

from dks_gym.envs import SensorFaults
from dks_gym.models.shred import ShredConfig

from .policies import PlacementTask

#: The placement benchmark's fault scenario, the same on every benchmark: one reading in ten lost, and each
#: sensor failing for good with probability 0.5 % per step (about 40 % of them within a 100-frame episode).
DEFAULT_FAULTS = SensorFaults(dropout=0.1, failure_rate=0.005)


@dataclass(frozen=True)
class Scenario:
    """What a ranking's test episodes run under.

    ``noise_seeds``: noise realizations per test trajectory, the seeds ``task.config.noise_seed``,
    ``noise_seed + 1``, ... ``faults``: the sensors' faults in every test episode (a
    :class:`~dks_gym.envs.SensorFaults`, a dict of its fields, or "default" for :data:`DEFAULT_FAULTS`;
    None keeps the task's own); the policies are fitted without them. ``constraint``: where sensors may go
    (:func:`~dks_gym_agents.policies.constraint_candidates`: "fluid", "surface", "wall", a keep-out mask or the
    allowed cells; the paper layout moves to the nearest allowed cells). ``shred``: static policies of the run
    whose layout a SHRED baseline is trained on and scored with (:func:`~dks_gym_agents.shred_baseline.evaluate_shred`,
    ``shred_config`` its settings), each a ``shred-<policy>`` row.
    """

    noise_seeds: int = 1
    faults: SensorFaults | dict[str, Any] | str | None = None
    constraint: str | np.ndarray | None = None
    shred: Sequence[str] = ()
    shred_config: ShredConfig = field(default_factory=ShredConfig)

    def __post_init__(self) -> None:
        if int(self.noise_seeds) < 1:
            raise ValueError(f"noise_seeds must be at least 1, got {self.noise_seeds!r}")
        faults = DEFAULT_FAULTS if isinstance(self.faults, str) and self.faults == "default" else self.faults
        object.__setattr__(self, "faults", SensorFaults.from_any(faults))  # unknown names fail here, before any work
        object.__setattr__(self, "shred", tuple(dict.fromkeys(self.shred)))

    def seeds(self, task: PlacementTask) -> list[int]:
        """The noise seeds of the test episodes: ``noise_seeds`` of them from the task's own."""
        first = int(task.config.noise_seed)
        return list(range(first, first + int(self.noise_seeds)))


def episodes(task: PlacementTask, trajectories: np.ndarray | None = None,
             noise_seeds: Sequence[int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The evaluation episodes: every trajectory (default: the whole split) under every noise seed (default:
    ``task.config.noise_seed``), as (trajectory, seed) arrays ordered seed-major."""
    n = task.dataset.n_trajectories(task.config.split)
    index = np.arange(n) if trajectories is None else np.asarray(trajectories, dtype=np.int64)
    seeds = [task.config.noise_seed] if noise_seeds is None else [int(s) for s in noise_seeds]
    return np.tile(index, len(seeds)), np.repeat(np.asarray(seeds, dtype=np.int64), len(index))


__all__ = ["DEFAULT_FAULTS", "Scenario", "episodes"]
