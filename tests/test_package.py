"""The package as a user meets it: a light import, a fast CLI listing, no top-level ``agents`` package."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

ROOT = Path(__file__).parents[1]


def _python(code: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True, timeout=120)


def test_import_registers_the_envs_without_torch(tmp_path: Path) -> None:
    """``import dks_gym`` registers the four ids (and their vector entry points) by string: no torch, no filters."""
    out = _python("import sys, gymnasium as gym, dks_gym\n"
                  "assert 'torch' not in sys.modules, 'torch imported'\n"
                  "assert not any(m.startswith(('dks_gym.filters', 'dks_gym.models')) for m in sys.modules)\n"
                  "for i in ('Burgers', 'Cylinder', 'Dambreak', 'Sphere'):\n"
                  "    spec = gym.spec(f'DKS/{i}-v0')\n"
                  "    assert spec.vector_entry_point == 'dks_gym.wrappers.vector:LatentFilterVectorEnv'\n"
                  "print(dks_gym.__version__)", tmp_path)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "0.1.0"


def test_top_level_exports_load_on_first_use(tmp_path: Path) -> None:
    out = _python("import dks_gym\n"
                  "from dks_gym import FilterConfig, LatentFilter, SensingEnv, load_model\n"
                  "from dks_gym.assimilation import FilterConfig as F\n"
                  "from dks_gym.wrappers import LatentFilter as L\n"
                  "assert FilterConfig is F and LatentFilter is L and callable(load_model)\n"
                  "print(sorted(set(dks_gym.__all__) - set(dir(dks_gym))))", tmp_path)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_agents_install_as_dks_gym_agents_only(tmp_path: Path) -> None:
    """Outside the source tree, ``agents`` is not importable (it would clash with other packages of that name)."""
    out = _python("import importlib.util\n"
                  "print(importlib.util.find_spec('agents') is None)\n"
                  "import dks_gym_agents\n"
                  "print(dks_gym_agents.PlacementTask.__module__)", tmp_path)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["True", "dks_gym_agents.policies"]


def test_pyproject_lists_every_package_folder() -> None:
    """The explicit package list (needed to install agents/ as dks_gym_agents) misses no subpackage."""
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    folders = {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "dks_gym").rglob("__init__.py")}
    assert set(config["packages"]) == folders | {"dks_gym_agents"}
    assert config["package-dir"] == {"dks_gym_agents": "agents"}


def test_cli_lists_lazy_commands_with_their_own_help_and_runs_them() -> None:
    """``dks-gym --help`` imports no later layer; the help it shows is the commands' own first line."""
    from dks_gym import cli

    runner = CliRunner()
    listing = runner.invoke(cli.main, ["--help"])
    assert listing.exit_code == 0, listing.output
    for name in [*cli.LAZY_COMMANDS, "evaluate-placement", "data", "train", "doctor"]:
        assert f"  {name}" in listing.output
    ctx = click.Context(cli.main)
    for name, (_, short) in cli.LAZY_COMMANDS.items():
        command = cli.main.get_command(ctx, name)
        assert command.get_short_help_str(limit=len(short)) == short, name
    placement = runner.invoke(cli.main, ["evaluate-placement", "--help"])
    assert placement.exit_code == 0 and "POLICIES" in placement.output


def test_cli_help_does_not_import_torch(tmp_path: Path) -> None:
    out = _python("import sys\nfrom click.testing import CliRunner\nfrom dks_gym.cli import main\n"
                  "r = CliRunner().invoke(main, ['--help'])\nassert r.exit_code == 0, r.output\n"
                  "print('torch' in sys.modules)", tmp_path)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"
