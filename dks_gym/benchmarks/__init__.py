"""The four benchmarks of the paper (SPEC section 1), looked up by name, and custom benchmarks of your own flow."""

from __future__ import annotations

from .base import PRESETS, Benchmark, GeneratedData, GeneratorUnavailable, check_preset, interleaved_sweep
from .burgers import BURGERS
from .custom import CUSTOM_ENV_ID, CustomBenchmark
from .cylinder import CYLINDER
from .dambreak import DAMBREAK
from .sphere import SPHERE

BENCHMARKS: dict[str, Benchmark] = {b.name: b for b in (BURGERS, CYLINDER, DAMBREAK, SPHERE)}


def get_benchmark(name: str | Benchmark) -> Benchmark:
    """Return the benchmark called ``name`` (case-insensitive), or raise naming the valid ones."""
    if isinstance(name, Benchmark):
        return name
    key = str(name).lower()
    if key not in BENCHMARKS:
        raise ValueError(f"unknown benchmark {name!r}; choose one of {', '.join(BENCHMARKS)}")
    return BENCHMARKS[key]


__all__ = [
    "BENCHMARKS",
    "CUSTOM_ENV_ID",
    "PRESETS",
    "Benchmark",
    "CustomBenchmark",
    "GeneratedData",
    "GeneratorUnavailable",
    "check_preset",
    "get_benchmark",
    "interleaved_sweep",
]
