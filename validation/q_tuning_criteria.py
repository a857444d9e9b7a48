"""Two criteria for the scale of the calibrated process noise Q, side by side: 95 % coverage and the CRPS.

`dks-gym train` ends by tuning the scale s of each model's calibrated Q until the EKF's 95 % intervals cover
95 % of the held-out frames (:func:`dks_gym.assimilation.tune_process_noise`). On a flow where the filter
degrades as s grows, coverage can reach 95 % only where the intervals are wide because the estimate has
fallen apart (the Kuramoto-Sivashinsky study in docs/results/kuramoto-sivashinsky). The CRPS is a proper
score: it rewards calibration and sharpness together. This runs the EKF on each model's held-out
trajectories (the tuning's own runs: 16 sensors, 20 % noise) at the tuned scale and a grid of others, and
records the coverage, the mean CRPS and the MSE over frames 1..n_t-1 at each.

    OMP_NUM_THREADS=1 python validation/q_tuning_criteria.py burgers \
        --out validation/results/q_tuning_criteria_burgers.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from dks_gym.assimilation.tuning import held_out_run, held_out_trajectories
from dks_gym.atomic import atomic_write_text
from dks_gym.dataset import load_dataset
from dks_gym.models import load_model
from dks_gym.names import MODEL_KINDS

#: The scales tried beside the tuned one.
SCALES = (2.0**-4, 2.0**-2, 1.0, 4.0, 16.0, 64.0, 256.0)


def scan(model: object, dataset: object, scales: list[float]) -> list[dict[str, float]]:
    """Coverage, mean CRPS and MSE of the tuning's EKF run (:func:`held_out_run`) at each scale of the model's Q."""
    trajectories = held_out_trajectories(model)
    rows = []
    for scale in scales:
        result = held_out_run(model, dataset, scale, trajectories)
        rows.append({"scale": scale, "coverage": float(np.mean(result.step_coverage[:, 1:])),
                     "crps": float(np.mean(result.step_crps[:, 1:])), "mse": float(np.mean(result.step_mse[:, 1:]))})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("benchmark")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    torch.set_num_threads(1)
    dataset = load_dataset(args.benchmark, "paper")
    models = {}
    for kind in MODEL_KINDS:
        model = load_model(args.benchmark, kind, dataset=dataset)
        tuned = float(model.calibration["Q_scale"])
        rows = scan(model, dataset, sorted([tuned, *(s for s in SCALES if not np.isclose(s, tuned, rtol=1e-6))]))
        best = min(rows, key=lambda row: row["crps"])
        models[kind] = {"tuned_scale": tuned, "crps_best_scale": best["scale"], "rows": rows}
        print(kind, f"tuned {tuned:.3g}, lowest CRPS at {best['scale']:.3g}", flush=True)
    out = {"benchmark": args.benchmark, "models": models,
           "command": f"python validation/q_tuning_criteria.py {args.benchmark} --out {args.out}"}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out, json.dumps(out, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
