"""``dks-gym evaluate-placement``: a standalone click command (registered on ``dks-gym`` with ``main.add_command``)."""

from __future__ import annotations

from functools import partial
from pathlib import Path

import click

from dks_gym.benchmarks import BENCHMARKS
from dks_gym.names import FILTERS, MODEL_KINDS
from dks_gym.parallel import executor_options, open_executor

from .adaptive import PPOAdaptive
from .baselines import GREEDY_OBJECTIVES, GreedyLayout
from .policies import CONSTRAINTS
from .registry import POLICIES, PolicyFactory, random_layouts
from .sequential import SequentialLayout


@click.command("evaluate-placement")
@click.argument("benchmark", type=click.Choice(list(BENCHMARKS), case_sensitive=False), required=False)
@click.option("--data", "data_file", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="Rank on this file in the dks-gym HDF5 schema instead: your own flow (a custom benchmark, "
                   "BENCHMARK left out; its models trained by `dks-gym train --data FILE`) or one of the four's.")
@click.option("--policies", default="paper,random,qr,greedy", show_default=True,
              help=f"Comma-separated, from: {', '.join(POLICIES)}.")
@click.option("--model", type=click.Choice(list(MODEL_KINDS)), default="koopman", show_default=True)
@click.option("--r", "r", type=click.IntRange(min=1), default=32, show_default=True,
              help="Latent dimension of the model (as trained by `dks-gym train --r`).")
@click.option("--filter", "filter_", type=click.Choice(list(FILTERS)), default="ekf", show_default=True)
@click.option("--preset", type=click.Choice(["lite", "paper"]), default="lite", show_default=True,
              help="Latent model preset (checkpoint under $DKS_GYM_HOME/models).")
@click.option("--data-preset", type=click.Choice(["paper", "small"]), default="paper", show_default=True)
@click.option("--n-sensors", type=click.IntRange(min=1), default=16, show_default=True)
@click.option("--noise-level", type=click.FloatRange(min=0, min_open=True), default=0.2, show_default=True)
@click.option("--noise-seed", type=int, default=0, show_default=True,
              help="Seed of the measurement noise, shared by every policy.")
@click.option("--noise-seeds", type=click.IntRange(min=1), default=1, show_default=True,
              help="Noise realizations per test trajectory (seeds NOISE_SEED, NOISE_SEED + 1, ...).")
@click.option("--faults", default="none", show_default=True,
              help="Sensor faults in every test episode: 'none', 'default' (one reading in ten lost, each sensor "
                   "failing with probability 0.005 per step) or a JSON object of SensorFaults fields, e.g. "
                   "'{\"dropout\": 0.2, \"drift\": 0.01}'.")
@click.option("--constraint", default="fluid", show_default=True,
              help="Where sensors may go: 'fluid' (every fluid cell), 'surface' (fluid cells touching a solid "
                   "body), 'wall' (the domain's walls and the body surface) or a .npy file: a boolean keep-out "
                   "mask of the grid's shape (True = forbidden) or an integer array of allowed flat cells. The "
                   "paper layout moves to the nearest allowed cells.")
@click.option("--budgets", default=None,
              help="Comma-separated sensor counts, e.g. 2,4,8,16,32: one run per budget under OUT/m<m>, then "
                   "OUT/budgets.md and OUT/budgets.png (error vs budget); replaces --n-sensors.")
@click.option("--resume", is_flag=True,
              help="With --budgets: keep the budgets an earlier run with the same settings finished in OUT and run "
                   "the others (an interrupted sweep goes on; new budgets join the table).")
@click.option("--shred", default="",
              help="Comma-separated static policies of the run (e.g. qr) whose layout a SHRED baseline (a shallow "
                   "recurrent decoder from the readings to the field, no filter) is trained on and scored with: "
                   "a shred-<policy> row per policy.")
@click.option("--random-seeds", type=click.IntRange(min=1), default=5, show_default=True,
              help="How many seeded random layouts 'random' evaluates.")
@click.option("--greedy-candidates", type=click.IntRange(min=1), default=None,
              help="Size of the candidate lattice of the greedy policies (default: 32, or 2m when that is more).")
@click.option("--greedy-trajectories", type=click.IntRange(min=1), default=None,
              help="Training trajectories the greedy objective averages over (default: 4 for 'greedy', 10 for "
                   "'greedy-trace' and 'd-optimal').")
@click.option("--sequential", "sequential_ckpt", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Checkpoint (.zip) of 'sequential' (python -m dks_gym_agents.sequential); trained when absent.")
@click.option("--ppo", "ppo_ckpt", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Checkpoint (.zip) of 'ppo' (python -m dks_gym_agents.adaptive); trained when absent.")
@click.option("--agent-timesteps", type=click.IntRange(min=1), default=None,
              help="Training steps of learned policies trained here (default: each trainer's).")
@click.option("--device", default="cpu", show_default=True)
@click.option("--train-if-missing", is_flag=True, help="Train the latent model when its checkpoint is missing.")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Folder for placement.json.gz, placement.md and placement_layouts.png.")
@executor_options("the policies' fits and test runs and the SHRED trainings")
def evaluate_placement_command(benchmark: str | None, data_file: Path | None, policies: str, model: str, r: int,
                               filter_: str, preset: str,
                               data_preset: str, n_sensors: int, noise_level: float, noise_seed: int,
                               noise_seeds: int, faults: str, constraint: str, budgets: str | None,
                               resume: bool, shred: str, random_seeds: int,
                               greedy_candidates: int | None,
                               greedy_trajectories: int | None,
                               sequential_ckpt: Path | None, ppo_ckpt: Path | None, agent_timesteps: int | None,
                               device: str, train_if_missing: bool, out: Path, scheduler: str | None,
                               workers: int | None) -> None:
    """Rank sensor-placement POLICIES on BENCHMARK's test split (or --data FILE's) with a latent filter in the loop.

    Every policy is fitted on the training split, then run on every episode (each test trajectory under each
    of the NOISE_SEEDS noise realizations) with the same noise for all; writes a ranked table (final-time
    and time-averaged MSE, mean and std across episodes, paired comparisons with the paper layout and with
    the random layouts, costs), a layout figure and a results JSON. --workers N or --scheduler ADDRESS fit
    and run the policies on local processes or a Dask cluster, with the same results (docs/placement.md).
    """
    from dks_gym.dataset import DatasetMissing, SchemaError
    from dks_gym.evaluation.results import ResultsError
    from dks_gym.filters import FilterDivergence
    from dks_gym.models.checkpoint import CheckpointMissing

    from .budgets import evaluate_budgets
    from .evaluate import evaluate_placement
    from .policies import PlacementTask
    from .scenario import Scenario

    if benchmark is None and data_file is None:
        raise click.UsageError("name a BENCHMARK (burgers, cylinder, dambreak, sphere) or a schema file with --data")
    try:
        scenario = Scenario(noise_seeds=noise_seeds, faults=parse_faults(faults),
                            constraint=constraint if constraint in CONSTRAINTS else _load_array(constraint),
                            shred=[name.strip() for name in shred.split(",") if name.strip()])
        registry = policy_registry(random_seeds, greedy_candidates, greedy_trajectories, sequential_ckpt, ppo_ckpt,
                                   agent_timesteps)
        sweep = parse_budgets(budgets) if budgets is not None else None
        if resume and sweep is None:
            raise ValueError("--resume keeps the finished budgets of a --budgets sweep; give --budgets")
        task = PlacementTask.load(benchmark and benchmark.lower(), model, model_preset=preset,
                                  data_preset=data_preset, data_path=data_file, r=r,
                                  device=device, train_if_missing=train_if_missing, kind=filter_,
                                  n_sensors=n_sensors if sweep is None else min(sweep), noise_level=noise_level,
                                  noise_seed=noise_seed)
        with open_executor(scheduler, workers) as executor:
            if sweep is not None:
                evaluate_budgets(task, sweep, scenario, policies, registry=registry, out=out, resume=resume,
                                 log=click.echo, executor=executor)
            else:
                evaluate_placement(task, policies, scenario, registry=registry, out=out, log=click.echo,
                                   executor=executor)
    except (CheckpointMissing, DatasetMissing, SchemaError, ResultsError, FilterDivergence, FileNotFoundError,
            ValueError, ImportError) as exc:
        raise click.ClickException(str(exc)) from exc
    click.echo((out / ("budgets.md" if budgets is not None else "placement.md")).read_text())


def policy_registry(random_seeds: int, greedy_candidates: int | None, greedy_trajectories: int | None,
                    sequential: Path | None, ppo: Path | None, agent_timesteps: int | None) -> dict[str, PolicyFactory]:
    """The named policies with the knobs of the command's options bound (:data:`~dks_gym_agents.registry.POLICIES`)."""
    steps = {} if agent_timesteps is None else {"timesteps": int(agent_timesteps)}
    greedy = {"n_candidates": greedy_candidates, "n_trajectories": greedy_trajectories}
    return {**POLICIES, "random": partial(random_layouts, random_seeds),
            **{name: partial(GreedyLayout, objective, **greedy) for objective, name in GREEDY_OBJECTIVES.items()},
            "sequential": partial(SequentialLayout, sequential, **steps), "ppo": partial(PPOAdaptive, ppo, **steps)}


def parse_faults(text: str) -> str | dict | None:
    """'none', 'default' or a JSON object of SensorFaults fields, as a Scenario takes it."""
    import json

    if text in ("none", "default"):
        return None if text == "none" else text
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"--faults must be 'none', 'default' or a JSON object of SensorFaults fields, got "
                         f"{text!r} ({exc.msg})") from exc
    if not isinstance(value, dict):
        raise ValueError(f"--faults JSON must be an object such as '{{\"dropout\": 0.1}}', got {text!r}")
    from dks_gym.envs import SensorFaults

    SensorFaults.from_any(value)  # unknown names and bad values fail here, before any work
    return value


def _load_array(path: str):
    """A keep-out mask or an array of allowed cells from a .npy file."""
    import numpy as np

    if not Path(path).is_file():
        raise ValueError(f"--constraint must be one of {', '.join(CONSTRAINTS)} or a .npy file, and {path!r} is "
                         "no file")
    return np.load(path, allow_pickle=False)


def parse_budgets(text: str) -> list[int]:
    """'2,4,8' -> [2, 4, 8], refusing anything but positive integers."""
    try:
        budgets = [int(part) for part in text.split(",") if part.strip()]
    except ValueError as exc:
        raise ValueError(f"--budgets must be comma-separated positive integers such as 2,4,8,16, got {text!r}") \
            from exc
    if not budgets or min(budgets) < 1:
        raise ValueError(f"--budgets must be comma-separated positive integers such as 2,4,8,16, got {text!r}")
    return budgets
