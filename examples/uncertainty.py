"""The calibrated Koopman EKF's predictive std against its error on one test trajectory of a benchmark.

    python examples/uncertainty.py                                   # Burgers: estimate, truth, +-2 std band
    python examples/uncertainty.py dambreak --channel alpha.water    # 2D: std map beside the error map
    python examples/uncertainty.py BENCHMARK --steps 1 20 99 --out OUT.png

Needs the benchmark's `paper` data (generated here when missing; the cylinder takes about 43 min) and the lite
Koopman model (trained here when missing: about 8 min for Burgers, 5 min for the dambreak). Prints the MSE and
the 95 % coverage at the plotted steps.
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np

import dks_gym  # noqa: F401  (registers the environments)
from dks_gym import LatentFilter, ModelSpec
from dks_gym.dataset import generate_dataset
from dks_gym.evaluation.figures import uncertainty_figure

ENV_IDS = {"burgers": "DKS/Burgers-v0", "cylinder": "DKS/Cylinder-v0", "dambreak": "DKS/Dambreak-v0"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("benchmark", nargs="?", default="burgers", choices=sorted(ENV_IDS))
    ap.add_argument("--channel", default=None, help="channel to draw (default: the observed one)")
    ap.add_argument("--steps", type=int, nargs="+", default=None,
                    help="frames to draw (default 1 20 99 in 1D, 10 99 in 2D)")
    ap.add_argument("--out", default=None, help="figure path (default uncertainty_BENCHMARK.png)")
    args = ap.parse_args()
    generate_dataset(args.benchmark, "paper")
    env = LatentFilter(gym.make(ENV_IDS[args.benchmark], split="test"),
                       model=ModelSpec("koopman", train_if_missing=True), filter="ekf")
    bench = env.unwrapped.benchmark
    channel = args.channel or bench.observed_channel
    if channel not in bench.channels:
        raise SystemExit(f"{args.benchmark} has no channel {channel!r}; choose one of {', '.join(bench.channels)}")
    steps = args.steps or ((1, 20, 99) if len(bench.coords()) == 1 else (10, 99))
    env.reset(seed=0, options={"trajectory": 0})
    kept = {"estimate": [], "estimate_std": [], "truth": []}
    for step in range(1, max(steps) + 1):
        _, _, terminated, truncated, info = env.step(None)
        if step in steps:
            kept["estimate"].append(info["estimate"])
            kept["estimate_std"].append(info["estimate_std"])
            kept["truth"].append(env.unwrapped.true_state)
            print(f"step {step:3d}: MSE {info['mse']:.2e}, 95% coverage {info['coverage']:.2f}")
        if terminated or truncated:
            break
    out = args.out or f"uncertainty_{args.benchmark}.png"
    path = uncertainty_figure(np.stack(kept["estimate"]), np.stack(kept["estimate_std"]), np.stack(kept["truth"]),
                              bench.coords(), out, steps=steps[:len(kept["estimate"])],
                              channel=bench.channels.index(channel), channel_name=channel,
                              fluid_mask=bench.fluid_mask(),
                              title=f"{args.benchmark}, test trajectory 0: lite Koopman, calibrated EKF, "
                                    f"16 sensors, 20% noise")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
