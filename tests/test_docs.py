"""Every ```python block of docs/**/*.md is checked, so the documentation cannot drift from the code.

* Every block runs in its own interpreter (cwd a temporary folder, DKS_GYM_HOME a data home of this module
  holding the session's Burgers `small` and `paper` data; the models are the shipped ones) and must exit 0,
  unless its first line is ``# doc-test: import-only (why)``: a fragment, or a block that needs CFD data, a
  GPU or long training.
* Every block, run or not, is compiled, each ``import X`` / ``from X import a, b`` in it is imported and every
  imported name must exist, and attribute chains on an imported module (``dks_gym.models.calibration.calibrate``,
  ``torch.linalg.matrix_exp``) must resolve as far as they run through modules.

A failure names the file and the line of the block's opening fence.
"""

from __future__ import annotations

import ast
import importlib
import os
import re
import shutil
import subprocess
import sys
import textwrap
import types
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
SKIP_MARKER = "# doc-test: import-only"
# A fence may be indented (a block inside a list item); the closing fence has the same indentation.
BLOCK = re.compile(r"^([ \t]*)```python[ \t]*\n(.*?)^\1```[ \t]*$", re.DOTALL | re.MULTILINE)


def doc_blocks() -> list[tuple[str, int, str]]:
    """(path relative to the repository, line of the opening fence, dedented code) of every python block."""
    out = []
    for path in sorted(DOCS.rglob("*.md")):
        text = path.read_text(encoding="utf-8")
        for m in BLOCK.finditer(text):
            line = text.count("\n", 0, m.start()) + 1
            out.append((path.relative_to(ROOT).as_posix(), line, textwrap.dedent(m.group(2))))
    return out


BLOCKS = doc_blocks()
RUN_BLOCKS = [b for b in BLOCKS if not b[2].lstrip().startswith(SKIP_MARKER)]


def _where(doc: str, line: int) -> str:
    return f"{doc}:{line}"


def _import(name: str, where: str) -> types.ModuleType:
    try:
        return importlib.import_module(name)
    except ImportError as exc:
        pytest.fail(f"{where}: `import {name}` fails: {exc}")


def _attribute(obj: object, attr: str) -> object:
    """``obj.attr``, importing ``obj.attr`` as a submodule when a package does not expose it yet."""
    if hasattr(obj, attr):
        return getattr(obj, attr)
    if isinstance(obj, types.ModuleType) and hasattr(obj, "__path__"):
        try:
            return importlib.import_module(f"{obj.__name__}.{attr}")
        except ImportError:
            pass
    raise AttributeError(attr)


def _chain(node: ast.Attribute) -> tuple[str, list[str]] | None:
    """``a.b.c`` -> ("a", ["b", "c"]); None when the chain does not start at a plain name."""
    attrs = []
    while isinstance(node, ast.Attribute):
        attrs.append(node.attr)
        node = node.value
    return (node.id, attrs[::-1]) if isinstance(node, ast.Name) else None


def check_names(code: str, where: str) -> None:
    """Compile the block, import what it imports, and check every imported name and module attribute chain."""
    try:
        tree = ast.parse(compile(code, where, "exec", flags=ast.PyCF_ONLY_AST))
    except SyntaxError as exc:
        pytest.fail(f"{where}: the block does not compile: {exc}")
    modules: dict[str, types.ModuleType] = {}  # names bound to modules by the block's imports
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                module = _import(alias.name, f"{where} (line {node.lineno} of the block)")
                if alias.asname:
                    modules[alias.asname] = module
                else:
                    head = alias.name.split(".")[0]
                    modules[head] = sys.modules[head]
        elif isinstance(node, ast.ImportFrom):
            if node.level or not node.module:
                pytest.fail(f"{where}: relative import in a documentation block")
            module = _import(node.module, f"{where} (line {node.lineno} of the block)")
            for alias in node.names:
                if alias.name == "*":
                    continue
                try:
                    value = _attribute(module, alias.name)
                except AttributeError:
                    pytest.fail(f"{where} (line {node.lineno} of the block): `from {node.module} import "
                                f"{alias.name}`: {node.module} has no {alias.name!r}")
                if isinstance(value, types.ModuleType):
                    modules[alias.asname or alias.name] = value
    for node in ast.walk(tree):
        if not isinstance(node, ast.Attribute) or not isinstance(node.ctx, ast.Load):
            continue
        chain = _chain(node)
        if chain is None or chain[0] not in modules:
            continue
        obj: object = modules[chain[0]]
        walked = chain[0]
        for attr in chain[1]:
            if not isinstance(obj, types.ModuleType):
                break  # past the modules: an object's attributes are not checked
            try:
                obj = _attribute(obj, attr)
            except AttributeError:
                pytest.fail(f"{where} (line {node.lineno} of the block): `{walked}.{attr}` does not exist")
            walked += f".{attr}"


@pytest.fixture(scope="module")
def docs_home(burgers_small: Path, burgers_paper: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A data home of this module only, holding the Burgers data generated once per session."""
    root = tmp_path_factory.mktemp("docs_home")
    (root / "data").mkdir()
    for path in (burgers_small, burgers_paper):
        shutil.copy(path, root / "data" / path.name)
    return root


def test_docs_have_python_blocks() -> None:
    assert len(BLOCKS) >= 8, f"found only {len(BLOCKS)} python blocks under docs/: is the fence pattern broken?"
    assert len(RUN_BLOCKS) >= 4, f"only {len(RUN_BLOCKS)} blocks under docs/ run"


def test_markers_are_known_and_say_why() -> None:
    bad = [_where(doc, line) for doc, line, code in BLOCKS if "doc-test:" in code.splitlines()[0]
           and not re.fullmatch(re.escape(SKIP_MARKER) + r" \(.+\)", code.splitlines()[0].strip())]
    assert not bad, f"a doc-test marker must read {SKIP_MARKER!r} (reason), on a block's first line: {bad}"


@pytest.mark.parametrize("doc, line, code", BLOCKS, ids=[_where(d, n) for d, n, _ in BLOCKS])
def test_doc_block_compiles_and_its_names_exist(doc: str, line: int, code: str) -> None:
    check_names(code, _where(doc, line))


@pytest.mark.parametrize("doc, line, code", RUN_BLOCKS, ids=[_where(d, n) for d, n, _ in RUN_BLOCKS])
def test_doc_block_runs(doc: str, line: int, code: str, docs_home: Path, tmp_path: Path) -> None:
    env = dict(os.environ, DKS_GYM_HOME=str(docs_home), MPLBACKEND="Agg")
    env.setdefault("OMP_NUM_THREADS", "1")
    try:
        proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
                              timeout=300)
    except subprocess.TimeoutExpired:
        pytest.fail(f"{_where(doc, line)}: the block ran over 300 s; mark it {SKIP_MARKER!r} (why)")
    assert proc.returncode == 0, (f"{_where(doc, line)}: the block failed (exit {proc.returncode}):\n"
                                  f"{proc.stderr[-3000:]}")
