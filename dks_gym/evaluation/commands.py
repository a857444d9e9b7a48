"""Click commands ``reproduce``, ``compare``, ``demo``, ``expected`` and ``leaderboard`` (registered on
``dks-gym`` lazily)."""

from __future__ import annotations

from pathlib import Path

import click

from ..benchmarks import BENCHMARKS
from ..names import FILTERS, MODEL_KINDS
from ..parallel import executor_options, open_executor
from .reproduce import EXPERIMENTS


def _errors() -> tuple[type[BaseException], ...]:
    from ..benchmarks import GeneratorUnavailable
    from ..dataset import DatasetMissing, SchemaError
    from ..filters import FilterDivergence
    from ..home import DataHomeError
    from ..models.checkpoint import CheckpointMissing
    from .results import ResultsError

    return (CheckpointMissing, DatasetMissing, SchemaError, GeneratorUnavailable, DataHomeError, ResultsError,
            FilterDivergence, ValueError, ImportError)


@click.command("reproduce")
@click.argument("benchmark", type=click.Choice(list(BENCHMARKS), case_sensitive=False))
@click.option("--preset", type=click.Choice(["lite", "paper"]), default="lite", show_default=True,
              help="Model architecture and training schedule.")
@click.option("--device", type=click.Choice(["cpu", "cuda"]), default="cpu", show_default=True)
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Output folder (default: results/BENCHMARK-PRESET).")
@click.option("--only", "only", multiple=True, type=click.Choice(list(EXPERIMENTS)),
              help="Run only this experiment (repeatable). Default: all of them.")
@click.option("--model", "models", multiple=True, type=click.Choice(list(MODEL_KINDS)),
              help="Run only this model's runs (repeatable). Default: all four.")
@click.option("--data-preset", type=click.Choice(["paper", "small"]), default="paper", show_default=True,
              help="Dataset preset to evaluate on (and to train on when a model is missing).")
@click.option("--no-train", is_flag=True, help="Fail instead of training a missing model.")
@click.option("--skip-done", is_flag=True,
              help="Keep the runs already in OUT/results.json.gz instead of rerunning them (continue a stopped run).")
@click.option("--noise-seed", type=int, default=0, show_default=True, help="Seed of the measurement noise.")
@executor_options("the independent trainings and filter runs")
def reproduce_command(benchmark: str, preset: str, device: str, out: Path | None, only: tuple[str, ...],
                      models: tuple[str, ...], data_preset: str, no_train: bool, skip_done: bool,
                      noise_seed: int, scheduler: str | None, workers: int | None) -> None:
    """Run the paper's Section IV experiments on BENCHMARK; write results.json.gz, tables.md and figures/.

    Experiments: main (forward vs EKF, approximate and exact IC), enkf, ensemble (n = 20/40/64), noise
    (10%/30%), latent (r = 16/64), multistep (T = 2/4/8), operator_norm, timing, calibrated, parameter (mu
    known, estimated with the state, or at the prior's mean). Missing models
    are trained (finished trainings are reused, interrupted ones resumed). The results file is rewritten
    after every run; a rerun keeps the records of the experiments it does not run, and --skip-done continues
    an interrupted run with the runs still missing. --workers N or --scheduler ADDRESS spread the independent
    trainings and runs over local processes or a Dask cluster, with the same results (docs/reproduce.md).
    """
    from .reproduce import reproduce

    try:
        with open_executor(scheduler, workers) as executor:
            reproduce(benchmark.lower(), preset=preset, device=device, out=out, only=only or None,
                      models=models or None, data_preset=data_preset, train=not no_train, skip_done=skip_done,
                      noise_seed=noise_seed, log=click.echo, executor=executor)
    except _errors() as exc:
        raise click.ClickException(str(exc)) from exc


@click.command("compare")
@click.argument("a", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.argument("b", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--experiment", default=None, help="Only the records of this experiment.")
@click.option("--force", is_flag=True,
              help="Compare files made under different protocol settings (refused otherwise, naming the fields).")
def compare_command(a: Path, b: Path, experiment: str | None, force: bool) -> None:
    """Print the ratios B / A of final MSE, operator norm and DA-step time for the runs in both results files.

    Both files must name the same protocol (name, version, fields) and share its run settings (budget, seeds,
    faults, ...): otherwise the command stops and says which fields differ, unless --force.
    """
    from .comparison import compare, format_comparison
    from .results import ResultsError, load_results

    try:
        doc_a, doc_b = load_results(a), load_results(b)
        rows = compare(doc_a, doc_b, force=force)
    except ResultsError as exc:
        raise click.ClickException(str(exc)) from exc
    if experiment is not None:
        rows = [r for r in rows if r["experiment"] == experiment]
    click.echo(f"A = {a}\nB = {b}")
    click.echo(format_comparison(doc_a, doc_b, rows))


@click.command("demo")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Folder for the figure and the results file (default: $DKS_GYM_HOME/demo).")
@click.option("--device", type=click.Choice(["cpu", "cuda"]), default="cpu", show_default=True)
@click.option("--train", is_flag=True,
              help="Train and tune the four lite models into $DKS_GYM_HOME/models first (minutes per model) "
                   "instead of using the shipped ones.")
def demo_command(out: Path | None, device: str, train: bool) -> None:
    """Burgers end to end: data, four lite models, forward run / EKF / EnKF, a table and a figure."""
    from .demo import run_demo

    try:
        run_demo(out, device=device, train=train, log=click.echo)
    except _errors() as exc:
        raise click.ClickException(str(exc)) from exc


@click.command("expected")
@click.argument("benchmark", required=False, type=click.Choice(["burgers", "cylinder", "dambreak"],
                                                               case_sensitive=False))
@click.option("--check", is_flag=True,
              help="Rerun the table's runs with the shipped models on the local paper data and compare (exit 1 on "
                   "a difference in the third significant digit).")
@click.option("--markdown", is_flag=True, help="Print docs/results/expected.md (every benchmark).")
@click.option("--device", type=click.Choice(["cpu", "cuda"]), default="cpu", show_default=True)
def expected_command(benchmark: str | None, check: bool, markdown: bool, device: str) -> None:
    """Print the shipped models' expected scores under BENCHMARK's protocol; --check reruns and compares them.

    Relative L2 error of the final frame (mean over the test trajectories, 95 % bootstrap interval), its score
    and the 95 % coverage of the predictive std, for each model and filter (calibrated Q and P0, EnKF n = 20).
    """
    from tqdm.auto import tqdm

    from ..dataset import load_dataset
    from .expected import compare_expected, expected_markdown, expected_table, measure_expected, scores_of

    if markdown or benchmark is None:
        if check:
            raise click.UsageError("--check needs a BENCHMARK")
        click.echo(expected_markdown(), nl=False)
        return
    benchmark = benchmark.lower()
    if not check:
        click.echo(expected_table(benchmark))
        return
    try:
        ds = load_dataset(benchmark, "paper")
        bar = tqdm(total=len(MODEL_KINDS) * len(FILTERS), desc=f"{benchmark}: shipped models x filters", unit="run")
        records = measure_expected(benchmark, ds, device=device, on_record=lambda rec: bar.update(1))
        bar.close()
    except _errors() as exc:
        raise click.ClickException(str(exc)) from exc
    measured = scores_of(records)
    click.echo(expected_table(benchmark, measured))
    mismatches = compare_expected(benchmark, measured)
    for mismatch in mismatches:
        click.echo(f"MISMATCH {mismatch}")
    click.echo(f"{benchmark}: {'reproduces' if not mismatches else 'does NOT reproduce'} the expected scores "
               f"({len(mismatches)} numbers differ beyond the third significant digit)")
    if mismatches:
        raise SystemExit(1)


@click.command("leaderboard")
@click.argument("results", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Write the page here (e.g. docs/results/leaderboard.md) instead of printing it.")
def leaderboard_command(results: tuple[Path, ...], out: Path | None) -> None:
    """Rank the runs of results files (or their folders) made under the protocol: one table per benchmark.

    Rows: each latent model under each filter of a reproduce file (its calibrated experiment, else main and
    enkf) and every estimator scored by dks_gym.evaluation.estimators; files or runs that leave the protocol
    are listed as not ranked, with the reason.
    """
    from .leaderboard import leaderboard_page, write_leaderboard
    from .results import ResultsError

    try:
        if out is None:
            click.echo(leaderboard_page(results), nl=False)
        else:
            click.echo(f"wrote {write_leaderboard(results, out)}")
    except (ResultsError, ValueError) as exc:
        raise click.ClickException(str(exc)) from exc


COMMANDS = (reproduce_command, compare_command, demo_command, expected_command, leaderboard_command)

__all__ = ["COMMANDS", "compare_command", "demo_command", "expected_command", "leaderboard_command",
           "reproduce_command"]
