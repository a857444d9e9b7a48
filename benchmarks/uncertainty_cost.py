"""The cost of ``estimate_std``: wall time per wrapper step with ``uncertainty=True`` and ``False``.

Burgers (grid 1024), ``small`` data, lite models with r = 32 (untrained weights: the cost of a step does not
depend on them), 16 sensors, the paper's Q and P0, one torch thread. Per (model, filter, N): ``LatentFilter``
(N = 1) or the batched vector env (N > 1) is stepped over whole episodes (99 steps each, resets not timed) with the
uncertainty switched on and off, alternating rep by rep so that a neighbour's load hits both alike; the
JSON keeps every rep's median ms per step and the overhead ``on / off``. Rows with ``num_envs`` "split"
time ``run_assimilation`` over the whole test split as one batch (``wall_time / (n_t - 1)``: readings,
filter, decoding, scores). Writes benchmarks/results/uncertainty_cost_cpu.json.

The ``variance`` rows time ``jacobian_variance`` alone at B elements (``--batch``, random states and
covariances): the model's own rule (``decoder_variance``: the neural decoders linearized by hand, pDMD's
affine decoder), the ``r`` vmapped Jacobian-vector products it replaced, one decode, and the float32
product ``(1024 x 128) @ (128 x 32 B)`` (the Burgers lite decoder's last dense layer times every column of
every element: the floor of an exact push), interleaved rep by rep.

    OMP_NUM_THREADS=1 python benchmarks/uncertainty_cost.py --reps 3
    OMP_NUM_THREADS=1 python benchmarks/uncertainty_cost.py --models koopman pdmd --filters ekf enkf --envs 1 16
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch

import dks_gym  # noqa: F401  (registers the env ids)
from dks_gym.assimilation import AssimilationConfig, FilterConfig, jacobian_variance, run_assimilation
from dks_gym.assimilation.uncertainty import _jvp_variance
from dks_gym.atomic import atomic_write_text
from dks_gym.filters.covariance import psd_sqrt
from dks_gym.dataset import generate_dataset, load_dataset
from dks_gym.models import build_model
from dks_gym.wrappers import LatentFilter, LatentFilterVectorEnv

sys.path.insert(0, str(Path(__file__).parent))
from perf import median_ms  # noqa: E402  (the one timing helper of the benchmarks)


def _episode_step_ms(env, n_envs: int) -> float:
    """Median wall time of one step (ms) over one episode, after a reset."""
    env.reset(seed=0)
    times, done = [], False
    while not done:
        tic = time.perf_counter()
        if n_envs == 1:
            _, _, terminated, truncated, _ = env.step(None)
        else:
            _, _, terminated, truncated, _ = env.step(np.zeros(n_envs, dtype=np.int64))
            terminated, truncated = bool(np.all(terminated)), bool(np.all(truncated))
        times.append(time.perf_counter() - tic)
        done = terminated or truncated
    return 1e3 * float(np.median(times[:-1]))  # the last step of a vector env also resets the batch


def variance_row(model, kind: str, batch: int, reps: int) -> dict:
    """``jacobian_variance`` at ``batch`` elements: the model's own rule, the JVPs, a decode, the floor product."""
    g = torch.Generator().manual_seed(0)
    z, mu = 0.5 * torch.randn(batch, model.r, generator=g), torch.full((batch,), 0.5)
    M = torch.randn(batch, model.r, model.r, generator=g)
    P = M @ M.mT / model.r + 1e-3 * torch.eye(model.r)
    L = psd_sqrt(P)
    W, K = torch.randn(1024, 128, generator=g), torch.randn(128, model.r * batch, generator=g)
    fns = {"own_rule": lambda: jacobian_variance(model, z, mu, P), "jvp": lambda: _jvp_variance(model, z, mu, L),
           "decode": lambda: model.decode(z, mu), "floor_matmul": lambda: W @ K}
    times: dict = {name: [] for name in fns}
    with torch.no_grad():
        for _ in range(reps):
            for name, fn in fns.items():
                times[name].append(median_ms(fn, 1 if name == "jvp" else 3))
    med = {name: float(np.median(t)) for name, t in times.items()}
    return {"model": kind, "batch": batch, "ms": times,
            "own_rule_over_floor": med["own_rule"] / med["floor_matmul"],
            "jvp_over_own_rule": med["jvp"] / med["own_rule"], "own_rule_in_decodes": med["own_rule"] / med["decode"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", default=["koopman"])
    parser.add_argument("--filters", nargs="+", default=["ekf", "enkf", "forward"])
    parser.add_argument("--envs", nargs="+", type=int, default=[1, 16])
    parser.add_argument("--reps", type=int, default=3)
    parser.add_argument("--batch", type=int, default=256, help="elements of the 'variance' rows")
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "uncertainty_cost_cpu.json"))
    args = parser.parse_args()
    torch.set_num_threads(1)
    generate_dataset("burgers", "small", progress=False)
    ds = load_dataset("burgers", "small")
    rows, variance = [], []
    for kind in args.models:
        model = build_model("burgers", kind, 32, "lite", dataset=ds, seed=0)
        if kind == "pdmd":
            model.fit_dataset(ds)
        variance.append(variance_row(model, kind, args.batch, args.reps))
        v = variance[-1]
        print(f"{kind:8s} variance B={args.batch}: own rule {v['own_rule_over_floor']:.2f}x the floor product, "
              f"{v['own_rule_in_decodes']:.1f} decodes; the JVPs {v['jvp_over_own_rule']:.1f}x slower", flush=True)
        for filt in args.filters:
            for n in args.envs:
                envs = {}
                paper = FilterConfig(kind=filt, Q="paper", P0="paper")  # the untrained models have no calibrated Q
                for unc in (True, False):
                    if n == 1:
                        envs[unc] = LatentFilter(gym.make("DKS/Burgers-v0", preset="small"), model=model,
                                                 config=paper, uncertainty=unc)
                    else:
                        envs[unc] = LatentFilterVectorEnv("burgers", n, model=model, config=paper, uncertainty=unc,
                                                          preset="small")
                on, off = [], []
                for _ in range(args.reps):
                    on.append(_episode_step_ms(envs[True], n))
                    off.append(_episode_step_ms(envs[False], n))
                row = {"model": kind, "filter": filt, "num_envs": n, "ms_per_step_on": on, "ms_per_step_off": off,
                       "median_on": float(np.median(on)), "median_off": float(np.median(off)),
                       "overhead": float(np.median(on) / np.median(off))}
                rows.append(row)
                print(f"{kind:8s} {filt:8s} N={n:3d}: {row['median_on']:7.2f} ms/step with, "
                      f"{row['median_off']:7.2f} without ({row['overhead']:.2f}x)", flush=True)
                for e in envs.values():
                    e.close()
            on, off = [], []
            config = AssimilationConfig().replace(kind=filt, Q="paper", P0="paper")
            for _ in range(args.reps):
                for unc, times in ((True, on), (False, off)):
                    result = run_assimilation(model, ds, config, uncertainty=unc)
                    times.append(1e3 * result.wall_time / (ds.n_frames - 1))
            row = {"model": kind, "filter": filt, "num_envs": "split", "batch": ds.n_trajectories("test"),
                   "ms_per_step_on": on, "ms_per_step_off": off, "median_on": float(np.median(on)),
                   "median_off": float(np.median(off)), "overhead": float(np.median(on) / np.median(off))}
            rows.append(row)
            print(f"{kind:8s} {filt:8s} test split (B={row['batch']}): {row['median_on']:7.2f} ms/step with, "
                  f"{row['median_off']:7.2f} without ({row['overhead']:.2f}x)", flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    doc = {"benchmark": "burgers", "preset": "small", "r": 32, "model_preset": "lite", "n_sensors": 16,
           "torch_threads": 1, "torch": torch.__version__, "machine": platform.processor() or platform.machine(),
           "reps": args.reps, "rows": rows, "variance": variance}
    atomic_write_text(out, json.dumps(doc, indent=1) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
