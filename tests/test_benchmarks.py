"""The speed benchmark runs every section and writes its JSON (a smoke run: timings are not checked here)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_perf_benchmark_writes_every_section(burgers_small: Path, tmp_path: Path) -> None:
    out = tmp_path / "perf.json"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    subprocess.run([sys.executable, str(ROOT / "benchmarks" / "perf.py"), "--quick", "--out", str(out)], check=True,
                   env=env, cwd=tmp_path, capture_output=True, timeout=600)
    result = json.loads(out.read_text())
    assert set(result) == {"machine", "env", "jacobian", "ekf", "enkf", "algebra", "vector", "training"}
    assert result["machine"]["torch_threads"] == 1 and len(result["machine"]["loadavg_end"]) == 3
    # The sensor-local Jacobian the benchmark times is the one autodiff through the whole decoder gives.
    assert result["jacobian"]["max_relative_difference"] < 1e-5
    assert {(row["filter"], row["num_envs"]) for row in result["vector"]} == {
        ("ekf", 1), ("ekf", 4), ("enkf", 1), ("enkf", 4)}
    (row,) = result["training"]  # --quick: the lite Burgers Koopman model
    assert (row["benchmark"], row["preset"], row["model"]) == ("burgers", "lite", "koopman")
    assert row["step_ratio"] > 0 and row["fraction_of_peak_after"] > 0
    # The schedule the shipped model was trained with, read from its file (the metadata of the package's weights).
    assert row["schedule_before"]["steps"] == row["steps_before"] == 8000
