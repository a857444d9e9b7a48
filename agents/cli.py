"""``dks-gym evaluate-placement``: a standalone click command (registered on ``dks-gym`` with ``main.add_command``)."""

from __future__ import annotations

from pathlib import Path

import click

from dks_gym.benchmarks import BENCHMARKS
from dks_gym.names import FILTERS, MODEL_KINDS

from .evaluate import POLICIES


@click.command("evaluate-placement")
@click.argument("benchmark", type=click.Choice(list(BENCHMARKS), case_sensitive=False))
@click.option("--policies", default="paper,random,qr,greedy", show_default=True,
              help=f"Comma-separated, from: {', '.join(POLICIES)}.")
@click.option("--model", type=click.Choice(list(MODEL_KINDS)), default="koopman", show_default=True)
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
@click.option("--random-seeds", type=click.IntRange(min=1), default=5, show_default=True,
              help="How many seeded random layouts 'random' evaluates.")
@click.option("--greedy-candidates", type=click.IntRange(min=1), default=32, show_default=True,
              help="Size of the candidate lattice of the greedy policies.")
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
              help="Folder for placement.json, placement.md and placement_layouts.png.")
def evaluate_placement_command(benchmark: str, policies: str, model: str, filter_: str, preset: str,
                               data_preset: str, n_sensors: int, noise_level: float, noise_seed: int,
                               noise_seeds: int, random_seeds: int, greedy_candidates: int,
                               greedy_trajectories: int | None,
                               sequential_ckpt: Path | None, ppo_ckpt: Path | None, agent_timesteps: int | None,
                               device: str, train_if_missing: bool, out: Path) -> None:
    """Rank sensor-placement POLICIES on BENCHMARK's test split with a latent filter in the loop.

    Every policy is fitted on the training split, then run on every episode (each test trajectory under each
    of the NOISE_SEEDS noise realizations) with the same noise for all; writes a ranked table (final-time
    and time-averaged MSE, mean and std across episodes, paired comparisons with the paper layout and with
    the random layouts, costs), a layout figure and a results JSON.
    """
    from dks_gym.dataset import DatasetMissing, SchemaError
    from dks_gym.evaluation.results import ResultsError
    from dks_gym.filters import FilterDivergence
    from dks_gym.models.checkpoint import CheckpointMissing

    from .evaluate import evaluate_placement

    try:
        evaluate_placement(
            benchmark.lower(), policies, model=model, filter=filter_, model_preset=preset, data_preset=data_preset,
            n_sensors=n_sensors, noise_level=noise_level, noise_seed=noise_seed, noise_seeds=noise_seeds,
            random_seeds=random_seeds,
            greedy_candidates=greedy_candidates, greedy_trajectories=greedy_trajectories,
            sequential=sequential_ckpt, ppo=ppo_ckpt, agent_timesteps=agent_timesteps, out=out, device=device,
            train_if_missing=train_if_missing, log=click.echo,
        )
    except (CheckpointMissing, DatasetMissing, SchemaError, ResultsError, FilterDivergence, FileNotFoundError,
            ValueError) as exc:
        raise click.ClickException(str(exc)) from exc
    click.echo((out / "placement.md").read_text())
