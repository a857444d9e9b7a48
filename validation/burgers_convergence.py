"""Accuracy and cost of the Burgers reference data: the shipped scheme against the Cole-Hopf solution.

Writes JSON with (1) the error of the shipped resolution (nx = 1024, Courant 0.1, diffusive factor 0.45)
at t = 0.495 for nu in {0.01, 0.1, 1.0}, (2) a grid-refinement table with observed orders, (3) the
wall time of ``BURGERS.generate("paper")`` and (4) checks of the reference itself: how much a finer
quadrature changes the Cole-Hopf solution, its distance to an independent pseudo-spectral solver
(Fourier collocation + DOP853), and the drift of the mean of u, which the exact solution conserves.
Run from the repository root:

    OMP_NUM_THREADS=1 python validation/burgers_convergence.py --out validation/results/burgers_convergence.json
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch

from dks_gym.benchmarks.burgers import (
    BURGERS,
    COURANT,
    DIFFUSIVE_FACTOR,
    exact_solution,
    pseudo_spectral_solution,
    solve,
)

NUS = (0.01, 0.1, 1.0)
T_FINAL = 0.495


def errors_against_exact(nx: int, t: float = T_FINAL) -> dict[str, dict[str, float]]:
    """Max and RMS error of the scheme at time ``t`` on ``nx`` points, per viscosity."""
    u = solve(np.array(NUS), np.array([0.0, t]), nx=nx)[:, -1]
    x = 2 * math.pi * np.arange(nx) / nx
    out = {}
    for i, nu in enumerate(NUS):
        e = u[i] - exact_solution(x, t, nu)
        out[str(nu)] = {"max": float(np.abs(e).max()), "rms": float(np.sqrt(np.mean(e**2)))}
    return out


def reference_checks(t: float = T_FINAL) -> dict[str, dict[str, float]]:
    """Per viscosity: quadrature change of the exact solution, its gap to the pseudo-spectral solver, and the
    shipped scheme's MSE against it and drift of the mean of u (nx = 1024)."""
    out = {}
    u = solve(np.array(NUS), np.array([0.0, t]), nx=1024)[:, -1]
    x1024 = 2 * math.pi * np.arange(1024) / 1024
    for i, nu in enumerate(NUS):
        nx = {1.0: 64, 0.1: 512, 0.01: 2048}[nu]  # enough Fourier modes for each front
        x = 2 * math.pi * np.arange(nx) / nx
        exact = exact_solution(x, t, nu)
        exact1024 = exact_solution(x1024, t, nu)
        out[str(nu)] = {
            "quadrature_change": float(np.abs(exact_solution(x, t, nu, refine=2.0) - exact).max()),
            "pseudo_spectral_max_difference": float(np.abs(pseudo_spectral_solution(nu, t, nx)[1] - exact).max()),
            "scheme_mse_nx1024": float(np.mean((u[i] - exact1024) ** 2)),
            "scheme_mean_drift_nx1024": float(abs(u[i].mean())),
        }
        print(f"nu={nu}: {json.dumps(out[str(nu)])}", flush=True)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("validation/results/burgers_convergence.json"))
    parser.add_argument("--grids", type=int, nargs="+", default=[128, 256, 512, 1024, 2048])
    parser.add_argument("--repeats", type=int, default=2, help="timed runs of generate('paper'); the minimum is kept")
    args = parser.parse_args()
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))

    refinement = {}
    for nx in args.grids:
        start = time.perf_counter()
        refinement[nx] = errors_against_exact(nx)
        print(f"nx={nx:5d} ({time.perf_counter() - start:.1f} s): {json.dumps(refinement[nx])}", flush=True)
    orders = {
        str(fine): {
            nu: {norm: math.log2(refinement[coarse][nu][norm] / refinement[fine][nu][norm]) for norm in ("max", "rms")}
            for nu in refinement[fine]
        }
        for coarse, fine in zip(args.grids[:-1], args.grids[1:])
        if fine == 2 * coarse
    }
    shipped = refinement[1024] if 1024 in refinement else errors_against_exact(1024)
    checks = reference_checks()

    # The machine may be shared: keep the fastest of a few runs and record the load.
    generate_seconds = []
    for _ in range(args.repeats):
        start = time.perf_counter()
        data = BURGERS.generate("paper", seed=0, progress=False)
        n_trajectories = sum(1 for _ in data.trajectories)  # the solve runs here
        generate_seconds.append(time.perf_counter() - start)
    print(f"BURGERS.generate('paper'): {n_trajectories} trajectories in {min(generate_seconds):.2f} s", flush=True)

    result = {
        "benchmark": "burgers",
        "t": T_FINAL,
        "scheme": {"courant": COURANT, "diffusive_factor": DIFFUSIVE_FACTOR},
        "shipped_nx1024": shipped,
        "reference_checks": checks,
        "refinement": {str(nx): errs for nx, errs in refinement.items()},
        "observed_order": orders,
        "generate_paper_seconds": min(generate_seconds),
        "generate_paper_seconds_all": generate_seconds,
        "generate_paper_trajectories": n_trajectories,
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "torch_threads": torch.get_num_threads(),
            "load_average_1min": os.getloadavg()[0],
            "torch": torch.__version__,
            "numpy": np.__version__,
        },
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
