"""Gymnasium environments: ``DKS/Burgers-v0``, ``DKS/Cylinder-v0``, ``DKS/Dambreak-v0``, ``DKS/Sphere-v0``."""

from __future__ import annotations

from gymnasium.envs.registration import register, registry

from ..benchmarks import BENCHMARKS
from .faults import SensorFaults
from .sensing import SENSOR_MODES, SensingEnv


def register_envs() -> None:
    """Register the four environment ids with Gymnasium (idempotent)."""
    for name, bench in BENCHMARKS.items():
        if bench.env_id not in registry:
            # Strings, so that registering imports neither torch nor the filter stack.
            register(id=bench.env_id, entry_point="dks_gym.envs.sensing:SensingEnv", kwargs={"benchmark": name},
                     vector_entry_point="dks_gym.wrappers.vector:LatentFilterVectorEnv")


__all__ = ["SENSOR_MODES", "SensingEnv", "SensorFaults", "register_envs"]
