"""The ``dks-gym`` command line."""

from __future__ import annotations

import importlib
import sys
import time
from pathlib import Path
from typing import Any

import click

from .benchmarks import BENCHMARKS, PRESETS, GeneratorUnavailable
from .names import MODEL_KINDS


def _plugin_commands() -> dict[str, Any]:
    """Commands other installed packages add through the ``dks_gym.commands`` entry-point group."""
    from importlib.metadata import entry_points

    return {ep.name: ep for ep in entry_points(group="dks_gym.commands")}


class _LazyGroup(click.Group):
    """The dks-gym group: commands defined in later layers (evaluation, the agents package) are imported only
    when invoked, so ``dks-gym --help`` and ``dks-gym data ...`` start without torch."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted({*super().list_commands(ctx), *LAZY_COMMANDS, *_plugin_commands()})

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name in self.commands:
            return self.commands[name]
        if name in LAZY_COMMANDS:
            module, attr = LAZY_COMMANDS[name][0].split(":")
            command = getattr(importlib.import_module(module), attr)
        elif name in (plugins := _plugin_commands()):
            command = plugins[name].load()
        else:
            return None
        self.add_command(command, name)
        return command

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        """The command list, with the short help of lazy commands taken from :data:`LAZY_COMMANDS`."""
        plugins = _plugin_commands()
        rows = []
        for name in self.list_commands(ctx):
            if name in self.commands:
                rows.append((name, self.commands[name].get_short_help_str(limit=formatter.width - 6 - len(name))))
            elif name in LAZY_COMMANDS:
                rows.append((name, LAZY_COMMANDS[name][1]))
            else:
                rows.append((name, f"from {plugins[name].value.split('.')[0]}; see dks-gym {name} --help"))
        if rows:
            with formatter.section("Commands"):
                formatter.write_dl(rows)


#: Commands of the evaluation layer: where each is defined and its one-line help (a test keeps them equal).
LAZY_COMMANDS = {
    "compare": ("dks_gym.evaluation.commands:compare_command",
                "Print the ratios B / A of final MSE, operator norm and DA-step time for the runs in..."),
    "demo": ("dks_gym.evaluation.commands:demo_command",
             "Burgers end to end: data, four lite models, forward run / EKF / EnKF, a table and a..."),
    "expected": ("dks_gym.evaluation.commands:expected_command",
                 "Print the shipped models' expected scores under BENCHMARK's protocol; --check reruns and..."),
    "leaderboard": ("dks_gym.evaluation.commands:leaderboard_command",
                    "Rank the runs of results files (or their folders) made under the protocol: one table..."),
    "reproduce": ("dks_gym.evaluation.commands:reproduce_command",
                  "Run the paper's Section IV experiments on BENCHMARK; write results.json.gz, tables.md and..."),
}


@click.group(cls=_LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="dks-gym")
@click.option("--threads", type=click.IntRange(min=1), default=None, metavar="N",
              help="Torch CPU threads for training and filtering (default: DKS_GYM_THREADS, OMP_NUM_THREADS, "
                   "else 1, the fastest measured on small CPUs; see docs/performance.md).")
def main(threads: int | None) -> None:
    """dks-gym: Gymnasium environments for sparse flow sensing (Deep Koopman Sensing)."""
    import logging

    from .threads import set_threads

    set_threads(threads)
    # The library logs what it is about to do (training a missing model ...) to the "dks_gym" logger; the
    # command line shows it, a Python caller decides with logging's own settings.
    log = logging.getLogger("dks_gym")
    if not log.handlers:
        handler = logging.StreamHandler()
        handler.setFormatter(logging.Formatter("dks-gym: %(message)s"))
        log.addHandler(handler)
        log.setLevel(logging.INFO)


@main.group()
def data() -> None:
    """Generate, import and inspect benchmark datasets."""


@data.command("generate")
@click.argument("benchmark", type=click.Choice(list(BENCHMARKS), case_sensitive=False))
@click.option("--preset", type=click.Choice(PRESETS), default="paper", show_default=True)
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the parameter sample.")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Output file (default: $DKS_GYM_HOME/data/BENCHMARK-PRESET.h5).")
@click.option("--overwrite", is_flag=True, help="Regenerate even if the file exists.")
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help="Parallel OpenFOAM runs for cylinder and dambreak (default 1).")
@click.option("--scheduler", default=None, metavar="ADDRESS",
              help="Run the OpenFOAM runs of cylinder and dambreak on the Dask cluster of this scheduler (e.g. "
                   "tcp://host:8786; pip install 'dks-gym[cluster]'); its workers must see the output's folder.")
@click.option("--device", default=None,
              help="Torch device of the burgers and sphere solvers: cpu (default), cuda or cuda:N.")
@click.option("--force", is_flag=True, help="Run a preset that needs a GPU on the CPU anyway (days for the sphere).")
def data_generate(benchmark: str, preset: str, seed: int, out: Path | None, overwrite: bool,
                  workers: int | None, scheduler: str | None, device: str | None, force: bool) -> None:
    """Generate BENCHMARK's dataset (burgers, cylinder, dambreak, sphere).

    Prints what the run will cost before it starts. The CFD benchmarks cache their OpenFOAM runs in
    FILE.work next to the output: an interrupted generation resumes when rerun, and the folder is deleted
    once the file is written.
    """
    from .dataset import Dataset, generate_dataset
    from .home import DataHomeError, dataset_path
    from .parallel import open_executor
    from .solvers.openfoam import OpenFOAMError

    benchmark = benchmark.lower()
    options = {}
    openfoam = benchmark in ("cylinder", "dambreak")
    for name, value in (("--workers", workers), ("--scheduler", scheduler)):
        if value is not None and not openfoam:
            raise click.UsageError(f"{name} is for the OpenFOAM benchmarks (cylinder, dambreak); "
                                   f"{benchmark} is one batched torch solve (see --device)")
    if workers is not None and scheduler is not None:
        raise click.UsageError("give --scheduler (a Dask cluster) or --workers (local processes), not both")
    if workers is not None:
        options["workers"] = workers
    if device is not None:
        if openfoam:
            raise click.UsageError(f"--device is for the torch solvers (burgers, sphere); {benchmark} runs "
                                   "OpenFOAM on the CPU (see --workers)")
        options["device"] = device
    cost = BENCHMARKS[benchmark].generation_costs.get(preset)
    target = out if out is not None else dataset_path(benchmark, preset)
    if cost is not None and not (target.exists() and not overwrite):
        on_cpu = device is None or device == "cpu"
        if cost.gpu and on_cpu and not force:
            raise click.UsageError(
                f"the {benchmark} {preset} preset is meant for a GPU: {cost.time}. Run it with --device cuda on a "
                f"machine with a CUDA GPU, use --preset small to try the benchmark (a "
                f"{BENCHMARKS[benchmark].generation_costs['small'].time} run), or add --force to run it on the CPU."
            )
        click.echo(f"generating {benchmark} {preset}: expect {cost.describe()}", err=True)
    start = time.perf_counter()
    try:
        with open_executor(scheduler) as executor:
            if executor is not None:
                options["executor"] = executor
            path = generate_dataset(benchmark, preset, path=out, seed=seed, overwrite=overwrite, **options)
    except (GeneratorUnavailable, DataHomeError, OpenFOAMError, ValueError) as exc:
        raise click.ClickException(str(exc)) from exc
    with Dataset(path) as ds:
        click.echo(ds.summary())
    click.echo(f"done in {time.perf_counter() - start:.1f} s: {path}")


@data.command("kuramoto-sivashinsky")
@click.argument("folder", type=click.Path(file_okay=False, path_type=Path))
@click.option("--n-train", type=click.IntRange(min=2), default=32, show_default=True, help="Training viscosities.")
@click.option("--n-test", type=click.IntRange(min=1), default=12, show_default=True,
              help="Test viscosities, each between two training ones.")
@click.option("--per-value", type=click.IntRange(min=1), default=1, show_default=True,
              help="Trajectories (random initial conditions) per viscosity (pDMD needs 1: distinct values).")
@click.option("--frames", type=click.IntRange(min=2), default=100, show_default=True, help="Frames, 0.5 apart.")
@click.option("--points", type=click.IntRange(min=4), default=64, show_default=True, help="Grid points on [0, L).")
@click.option("--length", type=click.FloatRange(min=0, min_open=True), help="Domain length L [default: 22].")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the initial conditions.")
def data_kuramoto_sivashinsky(folder: Path, n_train: int, n_test: int, per_value: int, frames: int, points: int,
                              length: float | None, seed: int) -> None:
    """Solve the 1D Kuramoto-Sivashinsky equation and write the trajectories in The Well's layout in FOLDER.

    A flow none of the four (docs/envs.md, "End to end"); `dks-gym data import the-well FOLDER --out FILE`."""
    from .dataset.kuramoto_sivashinsky import generate_well_folder

    try:
        files = generate_well_folder(folder, n_train=n_train, n_test=n_test, per_value=per_value, n_t=frames,
                                     n_x=points, seed=seed, **({} if length is None else {"L": length}))
    except (ValueError, FileExistsError, FloatingPointError) as exc:
        raise click.ClickException(str(exc)) from exc
    click.echo(", ".join(f"{len(v)} {k} files" for k, v in files.items()) + f" -> {folder}")


@data.command("info")
@click.argument("file", type=click.Path(exists=True, dir_okay=False, path_type=Path))
def data_info(file: Path) -> None:
    """Validate FILE against the dks-gym HDF5 schema and describe it."""
    from .dataset import Dataset, SchemaError

    try:
        with Dataset(file) as ds:
            click.echo(ds.summary())
    except SchemaError as exc:
        click.echo(f"invalid dataset: {exc}", err=True)
        sys.exit(1)


@data.group("import")
def data_import() -> None:
    """Convert another collection's files into one dks-gym schema file (docs/envs.md, "Your own flow")."""


def _imported(run: Any, out: Path) -> None:
    """Run an import, turning its errors into clean messages, and say what was written."""
    import h5py

    from .dataset.importing import LayoutError
    from .home import DataHomeError

    try:
        run()
    except (LayoutError, ValueError, FileExistsError, RuntimeError, DataHomeError) as exc:
        raise click.ClickException(str(exc)) from exc
    with h5py.File(out, "r") as f:
        counts = ", ".join(f"{f[s]['params'].shape[0]} {s}" for s in ("train", "test"))
        click.echo(f"imported {counts} trajectories of {f.attrs['benchmark']} (channels "
                   f"{', '.join(f.attrs['channels'])}, grid {' x '.join(map(str, f['train/fields'].shape[3:]))}, "
                   f"dt {f.attrs['dt']:g}) -> {out}; `dks-gym data info {out}` describes it")


@data_import.command("the-well")
@click.argument("folder", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), required=True, help="The schema file to write.")
@click.option("--param", default=None, help="The simulation parameter to keep (default: the one that varies).")
@click.option("--valid", type=click.Choice(["train", "drop"]), default="train", show_default=True,
              help="Append The Well's valid split to train, or drop it.")
@click.option("--observed", default=None, help="The observed channel (default: the first).")
@click.option("--name", default=None, help="The benchmark name (default: the files' dataset_name).")
@click.option("--overwrite", is_flag=True, help="Replace --out if it exists.")
def import_the_well_command(folder: Path, out: Path, param: str | None, valid: str, observed: str | None,
                            name: str | None, overwrite: bool) -> None:
    """Import a dataset folder of The Well.

    FOLDER holds The Well's files in data/train, data/valid and data/test (or train, valid, test); they
    become one schema file: the time-varying fields are the channels (a vector field's components
    channels of their own), the varying simulation parameter the parameter."""
    from .dataset.the_well import import_the_well

    _imported(lambda: import_the_well(folder, out, param=param, valid=valid, observed=observed, name=name,
                                      overwrite=overwrite), out)


@data_import.command("pdebench")
@click.argument("files", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), required=True, help="The schema file to write.")
@click.option("--test", "test", multiple=True, type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="A file (viscosity) held out as the test split; repeat for several.")
@click.option("--test-fraction", type=float, default=None,
              help="Without --test: the share of each file's first trajectories held out (PDEBench's 0.1).")
@click.option("--max-per-file", type=click.IntRange(min=1), default=None, help="Keep each file's first N trajectories.")
@click.option("--name", default="pdebench_burgers", show_default=True, help="The benchmark name.")
@click.option("--overwrite", is_flag=True, help="Replace --out if it exists.")
def import_pdebench_command(files: tuple[Path, ...], out: Path, test: tuple[Path, ...], test_fraction: float | None,
                            max_per_file: int | None, name: str, overwrite: bool) -> None:
    """Import PDEBench 1D Burgers files.

    FILES are PDEBench's 1D_Burgers_Sols_Nu<value>.hdf5 (one viscosity each, the parameter nu); they become
    one schema file. The test split is the --test files, or else the first tenth of each file (PDEBench's)."""
    from .dataset.pdebench import import_pdebench

    _imported(lambda: import_pdebench(files, out, test=test, test_fraction=test_fraction, max_per_file=max_per_file,
                                      name=name, overwrite=overwrite), out)


#: Optional Python packages: (import name, distribution, what needs it, pip extra).
_OPTIONAL_PACKAGES = (
    ("fluidfoam", "fluidfoam", "reading OpenFOAM output (cylinder, dambreak data)", "cfd"),
    ("dask", "dask", "Dask, for spreading OpenFOAM runs over a cluster", "cluster"),
    ("distributed", "distributed", "Dask's cluster executor (client.get_executor())", "cluster"),
    ("pydmd", "pydmd", "pDMD latent model", "models"),
    ("xlstm", "xlstm", "xLSTM latent model", "models"),
    ("stable_baselines3", "stable-baselines3", "RL sensor placement agents", "agents"),
)


@main.command("doctor")
def doctor() -> None:
    """Report which external tools and optional packages are present (OpenFOAM, CUDA, extras)."""
    import importlib
    from importlib import metadata

    from .solvers.openfoam import INSTALL_HINT, TOOLS
    from .solvers.openfoam import doctor as openfoam_report

    report = openfoam_report()
    click.echo("OpenFOAM (cylinder and dambreak generators):")
    version = report.get("OpenFOAM version")
    missing = [tool for tool in TOOLS if report.get(tool) is None]
    click.echo(f"  version: {version or 'not found'}   WM_PROJECT_DIR: {report.get('WM_PROJECT_DIR')}")
    for tool in TOOLS:
        click.echo(f"  {tool:<15} {report.get(tool) or 'MISSING'}")
    if missing:
        click.echo(f"  -> {INSTALL_HINT}")

    import torch

    click.echo(f"torch {torch.__version__}:")
    if torch.cuda.is_available():
        names = ", ".join(torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count()))
        click.echo(f"  CUDA available ({torch.version.cuda}): {names}")
    else:
        click.echo("  CUDA not available (CPU only)")

    click.echo("optional packages:")
    for module, dist, purpose, extra in _OPTIONAL_PACKAGES:
        try:
            importlib.import_module(module)
        except Exception as exc:  # noqa: BLE001 - any import failure means the feature is unavailable
            status = f"MISSING ({type(exc).__name__}) -> pip install 'dks-gym[{extra}]'"
        else:
            try:
                status = metadata.version(dist)
            except metadata.PackageNotFoundError:
                status = "installed"
        click.echo(f"  {dist:<18} {status:<12} {purpose}")


@main.command("train")
@click.argument("benchmark", type=click.Choice(list(BENCHMARKS), case_sensitive=False), required=False)
@click.option("--model", "model", type=click.Choice([*MODEL_KINDS, "all"]), default="all",
              show_default=True, help="Latent model to train; 'all' trains the four in turn.")
@click.option("--preset", type=click.Choice(["lite", "paper"]), default="lite", show_default=True,
              help="Architecture and schedule: the paper's, or narrow and CPU-trainable.")
@click.option("--r", "r", type=click.IntRange(min=1), default=32, show_default=True, help="Latent dimension.")
@click.option("--T", "T", type=click.IntRange(min=1), default=1, show_default=True,
              help="Training horizon (Eq. 11); 1 is the paper's one-step loss.")
@click.option("--steps", type=click.IntRange(min=1), default=None, help="Total Adam steps (default: the preset's).")
@click.option("--batch-size", type=click.IntRange(min=1), default=None, help="Batch size (default: the preset's).")
@click.option("--lr", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Adam learning rate (default: the preset's; paper 1e-4).")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the initial weights and the batches.")
@click.option("--device", default="cpu", show_default=True, help="cpu, cuda or cuda:N.")
@click.option("--data-preset", type=click.Choice(PRESETS), default="paper", show_default=True,
              help="Dataset to train on ($DKS_GYM_HOME/data/BENCHMARK-PRESET.h5).")
@click.option("--data", "data_file", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="Train on this file in the dks-gym HDF5 schema instead: your own flow (a custom benchmark, "
                   "BENCHMARK left out) or one of the four's.")
@click.option("--resume/--restart", default=True, show_default=True,
              help="Continue from an existing checkpoint, or start afresh and overwrite it.")
@click.option("--checkpoint-every", type=click.IntRange(min=1), default=None,
              help="Steps between checkpoints (default: a tenth of the steps, at most 1000).")
@click.option("--eval/--no-eval", "evaluate", default=True, show_default=True,
              help="Report the one-step error on the training data against predicting no change.")
@click.option("--progress/--no-progress", default=True, show_default=True, help="Show a progress bar.")
@click.option("--export", is_flag=True,
              help="Write the trained lite models into the package's shipped weights (dks_gym/models/weights/): "
                   "the step that regenerates the shipped files.")
def train(benchmark: str | None, model: str, preset: str, r: int, T: int, steps: int | None, batch_size: int | None,
          lr: float | None, seed: int, device: str, data_preset: str, data_file: Path | None, resume: bool,
          checkpoint_every: int | None, evaluate: bool, progress: bool, export: bool) -> None:
    """Train BENCHMARK's latent models into checkpoints under $DKS_GYM_HOME/models (pDMD: fit).

    With --data FILE, train on that schema file: a custom benchmark (your own flow, any grid; its encoder and
    decoder sized from the grid, docs/models.md) or one of the four's. The end of training tunes each model's
    process-noise scale (`dks-gym calibrate`), so that its checkpoint is ready for the filters."""
    from .assimilation import tune_if_missing
    from .home import DataHomeError
    from .models.shipped import export_model
    from .models import one_step_error, train_model, training_schedule

    kinds = list(MODEL_KINDS) if model == "all" else [model]
    ds = _training_data(benchmark, data_preset, data_file)
    for kind in kinds:
        try:
            result = train_model(
                ds.benchmark, kind, r, preset, T, dataset=ds,
                schedule=training_schedule(ds.benchmark, preset, steps=steps, batch_size=batch_size, lr=lr),
                seed=seed, device=device, resume=resume, checkpoint_every=checkpoint_every, progress=progress,
            )
        except (ValueError, DataHomeError) as exc:
            raise click.ClickException(str(exc)) from exc
        if result.loaded_only:
            line = f"{kind}: already trained, loaded in {result.wall_time_s:.1f} s"
        elif result.model.fitted_in_closed_form:
            line = f"{kind}: POD + parametric DMD fitted in {result.wall_time_s:.1f} s"
        else:
            line = (f"{kind}: {result.new_steps} steps in {result.wall_time_s:.1f} s "
                    f"({result.steps_done} in all)")
        if len(result.losses):
            line += f", final loss {result.losses[-1, 0]:.3e} (normalized)"
        if result.best_validation_loss is not None:
            line += (f", best validation loss {result.best_validation_loss:.3e}"
                     f"{' (stopped early)' if result.stopped_early else ''}")
        click.echo(f"{line} -> {result.path}")
        tune_if_missing(result.model, ds, progress=progress)
        if "Q_scale" in result.model.calibration:  # absent only without a calibrated Q (an older checkpoint)
            click.echo(f"  process-noise scale {float(result.model.calibration['Q_scale']):.3g} "
                       "(the EKF's 95 % intervals cover 95 % of the held-out frames)")
        if export:
            try:
                click.echo(f"  exported -> {export_model(result.path, ds)}")
            except ValueError as exc:
                raise click.ClickException(str(exc)) from exc
        if evaluate:
            err = one_step_error(result.model, ds)
            click.echo(
                f"  one-step MSE on {err['pairs']} training pairs: {err['model_mse']:.3e} "
                f"(persistence {err['persistence_mse']:.3e}, ratio {err['model_mse'] / err['persistence_mse']:.3g}; "
                f"reconstruction {err['reconstruction_mse']:.3e})"
            )


def _training_data(benchmark: str | None, data_preset: str, data_file: Path | None) -> Any:
    """The dataset `train` and `calibrate` work on: BENCHMARK's data-home file, or the schema file --data names
    (which must hold BENCHMARK when both are given)."""
    from .dataset import DatasetMissing, SchemaError, load_dataset

    if benchmark is None and data_file is None:
        raise click.UsageError("name a BENCHMARK (burgers, cylinder, dambreak, sphere) or a schema file with --data")
    try:
        return load_dataset(None if benchmark is None else benchmark.lower(), data_preset, data_file)
    except (DatasetMissing, SchemaError) as exc:
        raise click.ClickException(str(exc)) from exc


@main.command("calibrate")
@click.argument("benchmark", type=click.Choice(list(BENCHMARKS), case_sensitive=False), required=False)
@click.option("--model", "model", type=click.Choice([*MODEL_KINDS, "all"]), default="all", show_default=True,
              help="Latent model to tune; 'all' tunes the four in turn.")
@click.option("--preset", type=click.Choice(["lite", "paper"]), default="lite", show_default=True)
@click.option("--r", "r", type=click.IntRange(min=1), default=32, show_default=True, help="Latent dimension.")
@click.option("--T", "T", type=click.IntRange(min=1), default=1, show_default=True, help="Training horizon.")
@click.option("--data-preset", type=click.Choice(PRESETS), default="paper", show_default=True)
@click.option("--data", "data_file", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="The schema file the models were trained on (as for `dks-gym train --data`).")
@click.option("--progress/--no-progress", default=True, show_default=True, help="Show a progress bar.")
def calibrate(benchmark: str | None, model: str, preset: str, r: int, T: int, data_preset: str,
              data_file: Path | None, progress: bool) -> None:
    """Tune the process-noise scale of BENCHMARK's trained models (in $DKS_GYM_HOME/models) and store it.

    The scale of the calibrated Q that makes the EKF's 95 % intervals cover 95 % of the model's held-out
    frames (docs/filters.md). `dks-gym train` does it at the end of training; this command redoes it, for
    example for a checkpoint trained by an older dks-gym. The shipped models are tuned already."""
    from .assimilation import calibrate_process_noise
    from .models.checkpoint import CheckpointMissing, checkpoint_path
    from .models.lookup import load_model

    ds = _training_data(benchmark, data_preset, data_file)
    for kind in (list(MODEL_KINDS) if model == "all" else [model]):
        path = checkpoint_path(ds.benchmark, kind, preset, r, T, data_preset=ds.preset or "custom")
        try:
            latent = load_model(ds.benchmark, kind, r=r, preset=preset, T=T, dataset=ds, path=path)
        except (CheckpointMissing, ValueError) as exc:
            raise click.ClickException(str(exc)) from exc
        scale = calibrate_process_noise(latent, ds, progress=progress)
        click.echo(f"{kind}: process-noise scale {scale:.3g} -> {path}")


@main.command("models")
@click.option("--data/--no-data", "check_data", default=True, show_default=True,
              help="Check each shipped model against the local paper data, when present.")
def models_command(check_data: bool) -> None:
    """List the models shipped with dks-gym and whether the local data match the data they were trained on."""
    from .dataset import Dataset
    from .home import dataset_path
    from .models.shipped import data_fingerprint, fingerprint_differences, list_shipped

    shipped = list_shipped()
    if not shipped:
        click.echo("no shipped models in this installation")
        return
    datasets: dict[tuple[str, str], Any] = {}
    click.echo(f"{'file':<42}{'size':>9}  {'Q scale':>8}  local data")
    for item in shipped:
        fp = item.fingerprint
        key = (fp["benchmark"], fp["preset"])
        status = "not checked"
        if check_data:
            if key not in datasets:
                path = dataset_path(*key)
                datasets[key] = Dataset(path) if path.exists() else None
            ds = datasets[key]
            if ds is None:
                status = f"no data (`dks-gym data generate {key[0]}`)"
            else:
                diff = fingerprint_differences(fp, data_fingerprint(ds))
                status = "match" if not diff else "DIFFERENT: " + "; ".join(diff)
        scale = item.metadata.get("q_scale")
        size = f"{item.path.stat().st_size / 2**20:.1f} MiB"
        scale = "-" if scale is None else f"{scale:.3g}"
        click.echo(f"{item.path.name:<42}{size:>9}  {scale:>8}  {status}")
    for ds in datasets.values():
        if ds is not None:
            ds.close()


if __name__ == "__main__":  # pragma: no cover
    main()
