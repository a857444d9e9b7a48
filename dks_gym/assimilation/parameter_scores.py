"""How well a run estimated the physical parameter: the per-frame scores of an estimated mu
(:attr:`~dks_gym.assimilation.AssimilationResult.step_parameter`) summed up for a results record."""

from __future__ import annotations

from typing import Any

import numpy as np


def parameter_summary(step_parameter: dict[str, np.ndarray]) -> dict[str, Any]:
    """JSON-ready summary over the trajectories of a run that estimated mu: at the final frame the median and
    mean relative error, the fraction of trajectories whose true mu lies in the 95 % interval and whose estimate
    left the training range, the median of the estimated coordinate's std over its prior's, each trajectory's
    estimate and std; per frame the median relative error, the
    fraction inside the interval and the median std (how fast the sensors identify mu, if at all)."""
    error, inside = step_parameter["mu_relative_error"], step_parameter["mu_in_interval"].astype(np.float64)
    std, estimate = step_parameter["mu_std"], step_parameter["mu_estimate"]
    return {
        "final_relative_error_median": float(np.median(error[:, -1])),
        "final_relative_error_mean": float(np.mean(error[:, -1])),
        "final_in_interval_fraction": float(np.mean(inside[:, -1])),
        "final_out_of_range_fraction": float(np.mean(step_parameter["mu_out_of_range"][:, -1])),
        "final_std_ratio_median": float(np.median(step_parameter["mu_std_ratio"][:, -1])),
        "per_trajectory_final_estimate": [float(v) for v in estimate[:, -1]],
        "per_trajectory_final_std": [float(v) for v in std[:, -1]],
        "per_step_relative_error_median": [float(v) for v in np.median(error, axis=0)],
        "per_step_in_interval_fraction": [float(v) for v in np.mean(inside, axis=0)],
        "per_step_std_median": [float(v) for v in np.median(std, axis=0)],
    }


__all__ = ["parameter_summary"]
