"""The calibrated Koopman EKF's estimate, truth and +-2 std band on one Burgers test trajectory.

    python examples/uncertainty_burgers.py [OUT.png]      # default uncertainty_burgers.png

Needs the Burgers `paper` data and the lite Koopman model (`dks-gym train burgers --model koopman`; trained
here when missing). Prints the 95 % coverage and the MSE at the plotted steps.
"""

from __future__ import annotations

import sys

import gymnasium as gym
import numpy as np

import dks_gym  # noqa: F401  (registers the environments)
from dks_gym import LatentFilter
from dks_gym.dataset import generate_dataset
from dks_gym.evaluation.figures import uncertainty_figure

STEPS = (1, 20, 99)


def main(out: str = "uncertainty_burgers.png") -> None:
    generate_dataset("burgers", "paper")
    env = LatentFilter(gym.make("DKS/Burgers-v0", split="test"), model="koopman", filter="ekf",
                       train_if_missing=True)
    env.reset(seed=0, options={"trajectory": 0})
    kept = {"estimate": [], "estimate_std": [], "truth": []}
    for step in range(1, max(STEPS) + 1):
        _, _, _, _, info = env.step(None)
        if step in STEPS:
            kept["estimate"].append(info["estimate"])
            kept["estimate_std"].append(info["estimate_std"])
            kept["truth"].append(env.unwrapped.true_state)
            print(f"step {step:3d}: MSE {info['mse']:.2e}, 95% coverage {info['coverage']:.2f}")
    bench = env.unwrapped.benchmark
    path = uncertainty_figure(np.stack(kept["estimate"]), np.stack(kept["estimate_std"]), np.stack(kept["truth"]),
                              bench.coords(), out, steps=STEPS, channel_name="u",
                              title="Burgers, test trajectory 0: lite Koopman, calibrated EKF, 16 sensors, 20% noise")
    print(f"wrote {path}")


if __name__ == "__main__":
    main(*sys.argv[1:])
