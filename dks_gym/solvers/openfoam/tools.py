"""The OpenFOAM executables: finding them, the environment they run in, running one with its log.

:func:`check_openfoam` finds the solvers and says how to install them when they are missing; :func:`foam_env`
is the environment they run in (Debian's ``openfoam`` package only needs ``WM_PROJECT_DIR``; its
``etc/bashrc`` is never sourced); :func:`run_tool` runs one utility or solver with its log in the case
directory and raises :class:`OpenFOAMError` quoting the log on failure.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from collections.abc import Sequence
from pathlib import Path

from ...benchmarks.base import GeneratorUnavailable

#: Where Debian's ``openfoam`` package installs its data files; override with ``$WM_PROJECT_DIR``.
DEFAULT_PROJECT_DIR = "/usr/share/openfoam"
#: The executables the dks-gym CFD generators call.
TOOLS = ("blockMesh", "setFields", "interFoam", "pimpleFoam", "foamDictionary", "postProcess")
INSTALL_HINT = (
    "install OpenFOAM so that blockMesh, setFields, interFoam, pimpleFoam, foamDictionary and postProcess "
    "are on PATH: on Debian or Ubuntu run `apt-get install -y openfoam` (v1912 is the tested version; "
    "no bashrc needs sourcing), elsewhere see https://www.openfoam.com/download"
)


class OpenFOAMMissing(GeneratorUnavailable):
    """OpenFOAM's executables are not on PATH; the message says how to install them."""


class OpenFOAMError(RuntimeError):
    """An OpenFOAM utility or solver failed; the message names the case and quotes its log."""


def find_tools(tools: Sequence[str] = TOOLS) -> dict[str, str | None]:
    """Path of every tool in ``tools`` on PATH, None where missing."""
    return {tool: shutil.which(tool) for tool in tools}


def check_openfoam(tools: Sequence[str] = TOOLS) -> None:
    """Raise :class:`OpenFOAMMissing` naming the missing tools and how to install them."""
    missing = [tool for tool, path in find_tools(tools).items() if path is None]
    if missing:
        raise OpenFOAMMissing(f"OpenFOAM is not installed (missing {', '.join(missing)}); {INSTALL_HINT}")


def foam_env() -> dict[str, str]:
    """Environment for OpenFOAM processes: ``WM_PROJECT_DIR`` set, one thread, no colour codes."""
    env = dict(os.environ)
    env.setdefault("WM_PROJECT_DIR", DEFAULT_PROJECT_DIR)
    env["OMP_NUM_THREADS"] = "1"
    # Floating-point exceptions abort the run instead of propagating NaNs into the data.
    env.setdefault("FOAM_SIGFPE", "true")
    return env


def doctor() -> dict[str, str | None]:
    """What the CFD generators need and where it is: each tool's path, OpenFOAM's version, fluidfoam's."""
    report: dict[str, str | None] = dict(find_tools())
    report["OpenFOAM version"] = openfoam_version()
    report["WM_PROJECT_DIR"] = foam_env()["WM_PROJECT_DIR"]
    try:
        import fluidfoam

        report["fluidfoam"] = getattr(fluidfoam, "__version__", "installed")
    except ImportError:
        report["fluidfoam"] = None
    return report


def openfoam_version() -> str | None:
    """OpenFOAM's version string as its tools report it (e.g. ``"OpenFOAM v1912 patch=200626"``), or None."""
    if shutil.which("foamDictionary") is None:
        return None
    try:
        out = subprocess.run(
            ["foamDictionary", "-help-full"], capture_output=True, text=True, env=foam_env(), timeout=30, check=False
        ).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    version = re.search(r"Using:\s*OpenFOAM\S*\s*\((\w+)\)", out)
    patch = re.search(r"Build:\s*\((patch=\w+)\)", out)
    if version is None:
        return None
    return f"OpenFOAM v{version.group(1)}" + (f" {patch.group(1)}" if patch else "")


def run_tool(case_dir: Path, tool: str, *args: str, log_name: str | None = None, timeout: float | None = None) -> Path:
    """Run ``tool -case case_dir *args`` with its output in ``case_dir/log.<name>``; return the log path.

    Raises :class:`OpenFOAMMissing` if the tool is not installed and :class:`OpenFOAMError` (quoting the
    end of the log) if it exits with an error or runs past ``timeout`` seconds.
    """
    if shutil.which(tool) is None:
        check_openfoam((tool,))
    case_dir = Path(case_dir)
    log = case_dir / f"log.{log_name or tool}"
    with open(log, "w") as out:
        try:
            proc = subprocess.run(
                [tool, "-case", str(case_dir), *args],
                stdout=out,
                stderr=subprocess.STDOUT,
                env={**foam_env(), "PWD": str(case_dir.resolve())},
                cwd=case_dir,
                timeout=timeout,
                check=False,
            )
        except subprocess.TimeoutExpired as exc:
            raise OpenFOAMError(f"{tool} ran past {timeout} s in {case_dir}; see {log}") from exc
    if proc.returncode != 0:
        tail = "".join(log.read_text(errors="replace").splitlines(keepends=True)[-25:])
        raise OpenFOAMError(f"{tool} failed with exit code {proc.returncode} in {case_dir}; log {log} ends:\n{tail}")
    return log


def solver_build(log: Path) -> str | None:
    """The ``Build`` line of an OpenFOAM log header (e.g. ``"OPENFOAM=1912 patch=200626"``)."""
    match = re.search(r"^Build\s*:\s*(.+)$", Path(log).read_text(errors="replace"), flags=re.MULTILINE)
    return match.group(1).strip() if match else None
