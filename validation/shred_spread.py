"""How much SHRED's score moves between trainings: the placement benchmark's SHRED rows retrained with other seeds.

Each benchmark cell has one SHRED training (seed 0), with early stopping on a noisy validation loss. This study
retrains the `shred-qr` row of given runs (``<run>/placement.json.gz``: its layout, noise, faults and test
episodes) with seeds 0..S-1 and scores each on the same episodes, through the harness's own Eq. 18
(``frame_errors``). Seed 0 must give the committed number again (a reproducibility check from a fresh process);
the spread over seeds says how far one training's number can be read. Run from the repository root with the
runs' datasets in $DKS_GYM_HOME:

    OMP_NUM_THREADS=1 python validation/shred_spread.py docs/results/placement/benchmark/burgers/none/m16 \\
        docs/results/placement/benchmark/burgers/default/m16 --seeds 3 \\
        --out docs/results/placement/benchmark/shred_spread.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from dks_gym.atomic import atomic_path
from dks_gym.dataset import Dataset
from dks_gym.envs import SensorFaults
from dks_gym.evaluation.results import load_results
from dks_gym.home import dataset_path
from dks_gym.models.checkpoint import dataset_identity
from dks_gym.models.shred import Shred, ShredConfig, read_episodes
from dks_gym_agents.shred_baseline import frame_errors


def study(run: Path, n_seeds: int) -> dict:
    doc = load_results(run / "placement.json.gz")
    cfg = doc["config"]
    rec = next(r for r in doc["records"] if r.get("policy") == "shred-qr")
    ds = Dataset(dataset_path(doc["benchmark"], doc["dataset"]["preset"]))
    if dataset_identity(ds)["fingerprint"] != doc["dataset"]["fingerprint"]:
        raise SystemExit(f"{ds.path} is not the dataset {run} was made with (its fingerprint differs)")
    layout = np.asarray(rec["sensors"], dtype=np.int64)
    faults = SensorFaults.from_any(cfg.get("faults"))
    index, seeds = np.asarray(rec["trajectories"]), np.asarray(rec["noise_seeds"])
    readings = read_episodes(ds, layout, index, seeds, split=cfg["split"], noise_level=cfg["noise_level"],
                             faults=faults)
    truth = np.stack([ds.trajectory(cfg["split"], int(t)) for t in index])
    params = ds.params(cfg["split"])[index]
    base = ShredConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in rec["policy_config"].items()
                          if k in {f.name for f in dataclasses.fields(ShredConfig)}})
    out = {"run": run.as_posix(), "benchmark": doc["benchmark"], "m": len(layout),
           "faults": None if faults is None else faults.changed(), "committed_time_mean_mse":
           rec["time_mean_mse_mean"], "committed_seed": base.seed, "trainings": []}
    for seed in range(n_seeds):
        shred = Shred(ds, layout, noise_level=cfg["noise_level"], faults=faults,
                      config=dataclasses.replace(base, seed=seed)).fit(progress=True)
        mse = frame_errors(shred.reconstruct(readings, params), truth, ds.benchmark.scored_indices)
        row = {"seed": seed, "time_mean_mse": float(mse[:, 1:].mean()), "final_mse": float(mse[:, -1].mean()),
               "epochs": shred.epochs_run, "fit_seconds": shred.fit_seconds}
        out["trainings"].append(row)
        print(run, row, flush=True)
    values = np.array([t["time_mean_mse"] for t in out["trainings"]])
    out["spread"] = {"min": float(values.min()), "max": float(values.max()), "max_over_min":
                     float(values.max() / values.min())}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="folders holding a placement.json.gz with a shred-qr row")
    parser.add_argument("--seeds", type=int, default=3, help="SHRED trainings per run (seeds 0..S-1)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    results = [study(run, args.seeds) for run in args.runs]
    with atomic_path(args.out) as tmp:
        Path(tmp).write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
