"""Rank sensor layouts on Burgers with a lite Koopman EKF in the loop: the paper layout, seeded random
layouts, QR pivoting on POD modes, the D-optimal layout and a custom policy, all under the same noise, then
again with the default sensor faults (a tenth of the readings lost, sensors failing for good)."""
import numpy as np

from dks_gym_agents import PlacementTask, StaticPolicy
from dks_gym_agents.evaluate import evaluate_placement


class LeftHalf(StaticPolicy):
    """A deliberately poor layout: m cells evenly spaced over the left half of the domain."""

    name = "left-half"

    def choose(self, task: PlacementTask) -> np.ndarray:
        cells = task.fluid_cells[: len(task.fluid_cells) // 2]
        return cells[np.linspace(0, len(cells) - 1, task.n_sensors).astype(int)]


task = PlacementTask.load("burgers", "koopman", model_preset="lite", kind="ekf", n_sensors=16, train_if_missing=True)
for faults in (None, "default"):
    _, results = evaluate_placement("burgers", ["paper", "random", "qr", "d-optimal", LeftHalf()], task=task,
                                    faults=faults, out=f"placement-burgers-{faults or 'no'}-faults")
    print(f"faults: {faults or 'none'}")
    for r in sorted(results, key=lambda r: r.time_mean_mse.mean()):
        print(f"  {r.name:12s} time-averaged MSE {r.time_mean_mse.mean():.3e} ± {r.time_mean_mse.std():.1e}")
