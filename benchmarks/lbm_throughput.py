"""Lattice updates per second of the batched lattice Boltzmann solver (dks_gym.solvers.lbm).

Times D2Q9 and D3Q19 steps (Smagorinsky-BGK, a bounce-back body, walls, velocity inlet, pressure
outlet: the sphere/cylinder configuration) at a few batch sizes on the current device and prints
MLUPS = million node updates per second summed over the batch. Writes
benchmarks/results/lbm_throughput_<device>.json.

    python benchmarks/lbm_throughput.py                      # CPU, eager and compiled
    python benchmarks/lbm_throughput.py --device cuda --batch 1 8 32 --shape3d 193 66 64
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np
import torch

from dks_gym.solvers import lbm


def _case(shape: tuple[int, ...]) -> dict:
    d = len(shape)
    solid = np.zeros(shape, bool)
    idx = [slice(None)] * d
    idx[1] = [0, -1]
    solid[tuple(idx)] = True
    grids = np.meshgrid(*[np.arange(n) for n in shape], indexing="ij")
    centre = [n / 3 if a == 0 else (n - 1) / 2 for a, n in enumerate(shape)]
    radius = shape[1] / 8
    body = sum((g - c) ** 2 for g, c in zip(grids, centre)) < radius**2
    solid |= body
    return {"solid": solid, "body": body, "inlet_velocity": [0.05] + [0.0] * (d - 1), "outlet": True}


def measure(lattice: str, shape: tuple[int, ...], batch: int, device: str, compile: bool, steps: int) -> dict:
    sim = lbm.LBM(lattice, shape, np.linspace(1e-3, 1e-2, batch), device=device, compile=compile, **_case(shape))
    t0 = time.perf_counter()
    sim.step(3)  # warm-up (and compilation)
    if sim.device.type == "cuda":
        torch.cuda.synchronize()
    warm = time.perf_counter() - t0
    t0 = time.perf_counter()
    sim.step(steps)
    if sim.device.type == "cuda":
        torch.cuda.synchronize()
    sec = time.perf_counter() - t0
    assert bool(sim.is_finite().all())
    n = int(np.prod(shape))
    return {"lattice": lattice, "shape": list(shape), "batch": batch, "compile": compile, "steps": steps,
            "seconds": sec, "warmup_seconds": warm, "mlups": lbm.mlups(batch, n, steps, sec),
            "bytes_per_case_estimate": lbm.bytes_per_case(lattice, shape, compiled=compile)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--batch", type=int, nargs="+", default=[1, 4])
    ap.add_argument("--shape2d", type=int, nargs=2, default=[193, 66])
    ap.add_argument("--shape3d", type=int, nargs=3, default=[97, 34, 32])
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--compile", choices=["both", "on", "off"], default="both")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    modes = {"both": [False, True], "on": [True], "off": [False]}[args.compile]
    rows = []
    for lattice, shape in (("D2Q9", tuple(args.shape2d)), ("D3Q19", tuple(args.shape3d))):
        for compile in modes:
            for b in args.batch:
                row = measure(lattice, shape, b, args.device, compile, args.steps)
                rows.append(row)
                print(f"{lattice} {'x'.join(map(str, shape))} batch {b:3d} compile {compile!s:5}: "
                      f"{row['mlups']:8.2f} MLUPS (warm-up {row['warmup_seconds']:.1f} s)", flush=True)
    dev = torch.device(args.device)
    name = torch.cuda.get_device_name(dev) if dev.type == "cuda" else (platform.processor() or platform.machine())
    result = {"device": str(dev), "device_name": name, "torch": torch.__version__,
              "threads": torch.get_num_threads(), "rows": rows}
    out = args.out or Path(__file__).parent / "results" / f"lbm_throughput_{dev.type}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
