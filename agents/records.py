"""What a placement run produced: each policy's test-split result, and the results document that stores them.

``placement.json.gz`` is a results document of the ``dks-gym-results`` schema (:mod:`dks_gym.evaluation.results`),
one record per policy with ``experiment = "placement/<policy>"``, plus the placement fields ``policy``,
``adaptive``, ``sensors`` (static layout) or ``sensor_counts`` (adaptive: [cell, reads]),
``time_mean_mse_mean``/``_std``, ``per_trajectory_time_mean_mse``, ``fit_seconds`` (fitting here),
``offline_seconds`` (the offline cost: fitting plus the training recorded in a loaded agent checkpoint),
``decision_seconds`` (wall time per decision: per episode for static layouts, per step and trajectory for
adaptive ones), ``policy_config`` and the interval fields of the time-averaged MSE (``time_mean_mse_iqm``,
``time_mean_mse_ci95``: :func:`~dks_gym.evaluation.intervals.interval_fields`, stratified by trajectory).
A ``placement/forward`` record (no assimilation) is the reference.
Records keep each trajectory's final and time-averaged MSE and the mean curve over time, not every
trajectory's curve: no ranking, interval or figure reads those, and they were most of a committed file.
The document names the benchmark's protocol (:func:`~dks_gym.evaluation.conformance.stamp_protocol`).
"""

from __future__ import annotations

import math
import platform
from dataclasses import dataclass
from datetime import datetime, timezone
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from dks_gym.assimilation import AssimilationResult
from dks_gym.evaluation.conformance import stamp_protocol
from dks_gym.evaluation.intervals import interval_fields
from dks_gym.evaluation.results import make_record, new_results

from .policies import PlacementPolicy, PlacementTask

#: The name of a placement run's results document in its output folder (gzip-compressed JSON).
PLACEMENT_FILE = "placement.json.gz"


@dataclass
class PolicyResult:
    """One policy's test-split run: the batched filter result and the policy's costs and layouts."""

    policy: PlacementPolicy
    result: AssimilationResult
    layouts: np.ndarray  # (B, m) static; (B, n_t - 1, m) adaptive
    decision_seconds: float

    @property
    def name(self) -> str:
        return self.policy.name

    @property
    def time_mean_mse(self) -> np.ndarray:
        """(B,) MSE averaged over the assimilated frames 1..n_t-1."""
        return self.result.step_mse[:, 1:].mean(axis=1)


def _record(pr: PolicyResult) -> dict[str, Any]:
    rec = make_record(pr.result, experiment=f"placement/{pr.name}", keep_curves=False)
    tm = pr.time_mean_mse
    rec.update(
        policy=pr.name, adaptive=pr.policy.adaptive,
        time_mean_mse_mean=float(tm.mean()), time_mean_mse_std=float(tm.std(ddof=1)) if len(tm) > 1 else None,
        per_trajectory_time_mean_mse=[float(v) for v in tm],
        fit_seconds=None if not math.isfinite(pr.policy.fit_seconds) else float(pr.policy.fit_seconds),
        offline_seconds=None if not math.isfinite(pr.policy.offline_seconds) else float(pr.policy.offline_seconds),
        decision_seconds=float(pr.decision_seconds), policy_config=pr.policy.describe(),
        noise_seeds=[int(s) for s in pr.result.extras["noise_seeds"]],
    )
    rec.update(interval_fields(rec))  # the time-averaged MSE's too, now that the record holds it
    if pr.policy.adaptive:
        cells, counts = np.unique(pr.layouts, return_counts=True)
        rec["sensors"] = None
        rec["sensor_counts"] = [[int(c), int(n)] for c, n in zip(cells, counts)]
        rec["candidates"] = [int(c) for c in pr.policy.candidates]
    else:
        rec["sensors"] = [int(c) for c in pr.layouts[0]]
    return rec


def placement_document(task: PlacementTask, results: Sequence[PolicyResult], forward: AssimilationResult | None,
                       *, wall_time: float) -> dict[str, Any]:
    """The results document (``dks-gym-results`` schema) of one harness run, naming its protocol."""
    from dks_gym.version import __version__
    from dks_gym.models.checkpoint import dataset_identity

    ds, model_preset = task.dataset, task.model_preset
    records = [_record(pr) for pr in results]
    if forward is not None:
        rec = make_record(forward, experiment="placement/forward", keep_curves=False)
        tm = forward.step_mse[:, 1:].mean(axis=1)
        rec.update(policy="forward", adaptive=False, sensors=None, time_mean_mse_mean=float(tm.mean()),
                   noise_seeds=[int(s) for s in forward.extras["noise_seeds"]],
                   time_mean_mse_std=float(tm.std(ddof=1)) if len(tm) > 1 else None,
                   per_trajectory_time_mean_mse=[float(v) for v in tm], fit_seconds=None, offline_seconds=None,
                   decision_seconds=None,
                   policy_config={"name": "forward", "note": "no assimilation: the open-loop model, sensors unused"})
        rec.update(interval_fields(rec))
        records.append(rec)
    seeds = sorted({int(s) for s in results[0].result.extras["noise_seeds"]})
    config = dict(task.config.as_record(), n_test=ds.n_trajectories(task.config.split), n_frames=ds.n_frames,
                  noise_seeds=seeds, n_episodes=int(results[0].result.batch),
                  observed_channel=ds.observed_channel, scored_channels=list(ds.scored_channels),
                  model=task.model.kind, r=int(task.model.r), model_preset=model_preset, device=str(task.device),
                  policies=[pr.name for pr in results], ranking="time-averaged MSE over frames 1..n_t-1",
                  n_allowed_cells=int(len(task.allowed_cells)), constrained=task.candidates is not None,
                  created=datetime.now(timezone.utc).isoformat(timespec="seconds"), wall_time_s=wall_time,
                  dks_gym_version=__version__, torch_version=torch.__version__, python=platform.python_version())
    return stamp_protocol(new_results(ds.benchmark.name, model_preset, dataset_identity(ds), config, records,
                                      [{"model": task.model.kind, "r": int(task.model.r), "preset": model_preset}]))


__all__ = ["PolicyResult", "placement_document"]
