"""How much of SHRED's accuracy comes from its sensors: SHRED with every reading missing against SHRED with them.

SHRED in the placement benchmark (dks_gym.models.shred) gets the readings, the parameter mu and the time
since the start, as the filters do. Trained with every reading lost (SensorFaults(dropout=1): the inputs are
mu and time only) it becomes a parametric surrogate of the training split; the gap to the same SHRED with
the readings of a layout is what its sensors are worth. Writes JSON per benchmark with both time-averaged
test MSEs (noise seed 0, 20 % noise) and the training costs. Run from the repository root with the datasets
of the benchmark runs in $DKS_GYM_HOME:

    OMP_NUM_THREADS=1 python validation/shred_without_sensors.py burgers dambreak \\
        --out docs/results/placement/benchmark/shred_without_sensors.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from dks_gym.atomic import atomic_path
from dks_gym.dataset import Dataset
from dks_gym.home import dataset_path
from dks_gym.models.shred import Shred, read_episodes
from dks_gym_agents.shred_baseline import frame_errors


def study(benchmark: str, m: int) -> dict:
    ds = Dataset(dataset_path(benchmark, "paper"))
    layout = ds.benchmark.paper_layout(m)
    n = ds.n_trajectories("test")
    truth = np.stack([ds.trajectory("test", t) for t in range(n)])
    out = {"benchmark": benchmark, "m": m, "layout": "paper"}
    for name, faults in (("with_readings", None), ("without_readings", {"dropout": 1.0})):
        shred = Shred(ds, layout, noise_level=0.2, faults=faults).fit(progress=True)
        readings = read_episodes(ds, layout, np.arange(n), np.zeros(n, dtype=int), split="test", noise_level=0.2,
                                 faults=faults)
        mse = frame_errors(shred.reconstruct(readings, ds.params("test")), truth, ds.benchmark.scored_indices)
        out[name] = {"time_mean_mse": float(mse[:, 1:].mean()), "final_mse": float(mse[:, -1].mean()),
                     "fit_seconds": shred.fit_seconds, "epochs": shred.epochs_run}
        print(benchmark, name, out[name], flush=True)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("benchmarks", nargs="+")
    parser.add_argument("--m", type=int, default=4, help="sensors of the layout with readings (paper layout)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    results = [study(b, args.m) for b in args.benchmarks]
    with atomic_path(args.out) as tmp:
        Path(tmp).write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
