"""dks-gym: Gymnasium environments for sparse flow sensing from the paper *Deep Koopman Sensing*.

``import dks_gym`` registers ``DKS/Burgers-v0``, ``DKS/Cylinder-v0``, ``DKS/Dambreak-v0`` and ``DKS/Sphere-v0``.
"""

from __future__ import annotations

__version__ = "0.1.0"

from .envs import SensingEnv, register_envs
from .wrappers.vector import register_vector_entry_points

register_envs()
register_vector_entry_points()

__all__ = ["SensingEnv", "__version__", "register_envs"]
