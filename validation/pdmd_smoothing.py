"""The pDMD forward run of a benchmark's paper data under one thread count and BLAS kernel, per RBF ridge.

Run it under several settings and compare the printed final MSEs: a fit whose result moves with the threads
or the kernel is ill-conditioned at that ridge (docs/models.md, "The dambreak needs a larger RBF ridge")::

    for t in 1 2; do OMP_NUM_THREADS=$t python validation/pdmd_smoothing.py dambreak --threads $t; done
    OPENBLAS_CORETYPE=Prescott python validation/pdmd_smoothing.py dambreak
    OPENBLAS_CORETYPE=Sandybridge python validation/pdmd_smoothing.py dambreak

Needs the benchmark's paper data and its pDMD model (shipped, or `dks-gym train BENCHMARK --model pdmd`).
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("benchmark", choices=["burgers", "cylinder", "dambreak"])
    ap.add_argument("--threads", type=int, default=1, help="torch and BLAS threads")
    ap.add_argument("--smoothing", type=float, nargs="+", default=[1e-10, 1e-8], help="rbf_smoothing values")
    args = ap.parse_args()

    from dks_gym.threads import set_threads

    set_threads(args.threads)
    from dks_gym.assimilation import AssimilationConfig, run_assimilation
    from dks_gym.dataset import load_dataset
    from dks_gym.models import load_model

    ds = load_dataset(args.benchmark, "paper")
    model = load_model(args.benchmark, "pdmd", dataset=ds)
    for smoothing in args.smoothing:
        model.rbf_smoothing = smoothing  # drops the DMD fit: refitted with this ridge
        result = run_assimilation(model, ds, AssimilationConfig().replace(kind="forward"), uncertainty=False)
        print(json.dumps({"benchmark": args.benchmark, "threads": args.threads,
                          "openblas_coretype": os.environ.get("OPENBLAS_CORETYPE"), "rbf_smoothing": smoothing,
                          "forward_final_mse": float(np.mean(result.step_mse[:, -1]))}), flush=True)


if __name__ == "__main__":
    main()
