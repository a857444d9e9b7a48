"""README.md is the front door: its Python blocks run, its size stays small, its relative links resolve.

Every ```python block runs in its own interpreter with DKS_GYM_HOME pointed at a data home of this module
that holds the session's Burgers `small` data (so a model a block trains never meets other modules'
checkpoints). A block must exit 0 and print what it computed.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
MAX_CHARS = 8_500
BLOCK = re.compile(r"^```python[ \t]*\n(.*?)^```[ \t]*$", re.DOTALL | re.MULTILINE)
LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")


def python_blocks(text: str) -> list[tuple[int, str]]:
    """(line number of the opening fence, code) of every ```python block."""
    return [(text.count("\n", 0, m.start()) + 1, m.group(1)) for m in BLOCK.finditer(text)]


BLOCKS = python_blocks(README.read_text(encoding="utf-8"))


@pytest.fixture(scope="module")
def readme_home(burgers_small: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A data home of this module only, holding the small Burgers data generated once per session."""
    root = tmp_path_factory.mktemp("readme_home")
    (root / "data").mkdir()
    shutil.copy(burgers_small, root / "data" / burgers_small.name)
    return root


def test_readme_has_python_blocks() -> None:
    assert len(BLOCKS) >= 2, "README.md should show an env example and a LatentFilter example"


@pytest.mark.parametrize("line, code", BLOCKS, ids=[f"README.md:{line}" for line, _ in BLOCKS])
def test_readme_python_block_runs(line: int, code: str, readme_home: Path, tmp_path: Path) -> None:
    # As a user types it: no thread settings (dks_gym.threads picks them), only the test's data home.
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "DKS_GYM_THREADS")}
    env.update(DKS_GYM_HOME=str(readme_home), MPLBACKEND="Agg")
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=400)
    assert proc.returncode == 0, f"README.md block at line {line} failed:\n{proc.stderr[-3000:]}"
    assert proc.stdout.strip(), f"README.md block at line {line} printed nothing"


def test_readme_is_short() -> None:
    n = len(README.read_text(encoding="utf-8"))
    assert n <= MAX_CHARS, f"README.md has {n} characters (at most {MAX_CHARS}): move details to docs/"


def test_readme_relative_links_exist() -> None:
    text = README.read_text(encoding="utf-8")
    targets = [t for t in LINK.findall(text) if not re.match(r"^[a-z][a-z0-9+.-]*:", t, re.I)]
    missing = [t for t in targets if t.split("#")[0] and not (ROOT / t.split("#")[0]).exists()]
    assert targets, "README.md links to no documentation"
    assert not missing, f"README.md links to missing files: {missing}"


#: The README's results rows: the committed results folder and the experiment each row quotes.
README_RESULTS = {"Burgers, paper preset": ("burgers", "main"),
                  "Burgers, lite, calibrated Q": ("burgers-lite-calibrated", "calibrated"),
                  "Dambreak, lite": ("dambreak", "main"), "Cylinder, lite": ("cylinder", "main")}


def test_readme_results_print_the_committed_records_as_every_table_does() -> None:
    """The results table's numbers are the committed records' final EKF errors (approximate initial condition)
    printed by the one formatter the reproduce, demo, placement and compare tables use: the relative L2 error
    with the MSE in brackets (`MSE x` where a record predates the relative error), for Koopman and for the best
    of the other three models (by relative error where the records have it; ties listed together)."""
    from dks_gym.evaluation.formatting import percent, sci
    from dks_gym.evaluation.figures import MODEL_LABELS
    from dks_gym.evaluation.results import load_results, select

    rows = {cells[0]: cells for line in README.read_text().splitlines()
            if line.startswith("| ") and len(cells := [c.strip() for c in line.strip("|").split("|")]) == 5}
    assert set(README_RESULTS) <= set(rows)
    for label, (folder, experiment) in README_RESULTS.items():
        doc = load_results(ROOT / "docs" / "results" / folder / "results.json.gz")
        recs = {m: select(doc, experiment=experiment, model=m, filter="ekf", initial="approximate")[0]
                for m in ("koopman", "pdmd", "mlp", "xlstm")}
        relative = all(r.get("final_rel_l2_mean") is not None for r in recs.values())

        def cell(rec: dict) -> str:
            mse = sci(rec["final_mse_mean"])
            return f"{percent(rec['final_rel_l2_mean'])} ({mse})" if relative else f"MSE {mse}"

        def key(rec: dict) -> float:  # the printed value, so that equal prints tie
            return float(percent(rec["final_rel_l2_mean"])[:-2]) if relative else float(sci(rec["final_mse_mean"]))

        others = {m: r for m, r in recs.items() if m != "koopman"}
        best = min(key(r) for r in others.values())
        ties = [m for m, r in others.items() if key(r) == best]
        expected = f"{', '.join(MODEL_LABELS[m] for m in ties)} {cell(others[ties[0]])}"
        assert rows[label][1:3] == [cell(recs["koopman"]), expected], label
