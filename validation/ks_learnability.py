"""What the latent models learn of the Kuramoto-Sivashinsky example, and what the EKF makes of it.

For each trained checkpoint of a KS schema file: the mean squared error of the decoded reconstruction and of the
decoded one-step forecast on every (frame, next frame) pair of the training and the test split, beside
persistence (the next frame taken as this one) and the split's field variance (the error of u = 0, the
conserved mean); POD with r modes of the training frames as the linear reference. With ``--scan``, the EKF of
that checkpoint on the test split (16 sensors at the lattice layout, 20 % noise, the placement harness's
settings) at several scales of its calibrated process noise Q: the scale `dks-gym train` tunes for 95 %
coverage, and the ones given.

    export OMP_NUM_THREADS=1
    python validation/ks_learnability.py --data ks.h5 --checkpoint CK1 --checkpoint CK2 \\
        --scan CK2 --q-scales 0.25 1 4 16 --out validation/results/ks_learnability.json

``--lite-min-width 2`` rebuilds lite checkpoints trained before the sizing rule's minimum first width of 8
(the 2-4-8 rows of docs/results/kuramoto-sivashinsky).

(docs/results/kuramoto-sivashinsky/README.md gives the commands that make the data and the checkpoints.)
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dks_gym.assimilation import AssimilationConfig
from dks_gym.atomic import atomic_write_text
from dks_gym.dataset import Dataset
import dks_gym.models.presets as presets
from dks_gym.models import one_step_error
from dks_gym.models.checkpoint import model_from_checkpoint
from dks_gym_agents import PlacementTask
from dks_gym_agents.evaluate import evaluate_placement


def pair_errors(model: Any, ds: Dataset, split: str) -> dict[str, float]:
    """Reconstruction, one-step and persistence MSE on every consecutive pair of ``split``
    (:func:`~dks_gym.models.one_step_error` over all of them) and the field variance of the next frames."""
    pairs = ds.n_trajectories(split) * (int(ds.fields(split).shape[1]) - 1)
    errors = one_step_error(model, ds, split, max_pairs=pairs)
    nxt = np.asarray(ds.fields(split), dtype=np.float64)[:, 1:]
    return {"variance": float(nxt.var()), "reconstruction": errors["reconstruction_mse"],
            "one_step": errors["model_mse"], "persistence": errors["persistence_mse"]}


def pod_errors(ds: Dataset, ranks: list[int]) -> dict[str, dict[str, float]]:
    """POD of the training frames: the projection MSE of each split's frames on the first r modes."""
    train = np.asarray(ds.fields("train"), dtype=np.float64)
    flat = {s: np.asarray(ds.fields(s), dtype=np.float64).reshape(-1, int(np.prod(train.shape[2:])))
            for s in ("train", "test")}
    mean = flat["train"].mean(0)
    _, _, modes = np.linalg.svd(flat["train"] - mean, full_matrices=False)
    return {str(r): {s: float((((a - mean) @ modes[:r].T @ modes[:r] + mean - a) ** 2).mean()) for s, a in flat.items()}
            for r in ranks}


def ekf_at_scales(model: Any, ds: Dataset, scales: list[float]) -> list[dict[str, Any]]:
    """The EKF's time-averaged test MSE at the lattice layout for each scale of the calibrated Q (the tuned
    scale first), with the forward run's."""
    tuned = float(model.calibration.get("Q_scale", 1.0))
    rows = []
    for scale in [tuned, *scales]:
        model.calibration["Q_scale"] = scale
        task = PlacementTask(ds, model, AssimilationConfig().replace(kind="ekf", n_sensors=16))
        with tempfile.TemporaryDirectory() as tmp:
            doc, _ = evaluate_placement(task, ["paper"], out=Path(tmp))
        mse = {rec["policy"]: rec["time_mean_mse_mean"] for rec in doc["records"]}
        rows.append({"Q_scale": scale, "tuned": scale == tuned, "ekf_time_mean_mse": mse["paper"],
                     "forward_time_mean_mse": mse["forward"]})
        print(rows[-1], flush=True)
    model.calibration["Q_scale"] = tuned
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--checkpoint", type=Path, action="append", default=[])
    parser.add_argument("--scan", type=Path, help="the checkpoint whose EKF runs at the --q-scales")
    parser.add_argument("--q-scales", type=float, nargs="+", default=[0.25, 1.0, 4.0, 16.0])
    parser.add_argument("--lite-min-width", type=int,
                        help="rebuild lite checkpoints with this minimum first width of the sizing rule (2: the rule "
                             "before its minimum of 8, which the 2-4-8 rows were trained with)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.lite_min_width is not None:
        presets._MIN_WIDTH["lite"] = args.lite_min_width
    ds = Dataset(args.data)
    result: dict[str, Any] = {"data": args.data.name, "frames": int(ds.fields("train").shape[1]),
                              "pod": pod_errors(ds, [8, 16, 32]), "models": []}
    for path in args.checkpoint:
        model = model_from_checkpoint(path)
        result["models"].append({"checkpoint": path.name, "Q_scale": float(model.calibration.get("Q_scale", 1.0)),
                                 **{split: pair_errors(model, ds, split) for split in ("train", "test")}})
        print(result["models"][-1], flush=True)
    if args.scan is not None:
        result["ekf_scan"] = {"checkpoint": args.scan.name,
                              "rows": ekf_at_scales(model_from_checkpoint(args.scan), ds, args.q_scales)}
    result["command"] = "python validation/ks_learnability.py " + " ".join(
        os.path.basename(a) if os.path.isabs(a) else a for a in sys.argv[1:])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out, json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
