"""Size limits of the code: no module over 500 lines, no function or method over 80 lines.

Every module of ``dks_gym/`` and ``agents/`` is read with :mod:`ast` (nothing is imported). A module counts
its lines; a function or method (nested ones included) counts ``end_lineno - lineno + 1``, so its decorators
are left out and its docstring is in. A failure lists every offender with its count.

The escape: a module that must stay whole (say, one table that reads best in one place) opens with a comment
or docstring line containing ``whole:`` followed by the reason, e.g. ``# whole: the schema table is one
unit``. Such a module is exempt from both limits; the reason must be given (``whole:`` alone does not count).

Run as a script (``python tests/test_structure.py``) it prints the offenders and the counts, for CI logs.
"""

from __future__ import annotations

import ast
import re
import sys
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("dks_gym", "agents")
MAX_MODULE_LINES = 500
MAX_FUNCTION_LINES = 80
#: ``whole:`` and a reason on the module's first line (a comment, or the first line of its docstring).
WHOLE = re.compile(r"\bwhole:\s*\S")


@dataclass(frozen=True)
class Offender:
    """One module or function over its limit."""

    path: str
    line: int
    what: str  # "module" or the function's qualified name
    lines: int
    limit: int

    def __str__(self) -> str:
        return f"{self.path}:{self.line}: {self.what} has {self.lines} lines (limit {self.limit})"


def module_paths(repo: Path) -> list[Path]:
    """Every ``.py`` file of the checked packages under ``repo``, sorted."""
    return [path for package in PACKAGES if (repo / package).is_dir()
            for path in sorted((repo / package).rglob("*.py"))]


def declared_whole(text: str) -> bool:
    """Whether the module opens with a ``whole: <reason>`` comment or docstring line."""
    first = next((line.strip() for line in text.splitlines() if line.strip()), "")
    if not first.startswith(("#", '"""', "'''", 'r"""')):
        return False
    return WHOLE.search(first) is not None


def _functions(tree: ast.AST, prefix: str = "") -> list[tuple[str, ast.AST]]:
    """``(qualified name, node)`` of every function and method in ``tree``, nested ones included."""
    out = []
    for node in ast.iter_child_nodes(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            name = f"{prefix}{node.name}"
            out.append((name, node))
            out.extend(_functions(node, f"{name}.<locals>."))
        elif isinstance(node, ast.ClassDef):
            out.extend(_functions(node, f"{prefix}{node.name}."))
        else:
            out.extend(_functions(node, prefix))
    return out


def offenders(repo: Path) -> list[Offender]:
    """Every module over :data:`MAX_MODULE_LINES` and function over :data:`MAX_FUNCTION_LINES` under ``repo``."""
    out = []
    for path in module_paths(repo):
        text = path.read_text()
        if declared_whole(text):
            continue
        rel = str(path.relative_to(repo))
        n_lines = len(text.splitlines())
        if n_lines > MAX_MODULE_LINES:
            out.append(Offender(rel, 1, "module", n_lines, MAX_MODULE_LINES))
        for name, node in _functions(ast.parse(text, filename=rel)):
            length = node.end_lineno - node.lineno + 1
            if length > MAX_FUNCTION_LINES:
                out.append(Offender(rel, node.lineno, name, length, MAX_FUNCTION_LINES))
    return out


def test_no_module_or_function_over_its_limit() -> None:
    found = offenders(REPO)
    assert not found, "over the size limits (or mark a module `whole: <reason>`):\n" + "\n".join(map(str, found))


# The checker itself -------------------------------------------------------------------------------------------


def _function(name: str, n_lines: int, indent: str = "") -> str:
    """A function of exactly ``n_lines`` lines at ``indent``."""
    return f"{indent}def {name}():\n" + f"{indent}    x = 1\n" * (n_lines - 1)


def test_checker_counts_modules_functions_methods_and_nested_functions(tmp_path: Path) -> None:
    from tests.test_imports import _write  # inside the test: the script entry point does not need it

    nested = "def outer():\n" + _function("inner", 81, "    ")  # outer: 82 lines, inner: 81
    repo = _write(tmp_path, {
        "dks_gym/ok.py": _function("short", 80) + "x = 1\n" * 420,  # 500 lines, an 80-line function
        "dks_gym/long.py": "x = 1\n" * 501,
        "dks_gym/sub/f.py": _function("long", 81),
        "agents/m.py": "class A:\n" + _function("method", 81, "    ") + nested,
    })  # fmt: skip
    assert sorted(map(str, offenders(repo))) == [
        "agents/m.py:2: A.method has 81 lines (limit 80)",
        "agents/m.py:83: outer has 82 lines (limit 80)",
        "agents/m.py:84: outer.<locals>.inner has 81 lines (limit 80)",
        "dks_gym/long.py:1: module has 501 lines (limit 500)",
        "dks_gym/sub/f.py:1: long has 81 lines (limit 80)",
    ]


def test_a_module_marked_whole_with_a_reason_is_exempt(tmp_path: Path) -> None:
    from tests.test_imports import _write

    long = _function("long", 81) + "x = 1\n" * 500
    repo = _write(tmp_path, {
        "dks_gym/comment.py": "# whole: one lookup table, split it and it reads worse\n" + long,
        "dks_gym/docstring.py": '"""Tables. whole: the table is one unit."""\n' + long,
        "dks_gym/no_reason.py": "# whole:\n" + long,
        "dks_gym/second_line.py": '"""Tables.\n\nwhole: too late, not the first line."""\n' + long,
    })  # fmt: skip
    assert sorted({o.path for o in offenders(repo)}) == ["dks_gym/no_reason.py", "dks_gym/second_line.py"]


def main() -> int:
    """Print every offender, then how many modules and functions are over their limits; 1 if any."""
    found = offenders(REPO)
    for offender in found:
        print(offender)
    modules = sum(o.what == "module" for o in found)
    print(f"{len(module_paths(REPO))} modules checked: {modules} over {MAX_MODULE_LINES} lines, "
          f"{len(found) - modules} functions over {MAX_FUNCTION_LINES} lines")
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
