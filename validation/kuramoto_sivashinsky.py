"""Accuracy of the Kuramoto-Sivashinsky solver and the choice of its data parameters.

Writes JSON with (1) the leading Lyapunov exponent at L = 22 over long runs (the published check) and over
the short runs the test uses, (2) a scan of the leading exponent over the effective domain length
L_eff = L / sqrt(nu) (where KS is robustly chaotic), (3) the exponent over the data's nu range on L = 60,
(4) the time-step convergence of ETDRK4 at the data's setting, (5) the grid convergence and the spectral
tail, (6) the distance to scipy's DOP853 on the same Fourier ODE and (7) the cost of the data generator.
Run from the repository root (about 6 minutes of CPU time on one core):

    OMP_NUM_THREADS=1 python validation/kuramoto_sivashinsky.py --out validation/results/kuramoto_sivashinsky.json
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import time
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp

from dks_gym.solvers import kuramoto_sivashinsky as ks


def lyapunov_l22(seeds: int, t_total: float) -> dict[str, object]:
    """Leading exponent at L = 22, nu = 1: long runs (64 points, dt 0.1) and the test's short runs."""
    long_runs = [ks.leading_lyapunov_exponent(1.0, 22.0, n_x=64, dt=0.1, t_total=t_total, seed=s) for s in range(seeds)]
    short = [ks.leading_lyapunov_exponent(1.0, 22.0, n_x=48, dt=0.25, t_total=1500.0, transient=100.0, seed=s)
             for s in range(20)]
    out = {
        "long_runs": {"n_x": 64, "dt": 0.1, "t_total": t_total, "per_seed": long_runs,
                      "mean": float(np.mean(long_runs)), "sem": float(np.std(long_runs, ddof=1) / math.sqrt(seeds))},
        "test_setting": {"n_x": 48, "dt": 0.25, "t_total": 1500.0, "transient": 100.0, "per_seed": short,
                         "mean": float(np.mean(short)), "std": float(np.std(short, ddof=1)),
                         "min": float(np.min(short)), "max": float(np.max(short))},
    }
    print("L=22:", json.dumps({k: {q: v[q] for q in ("mean",)} for k, v in out.items()}), flush=True)
    return out


def lyapunov_scan(l_effs: np.ndarray, seeds: int, t_total: float) -> dict[str, list[float]]:
    """Leading exponent (nu = 1 units) at each effective length, ``seeds`` random initial conditions each."""
    out = {}
    for l_eff in l_effs:
        n_x = 64 if l_eff <= 40 else 128  # grid spacing below 0.7 in nu = 1 units
        out[f"{l_eff:g}"] = [ks.leading_lyapunov_exponent(1.0, float(l_eff), n_x=n_x, dt=0.1, t_total=t_total,
                                                          seed=100 + s) for s in range(seeds)]
        print(f"L_eff={l_eff:g}: {' '.join(f'{x:+.4f}' for x in out[f'{l_eff:g}'])}", flush=True)
    return out


def lyapunov_data_range(nus: np.ndarray, seeds: int, t_total: float) -> dict[str, list[float]]:
    """Leading exponent in the data's own time units over its nu range (L = 60, 128 points, dt 0.05)."""
    out = {f"{nu:g}": [ks.leading_lyapunov_exponent(float(nu), ks.LENGTH, n_x=128, dt=0.05, t_total=t_total,
                                                   seed=200 + s) for s in range(seeds)] for nu in nus}
    print("data range:", json.dumps(out), flush=True)
    return out


def attractor_state(nu: float, n_x: int, seed: int = 0) -> np.ndarray:
    """The state after 200 time units from a random start, on ``n_x`` points of the data's domain."""
    u0 = ks.initial_conditions(1, n_x, ks.LENGTH, np.random.default_rng(seed))[0]
    return ks.simulate(u0, nu, ks.LENGTH, 0.025, 8000, save_every=8000)[-1]


def time_convergence(T: float = 1.0) -> dict[str, dict[str, list[float]]]:
    """Max error after ``T`` (two frames) against dt = T / 2560, 256 points, for nu = 0.5 and 1."""
    out = {}
    steps = [10, 20, 40, 80, 160]
    for nu in (0.5, 1.0):
        u0 = attractor_state(nu, 256)
        ref = ks.simulate(u0, nu, ks.LENGTH, T / 2560, 2560, save_every=2560)[-1]
        errors = [float(np.abs(ks.simulate(u0, nu, ks.LENGTH, T / n, n, save_every=n)[-1] - ref).max()) for n in steps]
        out[f"{nu:g}"] = {"dt": [T / n for n in steps], "max_error": errors,
                          "ratio": [errors[i] / errors[i + 1] for i in range(len(steps) - 1)],
                          "max_abs_u": float(np.abs(ref).max())}
        print(f"time convergence nu={nu}: {json.dumps(out[f'{nu:g}'])}", flush=True)
    return out


def grid_convergence(T: float = 5.0) -> dict[str, dict[str, list[float]]]:
    """Max error after ``T`` of coarser grids against 512 points (same start, truncated), and their spectral tail."""
    out = {}
    grids = [96, 128, 192, 256, 384]
    for nu in (0.5, 1.0):
        u0 = attractor_state(nu, 512)
        v0 = np.fft.rfft(u0)
        ref = ks.simulate(u0, nu, ks.LENGTH, 0.005, round(T / 0.005), save_every=round(T / 0.005))[-1]
        errors, tails = [], []
        for n_x in grids:
            start = np.fft.irfft(v0[: n_x // 2] * (n_x / 512), n=n_x)
            u = ks.simulate(start, nu, ks.LENGTH, 0.005, round(T / 0.005), save_every=round(T / 0.005))[-1]
            fine = np.zeros(257, dtype=complex)
            fine[: n_x // 2] = np.fft.rfft(u)[: n_x // 2] * (512 / n_x)
            errors.append(float(np.abs(np.fft.irfft(fine, n=512) - ref).max()))
            tails.append(ks.spectral_tail(u))
        out[f"{nu:g}"] = {"n_x": grids, "max_error": errors, "spectral_tail": tails}
        print(f"grid convergence nu={nu}: {json.dumps(out[f'{nu:g}'])}", flush=True)
    return out


def dop853_agreement() -> dict[str, dict[str, float]]:
    """Max distance between ETDRK4 and DOP853 (rtol = atol = 1e-12) on the full complex-FFT Fourier ODE."""
    out = {}
    for name, L, nu, n_x, T, n_steps, amplitude in (("L22_nx32_T2", 22.0, 1.0, 32, 2.0, 400, 2.0),
                                                     ("L60_nx128_T1_attractor", ks.LENGTH, 1.0, 128, 1.0, 400, None)):
        u0 = (amplitude * ks.initial_conditions(1, n_x, L, np.random.default_rng(3))[0] if amplitude
              else attractor_state(nu, n_x))
        k = 2 * math.pi / L * np.fft.fftfreq(n_x, 1 / n_x)
        k_odd = np.where(np.arange(n_x) == n_x // 2, 0.0, k)

        def rhs(_: float, v: np.ndarray, k=k, k_odd=k_odd, nu=nu) -> np.ndarray:
            u = np.fft.ifft(v).real
            return (k**2 - nu * k**4) * v - 0.5j * k_odd * np.fft.fft(u * u)

        sol = solve_ivp(rhs, (0.0, T), np.fft.fft(u0).astype(complex), method="DOP853", rtol=1e-12, atol=1e-12)
        reference = np.fft.ifft(sol.y[:, -1]).real
        u = ks.simulate(u0, nu, L, T / n_steps, n_steps, save_every=n_steps)[-1]
        out[name] = {"max_difference": float(np.abs(u - reference).max()), "dt": T / n_steps,
                     "max_abs_u": float(np.abs(reference).max()), "dop853_rhs_evaluations": int(sol.nfev)}
        print(f"DOP853 {name}: {json.dumps(out[name])}", flush=True)
    return out


def generator_cost(repeats: int) -> dict[str, float]:
    """CPU time (minimum of ``repeats``) of the default ``trajectories()`` and of ``small_dataset()``.

    CPU time of this single-threaded process, not wall time: on a shared machine the wall time also counts
    the waits for a core.
    """
    out = {}
    for name, make in (("trajectories_default_cpu_seconds", ks.trajectories),
                       ("small_dataset_cpu_seconds", ks.small_dataset)):
        times = []
        for _ in range(repeats):
            start = time.process_time()
            make()
            times.append(time.process_time() - start)
        out[name] = min(times)
    print(f"cost: {json.dumps(out)}", flush=True)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("validation/results/kuramoto_sivashinsky.json"))
    parser.add_argument("--l22-seeds", type=int, default=8)
    parser.add_argument("--l22-time", type=float, default=10000.0)
    parser.add_argument("--scan-seeds", type=int, default=3)
    parser.add_argument("--scan-time", type=float, default=1500.0)
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    result = {
        "command": "OMP_NUM_THREADS=1 python validation/kuramoto_sivashinsky.py",
        "numpy": np.__version__,
        "machine": platform.machine(),
        "lyapunov_l22": lyapunov_l22(args.l22_seeds, args.l22_time),
        "time_convergence": time_convergence(),
        "grid_convergence": grid_convergence(),
        "dop853": dop853_agreement(),
        "generator_cost": generator_cost(args.repeats),
        "lyapunov_data_range": lyapunov_data_range(np.linspace(*ks.NU_RANGE, 6), args.scan_seeds, args.scan_time),
        "lyapunov_scan_l_eff": lyapunov_scan(np.arange(14.0, 87.0, 1.0), args.scan_seeds, args.scan_time),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
