"""The package's import structure: layers import only their own or earlier stages, and nothing is circular.

Stages, in order (issue 14): 0 the top-level utilities (``dks_gym/home.py``, ``version.py``, ``atomic.py`` and
any other module directly under ``dks_gym/`` except ``cli.py``), then benchmarks, solvers, dataset,
envs, models, filters, assimilation, wrappers, evaluation, agents (the ``agents/`` folder, installed as
``dks_gym_agents``) and cli (``dks_gym/cli.py``). Every ``import`` and ``from ... import`` node counts, at
module level or inside a function (a lazy import still ties the two layers together), relative imports
resolved. ``dks_gym/__init__.py`` is the package's front: at module level it may import stage 0 and envs
(registering the env ids, by string entry point), and inside a module-level ``__getattr__`` anything (the
lazy exports); no other module may import it.

The checker reads the files with :mod:`ast` only (nothing is imported), so it runs in well under a second.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

STAGES = (
    "utilities", "benchmarks", "solvers", "dataset", "envs", "models", "filters", "assimilation", "wrappers",
    "evaluation", "agents", "cli",
)  # fmt: skip
ROOT = "dks_gym"
#: Top-level package names of the agents folder: its folder name and the name it is installed under.
AGENT_PACKAGES = ("agents", "dks_gym_agents")
#: Modules directly under dks_gym/ that are a stage of their own rather than stage-0 utilities (every other
#: stage, dataset included, is the package of its name: dks_gym/dataset/, dks_gym/envs/, ...).
TOP_LEVEL_STAGES = {"cli": "cli"}
#: What dks_gym/__init__.py may import outside a module-level __getattr__.
ROOT_EAGER_STAGES = ("utilities", "envs")


@dataclass(frozen=True)
class Edge:
    """One import statement: ``source`` imports ``target`` at ``path:line``; ``lazy_export`` marks imports
    inside the root package's module-level ``__getattr__``."""

    source: str
    target: str
    path: str
    line: int
    lazy_export: bool = False


def module_files(repo: Path) -> dict[str, Path]:
    """``{dotted module name: file}`` of every module of ``dks_gym/`` and ``agents/`` under ``repo``."""
    out = {}
    for package in (ROOT, "agents"):
        base = repo / package
        for path in sorted(base.rglob("*.py")) if base.is_dir() else []:
            parts = list(path.relative_to(repo).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join(parts)] = path
    return out


def stage_of(module: str) -> str | None:
    """The stage of a dotted module name, ``"root"`` for the package itself, None outside the project."""
    parts = module.split(".")
    if parts[0] in AGENT_PACKAGES:
        return "agents"
    if parts[0] != ROOT:
        return None
    if len(parts) == 1:
        return "root"
    return parts[1] if parts[1] in STAGES else TOP_LEVEL_STAGES.get(parts[1], "utilities")


def _canonical(module: str) -> str:
    """``module`` under the folder's name: ``dks_gym_agents.x`` (the installed name) is ``agents.x``."""
    head, dot, rest = module.partition(".")
    return "agents" + dot + rest if head == "dks_gym_agents" else module


def _resolve(module: str, is_package: bool, node: ast.ImportFrom) -> str:
    """The absolute module a ``from`` import names (relative levels resolved against ``module``)."""
    if node.level == 0:
        return _canonical(node.module or "")
    package = module.split(".") if is_package else module.split(".")[:-1]
    base = package[: len(package) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def import_edges(modules: dict[str, Path], repo: Path) -> list[Edge]:
    """Every import between project modules, with where it stands."""
    edges = []
    for module, path in modules.items():
        tree = ast.parse(path.read_text(), filename=str(path))
        lazy_lines: set[int] = set()
        if module == ROOT:  # imports inside the root's module-level __getattr__ are its lazy exports
            for node in tree.body:
                if isinstance(node, ast.FunctionDef) and node.name == "__getattr__":
                    lazy_lines.update(n.lineno for n in ast.walk(node) if isinstance(n, (ast.Import, ast.ImportFrom)))
        rel = str(path.relative_to(repo))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                targets = [_canonical(alias.name) for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = _resolve(module, path.name == "__init__.py", node)
                # `from pkg import name`: an edge to pkg.name where that is a module, to pkg otherwise.
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
            else:
                continue
            for target in dict.fromkeys(targets):
                if stage_of(target) is not None and target != module:
                    edges.append(Edge(module, target, rel, node.lineno, node.lineno in lazy_lines))
    return edges


def stage_violations(edges: list[Edge]) -> list[str]:
    """Imports of a later stage (or of the root package, or by the root beyond what it may import)."""
    out = []
    for e in edges:
        source, target = stage_of(e.source), stage_of(e.target)
        if source == "root":
            if e.lazy_export or target in ROOT_EAGER_STAGES:
                continue
            problem = f"the package root imports {target} at import time (allowed: {', '.join(ROOT_EAGER_STAGES)})"
        elif target == "root":
            problem = "imports the package root (import from the module that defines the name instead)"
        elif STAGES.index(target) > STAGES.index(source):
            problem = f"{source} imports the later stage {target}"
        else:
            continue
        out.append(f"{e.path}:{e.line}: {e.source} -> {e.target}: {problem}")
    return out


def cycles(edges: list[Edge]) -> list[str]:
    """Each group of mutually importing modules (a strongly connected component), with its imports."""
    graph: dict[str, set[str]] = {}
    for e in edges:
        graph.setdefault(e.source, set()).add(e.target)
        graph.setdefault(e.target, set())
    # Tarjan's algorithm, iterative so that a deep import chain cannot hit the recursion limit.
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    components: list[list[str]] = []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is None:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        components.append(sorted(component))
            elif child not in index:
                index[child] = low[child] = len(index)
                stack.append(child)
                on_stack.add(child)
                work.append((child, iter(sorted(graph[child]))))
            elif child in on_stack:
                low[node] = min(low[node], index[child])
    out = []
    for component in components:
        members = set(component)
        where = [f"{e.path}:{e.line} ({e.source} -> {e.target})" for e in edges
                 if e.source in members and e.target in members]  # fmt: skip
        out.append(f"cycle {' <-> '.join(component)}: " + "; ".join(sorted(set(where))))
    return out


def check(repo: Path) -> list[str]:
    """Every stage violation and every import cycle among the modules under ``repo``."""
    edges = import_edges(module_files(repo), repo)
    return stage_violations(edges) + cycles(edges)


# The project --------------------------------------------------------------------------------------------------


def test_no_module_imports_a_later_stage() -> None:
    violations = stage_violations(import_edges(module_files(REPO), REPO))
    assert not violations, "imports against the stage order:\n" + "\n".join(violations)


def test_no_import_cycles() -> None:
    found = cycles(import_edges(module_files(REPO), REPO))
    assert not found, "import cycles:\n" + "\n".join(found)


# The checker itself -------------------------------------------------------------------------------------------


def _write(root: Path, files: dict[str, str]) -> Path:
    for rel, text in files.items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return root


def test_checker_accepts_a_clean_package(tmp_path: Path) -> None:
    repo = _write(tmp_path, {
        "dks_gym/__init__.py": "from .version import __version__\nfrom .envs import make\n\n"
                               "def __getattr__(name):\n    from .models import build\n    return build\n",
        "dks_gym/version.py": "__version__ = '0'\n",
        "dks_gym/benchmarks/__init__.py": "from .base import Benchmark\n",
        "dks_gym/benchmarks/base.py": "from ..version import __version__\n",
        "dks_gym/solvers/__init__.py": "",
        "dks_gym/solvers/case.py": "from ..benchmarks import Benchmark\n\ndef run():\n    from . import __name__\n",
        "dks_gym/envs/__init__.py": "from dks_gym.benchmarks.base import *\nmake = None\n",
        "dks_gym/models/__init__.py": "import dks_gym.solvers.case\nbuild = None\n",
        "dks_gym/cli.py": "from agents import run\n",
        "agents/__init__.py": "from dks_gym.models import build\nrun = None\n",
    })  # fmt: skip
    assert check(repo) == []


def test_checker_catches_a_lazy_back_import_and_its_cycle(tmp_path: Path) -> None:
    """A benchmark importing its solver inside a function (the pattern issue 14 removed) fails twice:
    as an import of a later stage and as a cycle, each naming the file and line."""
    repo = _write(tmp_path, {
        "dks_gym/__init__.py": "",
        "dks_gym/benchmarks/__init__.py": "",
        "dks_gym/benchmarks/cylinder.py": "X = 1\n\n\ndef generate():\n    from ..solvers.case import run\n",
        "dks_gym/solvers/__init__.py": "",
        "dks_gym/solvers/case.py": "from ..benchmarks.cylinder import X\n",
    })  # fmt: skip
    found = check(repo)
    assert len(found) == 2, found
    assert found[0].startswith("dks_gym/benchmarks/cylinder.py:5: ") and "later stage solvers" in found[0]
    assert found[1].startswith("cycle dks_gym.benchmarks.cylinder <-> dks_gym.solvers.case")
    assert "dks_gym/solvers/case.py:1" in found[1]


@pytest.mark.parametrize(
    "files, expected",
    [
        ({"dks_gym/models/checkpoint.py": "from .. import __version__\n"}, "imports the package root"),
        ({"dks_gym/__init__.py": "from .models import checkpoint\n"}, "root imports models at import time"),
        ({"dks_gym/dataset/reader.py": "import dks_gym.envs\n"}, "dataset imports the later stage envs"),
        ({"dks_gym/cli.py": "", "dks_gym/home.py": "from dks_gym.cli import main\n"}, "utilities imports the later"),
        ({"agents/cli.py": "", "agents/scoring.py": "from dks_gym_agents.cli import x\nfrom dks_gym.cli import main\n"},
         "agents imports the later stage cli"),
    ],
)  # fmt: skip
def test_checker_catches_each_kind_of_violation(tmp_path: Path, files: dict[str, str], expected: str) -> None:
    repo = _write(tmp_path, {"dks_gym/__init__.py": "", "dks_gym/models/__init__.py": "", **files})
    found = check(repo)
    assert len(found) == 1 and expected in found[0], found


def test_checker_catches_a_cycle_within_one_stage(tmp_path: Path) -> None:
    repo = _write(tmp_path, {
        "dks_gym/__init__.py": "",
        "dks_gym/models/__init__.py": "",
        "dks_gym/models/latent_model.py": "def f():\n    from .pdmd import PDMD\n",
        "dks_gym/models/pdmd.py": "from . import latent_model\n",
    })  # fmt: skip
    assert check(repo) == [
        "cycle dks_gym.models.latent_model <-> dks_gym.models.pdmd: dks_gym/models/latent_model.py:2 "
        "(dks_gym.models.latent_model -> dks_gym.models.pdmd); dks_gym/models/pdmd.py:1 "
        "(dks_gym.models.pdmd -> dks_gym.models.latent_model)"
    ]


def test_checker_sees_the_agents_under_their_installed_name(tmp_path: Path) -> None:
    """``dks_gym_agents.x`` is the module of ``agents/x.py``: a cycle through the installed name is found."""
    repo = _write(tmp_path, {
        "dks_gym/__init__.py": "",
        "agents/__init__.py": "",
        "agents/policies.py": "from .scoring import score\n",
        "agents/scoring.py": "def score():\n    from dks_gym_agents.policies import P\n",
    })  # fmt: skip
    found = check(repo)
    assert len(found) == 1 and found[0].startswith("cycle agents.policies <-> agents.scoring"), found
