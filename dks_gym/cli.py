"""The ``dks-gym`` command line."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import click

from .benchmarks import BENCHMARKS, PRESETS, GeneratorUnavailable


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="dks-gym")
def main() -> None:
    """dks-gym: Gymnasium environments for sparse flow sensing (Deep Koopman Sensing)."""


@main.group()
def data() -> None:
    """Generate and inspect benchmark datasets."""


@data.command("generate")
@click.argument("benchmark", type=click.Choice(list(BENCHMARKS), case_sensitive=False))
@click.option("--preset", type=click.Choice(PRESETS), default="paper", show_default=True)
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the parameter sample.")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Output file (default: $DKS_GYM_HOME/data/BENCHMARK-PRESET.h5).")
@click.option("--overwrite", is_flag=True, help="Regenerate even if the file exists.")
def data_generate(benchmark: str, preset: str, seed: int, out: Path | None, overwrite: bool) -> None:
    """Generate BENCHMARK's dataset (burgers, cylinder, dambreak, sphere)."""
    from .dataset import Dataset, generate_dataset
    from .home import DataHomeError

    start = time.perf_counter()
    try:
        path = generate_dataset(benchmark.lower(), preset, path=out, seed=seed, overwrite=overwrite)
    except (GeneratorUnavailable, DataHomeError) as exc:
        raise click.ClickException(str(exc)) from exc
    with Dataset(path) as ds:
        click.echo(ds.summary())
    click.echo(f"done in {time.perf_counter() - start:.1f} s: {path}")


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


if __name__ == "__main__":  # pragma: no cover
    main()
