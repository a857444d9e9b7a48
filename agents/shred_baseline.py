"""SHRED, the baseline without a filter: a shallow recurrent decoder trained on one static policy's layout and
scored on the ranking's test episodes, a ``shred-<policy>`` row beside the filter's."""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from dks_gym.assimilation import field_errors, relative_l2_errors
from dks_gym.evaluation.intervals import interval_fields
from dks_gym.evaluation.results import UNCERTAINTY_SCORES, relative_fields
from dks_gym.models.shred import Shred, ShredConfig, read_episodes

from .policies import PlacementTask
from .records import PolicyResult
from .scenario import episodes


def frame_errors(estimate: np.ndarray, truth: np.ndarray, scored: Sequence[int]) -> np.ndarray:
    """Eq. 18 (:func:`~dks_gym.assimilation.field_errors`) at every frame of episodes of fields
    (E, n_t, C, *grid): (E, n_t), float64."""
    flat = [torch.as_tensor(np.asarray(x, dtype=np.float64).reshape(-1, *x.shape[2:])) for x in (estimate, truth)]
    return field_errors(*flat, tuple(scored)).numpy().reshape(estimate.shape[:2])


def frame_relative_errors(estimate: np.ndarray, truth: np.ndarray,
                          scored: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
    """The relative L2 error (:func:`~dks_gym.assimilation.relative_l2_errors`) at every frame of episodes of
    fields (E, n_t, C, *grid): over the scored channels (E, n_t) and per scored channel (E, n_t, n_scored)."""
    flat = [torch.as_tensor(np.asarray(x, dtype=np.float64).reshape(-1, *x.shape[2:])) for x in (estimate, truth)]
    total, per_channel = relative_l2_errors(*flat, tuple(scored))
    return total.reshape(estimate.shape[:2]), per_channel.reshape(*estimate.shape[:2], -1)


def evaluate_shred(task: PlacementTask, pr: PolicyResult, noise_seeds: Sequence[int],
                   config: ShredConfig = ShredConfig(), progress: bool = False) -> dict[str, Any]:
    """SHRED (:mod:`dks_gym.models.shred`) trained on the training split with the layout of a static policy's
    result ``pr`` and the task's noise and faults, scored on the same test episodes: a results record named
    ``shred-<policy>`` (model "shred", filter "none") with the placement fields, and ``pod_floor_time_mean_mse``,
    the error of the POD projection of the truth that bounds it."""
    if pr.policy.adaptive or not np.all(pr.layouts == pr.layouts[:1]):
        raise ValueError(f"SHRED reads one fixed layout; {pr.name!r} gives a layout per episode or per step")
    ds, cfg = task.dataset, task.config
    layout = pr.layouts[0]
    shred = Shred(ds, layout, noise_level=cfg.noise_level, faults=cfg.faults, config=config).fit(progress=progress)
    index, seeds = episodes(task, noise_seeds=noise_seeds)
    tic = time.perf_counter()
    readings = read_episodes(ds, layout, index, seeds, split=cfg.split, noise_level=cfg.noise_level,
                             faults=cfg.faults)
    estimate = shred.reconstruct(readings, ds.params(cfg.split)[index])
    seconds = time.perf_counter() - tic
    truth = np.stack([ds.trajectory(cfg.split, int(t)) for t in index])
    step = frame_errors(estimate, truth, task.benchmark.scored_indices)
    floor = frame_errors(shred.project(truth), truth, task.benchmark.scored_indices)[:, 1:].mean()
    final, tm = step[:, -1], step[:, 1:].mean(axis=1)
    relative, per_channel = frame_relative_errors(estimate, truth, task.benchmark.scored_indices)
    rec: dict[str, Any] = {
        "experiment": f"placement/shred-{pr.name}", "model": "shred", "filter": "none", "initial": "approximate",
        "noise": float(cfg.noise_level), "r": int(shred.network.decoder[-1].out_features), "T": 1, "n_members": None,
        "batch": len(index), "final_mse_mean": float(final.mean()),
        "final_mse_std": float(final.std(ddof=1)) if len(final) > 1 else None,
        "per_step_mse_mean": [float(v) for v in step.mean(axis=0)],
        "per_trajectory_final_mse": [float(v) for v in final], "max_forecast_norm": None,
        "da_step_seconds": seconds / (ds.n_frames - 1), "wall_time": shred.fit_seconds + seconds,
        "trajectories": [int(t) for t in index], "params": [float(v) for v in ds.params(cfg.split)[index]],
        **{f"final_{n}_mean": None for n in UNCERTAINTY_SCORES},
        "policy": f"shred-{pr.name}", "adaptive": False, "sensors": [int(c) for c in layout],
        "time_mean_mse_mean": float(tm.mean()), "time_mean_mse_std": float(tm.std(ddof=1)) if len(tm) > 1 else None,
        "per_trajectory_time_mean_mse": [float(v) for v in tm], "fit_seconds": shred.fit_seconds,
        "offline_seconds": shred.fit_seconds, "decision_seconds": None, "policy_config": shred.describe(),
        "noise_seeds": [int(s) for s in seeds], "pod_floor_time_mean_mse": float(floor),
        **relative_fields(relative, per_channel[:, -1], task.benchmark.scored_channels),
    }
    rec.update(interval_fields(rec))
    return rec


__all__ = ["evaluate_shred", "frame_errors", "frame_relative_errors"]
