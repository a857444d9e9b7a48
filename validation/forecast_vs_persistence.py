"""The k-step decoded forecast of each trained latent model against persistence, on a benchmark's test split.

For every test trajectory and start frame s (every ``--stride``-th), encode x_s, roll the latent map k steps,
decode, and compare with x_{s+k}; persistence predicts x_{s+k} = x_s. MSE over the scored channels and every
cell (physical units), averaged over (trajectory, start) pairs. The estimator issue's convergence criterion
on the CFD benchmarks: each neural lite model's 10-step forecast beats persistence.

    python validation/forecast_vs_persistence.py dambreak --steps 10 \\
        --out validation/results/forecast_vs_persistence_dambreak.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np
import torch

from dks_gym.dataset import load_dataset
from dks_gym.models import load_model
from dks_gym.models.checkpoint import checkpoint_path, read_metadata
from dks_gym.names import MODEL_KINDS


@torch.no_grad()
def forecast_errors(model, ds, steps: int, stride: int) -> dict[str, float]:
    scored = [ds.channels.index(c) for c in ds.scored_channels]
    sums = np.zeros(2)
    count = 0
    for t in range(ds.n_trajectories("test")):
        x = torch.as_tensor(ds.read("test", t))
        starts = torch.arange(0, x.shape[0] - steps, stride)
        mu = torch.full((len(starts),), float(ds.params("test")[t]), dtype=torch.float64)
        z = model.rollout(model.encode(x[starts], mu), mu, steps)[:, -1]
        pred = model.decode(z, mu)[:, scored].double()
        target = x[starts + steps][:, scored].double()
        sums[0] += float(((pred - target) ** 2).flatten(1).mean(1).sum())
        sums[1] += float(((x[starts][:, scored].double() - target) ** 2).flatten(1).mean(1).sum())
        count += len(starts)
    return {"model_mse": sums[0] / count, "persistence_mse": sums[1] / count, "pairs": count}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("benchmark")
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--stride", type=int, default=5, help="every stride-th start frame (default 5)")
    ap.add_argument("--preset", default="lite")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    ds = load_dataset(args.benchmark, "paper")
    rows = {}
    for kind in MODEL_KINDS:
        path = checkpoint_path(args.benchmark, kind, args.preset, 32, 1)
        if not path.exists():
            print(f"{kind}: no checkpoint, skipped", file=sys.stderr)
            continue
        model = load_model(args.benchmark, kind, 32, args.preset, dataset=ds)
        err = forecast_errors(model, ds, args.steps, args.stride)
        meta = read_metadata(path)
        err.update(ratio=err["model_mse"] / err["persistence_mse"], steps_trained=meta.get("steps_done"),
                   train_time_s=meta.get("train_time_s"), stopped_early=meta.get("stopped_early"),
                   best_validation_loss=meta.get("best_validation_loss"))
        rows[kind] = err
        print(f"{kind:8s} {args.steps}-step forecast MSE {err['model_mse']:.3e}  "
              f"persistence {err['persistence_mse']:.3e}"
              f"  ratio {err['ratio']:.3f}  ({err['steps_trained']} steps, {err['train_time_s'] or 0:.0f} s)")
    doc = {"benchmark": args.benchmark, "preset": args.preset, "forecast_steps": args.steps, "stride": args.stride,
           "dataset": Path(str(ds.path)).name, "command": "python validation/forecast_vs_persistence.py "
           + " ".join(sys.argv[1:]), "models": rows}
    if args.out:
        Path(args.out).write_text(json.dumps(doc, indent=1) + "\n")
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
