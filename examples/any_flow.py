"""End to end on a flow none of the four benchmarks is, the 1D Kuramoto-Sivashinsky equation: solve it, write it
in The Well's layout, import it, train the four lite latent models, rank sensor placements with each model's EKF
in the loop. The commands doing the same, and their numbers: docs/results/kuramoto-sivashinsky/README.md.

    python examples/any_flow.py OUT            # 44 trajectories, the lite schedules: about 10 minutes on a CPU core
    python examples/any_flow.py OUT --small    # 4 trajectories, 2 training steps, r = 4: seconds (the test runs it)
"""
import sys
from pathlib import Path

from dks_gym.assimilation import AssimilationConfig, tune_if_missing
from dks_gym.dataset import Dataset, import_the_well
from dks_gym.dataset.kuramoto_sivashinsky import generate_well_folder, write_well_folder
from dks_gym.models import train_model, training_schedule
from dks_gym.names import MODEL_KINDS
from dks_gym.solvers.kuramoto_sivashinsky import small_dataset
from dks_gym_agents import PlacementTask
from dks_gym_agents.evaluate import evaluate_placement
from dks_gym_agents.registry import DEFAULT_POLICIES


def main(out: Path, small: bool = False) -> dict[str, dict]:
    if small:  # 4 trajectories of 20 frames on 64 points; the middle two viscosities are the test split
        write_well_folder(small_dataset(), [1, 2], out / "well")
    else:  # 32 training and 12 test viscosities, one trajectory each, 100 frames on 64 points of L = 22
        generate_well_folder(out / "well")
    ds = Dataset(import_the_well(out / "well", out / "ks.h5"))  # a custom benchmark named "kuramoto_sivashinsky"
    r, steps, m, policies = (4, 2, 4, ["paper", "qr"]) if small else (32, None, 16, DEFAULT_POLICIES)
    rankings = {}
    for kind in MODEL_KINDS:  # koopman, pdmd, mlp, xlstm
        schedule = training_schedule(ds.benchmark, "lite", steps=steps)  # steps None: the lite 1D schedule
        model = train_model(ds.benchmark, kind, r, dataset=ds, schedule=schedule, progress=False).model
        tune_if_missing(model, ds, progress=False)  # the process-noise scale, as `dks-gym train` ends with
        task = PlacementTask(ds, model, AssimilationConfig().replace(kind="ekf", n_sensors=m))
        rankings[kind], _ = evaluate_placement(task, policies, out=out / kind)
    return rankings


if __name__ == "__main__":
    main(Path(sys.argv[1]), small="--small" in sys.argv)
