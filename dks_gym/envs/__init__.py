"""Gymnasium environments: ``DKS/Burgers-v0``, ``DKS/Cylinder-v0``, ``DKS/Dambreak-v0``, ``DKS/Sphere-v0``, and
``DKS/Custom-v0``, the benchmark a schema file describes (``gym.make("DKS/Custom-v0", data_path=...)``)."""

from __future__ import annotations

from gymnasium.envs.registration import register, registry

from ..benchmarks import BENCHMARKS, CUSTOM_ENV_ID
from .faults import SensorFaults
from .sensing import SENSOR_MODES, SensingEnv


def register_envs() -> None:
    """Register the four benchmarks' environment ids and the custom one with Gymnasium (idempotent)."""
    # The custom id names no benchmark: the env takes the one its data_path describes.
    ids = {**{bench.env_id: name for name, bench in BENCHMARKS.items()}, CUSTOM_ENV_ID: None}
    for env_id, name in ids.items():
        if env_id not in registry:
            # Strings, so that registering imports neither torch nor the filter stack.
            register(id=env_id, entry_point="dks_gym.envs.sensing:SensingEnv", kwargs={"benchmark": name},
                     vector_entry_point="dks_gym.wrappers.vector:LatentFilterVectorEnv")


__all__ = ["SENSOR_MODES", "SensingEnv", "SensorFaults", "register_envs"]
