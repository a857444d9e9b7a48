"""Does a change to the filters move the EKF by round-off only? Run this on the tree before and after, compare.

EKF episodes of the shipped lite Koopman, MLP and pDMD models on 8 Burgers ``paper`` trajectories (the vector
env, both initial conditions with their default Q and P0, 60 steps, one torch thread); every step's mean and
covariance are saved. ``--compare`` prints, for each model and initial condition, the largest difference to
another run over all steps, relative to that step's largest entry. Needs the Burgers ``paper`` data and the
shipped models (``dks-gym data generate burgers``).

    PYTHONPATH=../before python validation/ekf_round_off.py --out /tmp/before.npz
    python validation/ekf_round_off.py --out /tmp/after.npz --compare /tmp/before.npz
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from dks_gym.assimilation import FilterConfig
from dks_gym.wrappers import LatentFilterVectorEnv


def episodes(n_envs: int = 8, steps: int = 60) -> dict[str, np.ndarray]:
    """Each model's and initial condition's EKF means ``(steps, B, r)`` and covariances ``(steps, B, r, r)``."""
    out = {}
    for model in ("koopman", "mlp", "pdmd"):
        for initial in ("approximate", "exact"):
            config = FilterConfig(kind="ekf", initial=initial)
            venv = LatentFilterVectorEnv("burgers", n_envs, model=model, config=config, uncertainty=False)
            venv.reset(seed=0)
            means, covs = [], []
            for _ in range(steps):
                venv.step(np.zeros(n_envs, dtype=np.int64))
                means.append(venv.filter.mean.numpy().copy())
                covs.append(venv.filter.cov.numpy().copy())
            out[f"{model}-{initial}-mean"], out[f"{model}-{initial}-cov"] = np.stack(means), np.stack(covs)
            venv.close()
    return out


def relative_difference(a: np.ndarray, b: np.ndarray) -> float:
    """The largest ``|a - b|`` over all steps, each step's relative to that step's largest ``|a|``."""
    axes = tuple(range(1, a.ndim))
    scale = np.abs(a).max(axis=axes, keepdims=True)
    return float((np.abs(a.astype(np.float64) - b) / scale).max())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", required=True, help="an .npz to write this tree's episodes to")
    parser.add_argument("--compare", help="an .npz another tree wrote: print the differences to it")
    args = parser.parse_args()
    torch.set_num_threads(1)
    ours = episodes()
    np.savez(args.out, **ours)
    if args.compare:
        other = np.load(args.compare)
        for key in ours:
            print(f"{key:28s} {relative_difference(other[key], ours[key]):.2e}")


if __name__ == "__main__":
    main()
