"""Wrap DKS/Burgers-v0 with each latent model; print the final-time MSE of forward run, EKF and EnKF (test split).

Runs on a fresh clone: generates the Burgers data if missing (seconds). On the ``paper`` data it uses the lite
models that ship with dks-gym; on the ``small`` data it trains lite models for them if missing (minutes per model
on one CPU core, cached in the data home). ``python examples/filter_burgers.py [paper|small]``.
"""
import sys

import gymnasium as gym

import dks_gym  # noqa: F401  (registers the environments)
from dks_gym.dataset import DatasetMissing, generate_dataset, load_dataset
from dks_gym.models import ModelSpec
from dks_gym.names import FILTERS, MODEL_KINDS
from dks_gym.wrappers import LatentFilter


def main(preset: str = "paper") -> None:
    try:
        load_dataset("burgers", preset)
    except DatasetMissing:  # empty data home: solve Burgers for the preset's viscosities
        generate_dataset("burgers", preset)
    print(f"{'model':8s} {'forward':>10s} {'EKF':>10s} {'EnKF':>10s}")
    for model in MODEL_KINDS:
        row = []
        for filt in FILTERS:
            env = LatentFilter(gym.make("DKS/Burgers-v0", preset=preset),
                               model=ModelSpec(model, train_if_missing=True), filter=filt)
            finals = []
            for trajectory in range(env.unwrapped.dataset.n_trajectories("test")):
                env.reset(seed=0, options={"trajectory": trajectory})
                done = False
                while not done:
                    _, _, terminated, truncated, info = env.step(None)
                    done = terminated or truncated
                finals.append(info["mse"])
            row.append(sum(finals) / len(finals))
        print(f"{model:8s} " + " ".join(f"{e:10.3e}" for e in row))


if __name__ == "__main__":
    main(*sys.argv[1:])
