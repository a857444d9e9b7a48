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
    assert set(result) == {"machine", "env", "jacobian", "ekf", "enkf", "algebra", "torchkf", "vector", "uncertainty",
                           "training"}
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
    # The members' readings it times (from their sensors' windows) are the whole-grid decode's.
    assert result["enkf"]["observe_max_relative_difference"] < 1e-5
    # The step timed against torch-kf computes what torch-kf computes (float32 round-off).
    assert [row["batch"] for row in result["torchkf"]["rows"]] == [4, 16]
    assert all(d < 1e-5 for row in result["torchkf"]["rows"] for d in row["max_relative_difference"].values())
    assert [row["num_envs"] for row in result["uncertainty"]] == [1, 4]
    assert all(set(row["ms_per_env_step"]) == {"separate_on", "separate_off", "vector_on", "vector_off"}
               and row["speedup_on"] > 0 for row in result["uncertainty"])


def test_a_partial_perf_run_refreshes_only_its_entries() -> None:
    """``--sections`` / ``--filters`` replace only the sections (the vector rows by filter and N) they ran."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("perf", ROOT / "benchmarks" / "perf.py")
    perf = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(perf)
    previous = {"machine": {"run": "full"}, "ekf": {"ms": 1}, "enkf": {"ms": 2},
                "vector": [{"filter": "ekf", "num_envs": 256, "speedup": 17}, {"filter": "enkf", "num_envs": 16},
                           {"filter": "enkf", "num_envs": 256, "speedup": 5}]}
    run = {"machine": {"run": "partial"}, "enkf": {"ms": 3}, "vector": [{"filter": "enkf", "num_envs": 256,
                                                                          "speedup": 14}]}
    out = perf.refreshed(previous, run, ["enkf", "vector"])
    assert out["machine"] == {"run": "full"} and out["ekf"] == {"ms": 1} and out["enkf"] == {"ms": 3}
    assert out["vector"] == [previous["vector"][0], previous["vector"][1], run["vector"][0]]
    assert out["refreshed"] == {"enkf": {"run": "partial"}, "vector": {"run": "partial"}}
    assert previous["vector"][2]["speedup"] == 5  # the previous results are not changed in place
