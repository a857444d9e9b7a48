"""Your own estimator under the protocol: ridge regression from the standardized readings of the current frame to
the leading POD coefficients of the training fields, scored on Burgers beside the calibrated Koopman EKF.

``python examples/ridge_estimator.py [--out FOLDER]`` (seconds; generates the Burgers data if missing, writes
FOLDER/results.json.gz when given). docs/estimators.md explains the interface.
"""
import sys
from pathlib import Path

import numpy as np

from dks_gym.dataset import DatasetMissing, generate_dataset, load_dataset
from dks_gym.evaluation.estimators import score_estimator
from dks_gym.evaluation.results import load_results, select


class Ridge:
    """estimate = mean field + POD modes @ (ridge weights @ standardized readings)."""

    def __init__(self, rank: int = 16, alpha: float = 1e-2) -> None:
        self.rank, self.alpha = rank, alpha

    def fit(self, train) -> None:
        fields = train.fields  # (N, n_t, C, *grid): the training split
        X = fields[:, 1:].reshape(-1, int(np.prod(train.field_shape)))  # the frames estimated (1..n_t-1)
        R = train.readings()[:, 1:].reshape(len(X), -1)  # their noisy readings, made as the test episodes' are
        self.mean, self.shape = X.mean(0), train.field_shape
        self.modes = np.linalg.svd(X - self.mean, full_matrices=False)[2][: self.rank]  # (rank, C * cells)
        self.r_mean, self.r_std = R.mean(0), R.std(0)
        Z = np.c_[(R - self.r_mean) / self.r_std, np.ones(len(R))]
        Y = (X - self.mean) @ self.modes.T  # the POD coefficients to predict
        self.W = np.linalg.solve(Z.T @ Z + self.alpha * len(Z) * np.eye(Z.shape[1]), Z.T @ Y)

    def estimate(self, readings, sensors, mu):
        z = np.append((readings[-1] - self.r_mean) / self.r_std, 1.0)  # the current frame's readings only
        return (self.mean + (z @ self.W) @ self.modes).reshape(self.shape)


def main(out: str | None = None) -> dict:
    try:
        load_dataset("burgers", "paper")
    except DatasetMissing:  # empty data home: solve Burgers for the paper's viscosities (seconds)
        generate_dataset("burgers", "paper", progress=False)
    doc = score_estimator(Ridge(), "burgers", name="ridge", out=out)
    ours = load_results(Path(__file__).resolve().parents[1] / "docs/results/burgers-lite-calibrated/results.json.gz")
    koopman = select(ours, experiment="calibrated", model="koopman", filter="ekf")[0]
    for label, rec in (("ridge", doc["records"][0]), ("Koopman calibrated EKF", koopman)):
        print(f"{label:24s} final relative L2 {rec['final_rel_l2_mean']:.3%}  MSE {rec['final_mse_mean']:.3e}")
    return doc


if __name__ == "__main__":
    main(sys.argv[sys.argv.index("--out") + 1] if "--out" in sys.argv else None)
