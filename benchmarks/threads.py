"""Torch CPU threads per task: each task timed at 1 and at N threads, side by side and interleaved.

Tasks, on the Burgers benchmark (grid 1024) with the ``lite`` models (untrained weights: the cost of a
step does not depend on them):

- ``train``: one Adam step at the lite batch size (the loss of Eq. 10), per model kind;
- ``ekf`` / ``enkf``: one data-assimilation step of the assimilation core (forecast, update, decode,
  score), 16 sensors, one episode at a time as ``LatentFilter`` runs it, per model kind.

The thread counts alternate rep by rep (1, N, 1, N, ...) so that a neighbour's load hits both alike; the
JSON keeps every rep's median and the ratio t(N) / t(1) per task. ``dks_gym.threads`` chooses its per-task
defaults from these ratios. Writes benchmarks/results/threads_cpu.json.

    python benchmarks/threads.py --reps 3                  # 1 vs 2 threads, idle machine
    python benchmarks/threads.py --reps 3 --busy 1         # the same beside one busy process (another job)
    python benchmarks/threads.py --threads 4 --reps 7

``--busy N`` starts N single-threaded processes doing matrix products for the whole run, a stand-in for
the other jobs of a shared machine; the default output name then ends in ``_busyN``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from dks_gym.assimilation import AssimilationConfig, run_assimilation
from dks_gym.dataset import generate_dataset, load_dataset
from dks_gym.models import build_model
from dks_gym.models import WindowSampler, training_loss, training_schedule
from dks_gym.names import MODEL_KINDS


def _train_step(kind: str, ds) -> Callable[[], None] | None:
    if kind == "pdmd":  # fitted in closed form: no training step
        return None
    model = build_model("burgers", kind, 32, "lite", dataset=ds, seed=0)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    sampler = WindowSampler(ds, 1, seed=0, in_memory=True, progress=False)
    batch = training_schedule("burgers", "lite").batch_size

    def step() -> None:
        x, mu = sampler.sample(batch)
        loss, _ = training_loss(model, x, mu)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    return step


def _da_step(kind: str, filt: str, ds) -> Callable[[], None]:
    model = build_model("burgers", kind, 32, "lite", dataset=ds, seed=0)
    if kind == "pdmd":
        model.fit_dataset(ds, seed=0)
    config = AssimilationConfig().replace(kind=filt, n_members=20, noise_level=0.2, n_sensors=16)

    def episode() -> None:
        run_assimilation(model, ds, config, trajectories=[0], progress=False)

    return episode


def timed(fn: Callable[[], None], threads: int, repeat: int) -> float:
    torch.set_num_threads(threads)
    fn()  # warm-up at this thread count
    t0 = time.perf_counter()
    for _ in range(repeat):
        fn()
    return (time.perf_counter() - t0) / repeat


BUSY_LOOP = ("import torch; torch.set_num_threads(1); a = torch.randn(512, 512)\n"
             "while True: a = (a @ a).tanh()")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2, help="the N compared with 1 (default 2)")
    ap.add_argument("--reps", type=int, default=5, help="interleaved repetitions (default 5)")
    ap.add_argument("--busy", type=int, default=0, help="single-threaded busy processes beside the run (default 0)")
    ap.add_argument("--out", default=None, help="JSON path (default benchmarks/results/threads_cpu[_busyN].json)")
    args = ap.parse_args()
    suffix = f"_busy{args.busy}" if args.busy else ""
    out = Path(args.out or Path(__file__).parent / "results" / f"threads_cpu{suffix}.json")
    busy = [subprocess.Popen([sys.executable, "-c", BUSY_LOOP]) for _ in range(args.busy)]
    try:
        results = measure(args.threads, args.reps)
    finally:
        for proc in busy:
            proc.kill()
    doc = {"benchmark": "threads", "threads": [1, args.threads], "reps": args.reps, "busy_processes": args.busy,
           "unit": "seconds per train step (train/*) or per 99-step episode (ekf/*, enkf/*)",
           "machine": {"cpu_count": os.cpu_count(), "platform": platform.platform(),
                       "python": sys.version.split()[0], "torch": torch.__version__},
           "command": "python benchmarks/threads.py " + " ".join(sys.argv[1:]),
           "results": results}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {out}")


def measure(threads: int, reps: int) -> dict[str, dict]:
    """Median seconds of every task at 1 and ``threads`` threads over ``reps`` interleaved repetitions."""
    ds = load_dataset("burgers", "small", generate_dataset("burgers", "small", progress=False))
    tasks: dict[str, tuple[Callable[[], None], int]] = {}
    for kind in MODEL_KINDS:
        train = _train_step(kind, ds)
        if train is not None:
            tasks[f"train/{kind}"] = (train, 5)
        for filt in ("ekf", "enkf"):
            tasks[f"{filt}/{kind}"] = (_da_step(kind, filt, ds), 1)  # one 99-step episode
    results = {}
    for name, (fn, repeat) in tasks.items():
        times: dict[int, list[float]] = {1: [], threads: []}
        for _ in range(reps):
            for n in (1, threads):
                times[n].append(timed(fn, n, repeat))
        t1, tn = float(np.median(times[1])), float(np.median(times[threads]))
        results[name] = {"seconds_1": t1, f"seconds_{threads}": tn, "ratio": tn / t1,
                         "reps_1": times[1], f"reps_{threads}": times[threads]}
        print(f"{name:<14} 1 thread {t1 * 1e3:9.1f} ms   {threads} threads {tn * 1e3:9.1f} ms   "
              f"ratio {tn / t1:5.2f}", flush=True)
    return results


if __name__ == "__main__":
    main()
