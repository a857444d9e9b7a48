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
    assert set(result) == {"machine", "env", "jacobian", "ekf", "enkf", "algebra", "vector", "uncertainty", "training"}
    assert result["machine"]["torch_threads"] == 1 and len(result["machine"]["loadavg_end"]) == 3
    # The sensor-local Jacobian the benchmark times is the one autodiff through the whole decoder gives.
    assert result["jacobian"]["max_relative_difference"] < 1e-5
    assert {(row["filter"], row["num_envs"]) for row in result["vector"]} == {
        ("ekf", 1), ("ekf", 4), ("enkf", 1), ("enkf", 4)}
    assert all(row["fraction_of_peak"]["training_mode"] > 0 for row in result["training"])
    assert [row["num_envs"] for row in result["uncertainty"]] == [1, 4]
    assert all(set(row["ms_per_env_step"]) == {"separate_on", "separate_off", "vector_on", "vector_off"}
               and row["speedup_on"] > 0 for row in result["uncertainty"])
