"""Rank sensor layouts on Burgers with a lite Koopman EKF in the loop: the paper layout, seeded random
layouts, QR pivoting on POD modes, the D-optimal layout and a custom policy, all under the same noise, in three
scenarios: no faults, the default sensor faults (a tenth of the readings lost, sensors failing for good), and a
keep-out zone (no sensor in the middle third of the domain). For budgets, pass the same policies to
dks_gym_agents.budgets.evaluate_budgets (your policy is fitted afresh at each budget)."""
import numpy as np

from dks_gym_agents import PlacementTask, StaticPolicy
from dks_gym_agents.evaluate import evaluate_placement
from dks_gym_agents.scenario import Scenario


class LeftHalf(StaticPolicy):
    """A deliberately poor layout: m cells evenly spaced over the left half of the cells it may use."""

    name = "left-half"

    def choose(self, task: PlacementTask) -> np.ndarray:
        cells = task.allowed_cells[: len(task.allowed_cells) // 2]  # allowed_cells honours the constraint
        return cells[np.linspace(0, len(cells) - 1, task.n_sensors).astype(int)]


task = PlacementTask.load("burgers", "koopman", model_preset="lite", kind="ekf", n_sensors=16, train_if_missing=True)
keep_out = np.zeros(task.benchmark.grid, dtype=bool)
keep_out[len(keep_out) // 3: 2 * len(keep_out) // 3] = True  # True = no sensor here
scenarios = {"no faults": Scenario(), "default faults": Scenario(faults="default"),
             "keep-out zone": Scenario(constraint=keep_out)}
for name, scenario in scenarios.items():
    _, results = evaluate_placement(task, ["paper", "random", "qr", "d-optimal", LeftHalf()], scenario,
                                    out=f"placement-burgers-{name.replace(' ', '-')}")
    print(name)
    for r in sorted(results, key=lambda r: r.time_mean_mse.mean()):
        print(f"  {r.name:12s} time-averaged MSE {r.time_mean_mse.mean():.3e} ± {r.time_mean_mse.std():.1e}")
