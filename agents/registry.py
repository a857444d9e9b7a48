"""The named placement policies: a registry from a name to the class (its knobs bound) that builds it.

``evaluate_placement(task, "paper,random,qr")`` looks each name up in a registry, :data:`POLICIES` unless
told otherwise. A policy's own knobs live on the policy: to change them, bind them in the registry entry
(``{**POLICIES, "greedy": partial(GreedyLayout, "error", n_candidates=12)}``) or pass the policy object itself
beside the names (``["paper", GreedyLayout("trace", n_trajectories=2)]``).
"""

from __future__ import annotations

from functools import partial
from pathlib import Path
from collections.abc import Callable, Mapping, Sequence

from .adaptive import PPOAdaptive
from .baselines import GREEDY_OBJECTIVES, GreedyLayout, PaperLayout, QRLayout, RandomLayout
from .policies import PlacementPolicy
from .sequential import SequentialLayout

#: A registry entry: a policy class, or a callable with its knobs bound, giving one policy or several.
PolicyFactory = Callable[[], PlacementPolicy | Sequence[PlacementPolicy]]


def random_layouts(n_seeds: int = 5) -> list[RandomLayout]:
    """``n_seeds`` seeded random layouts (``random-0``, ``random-1``, ...): the reference every paired
    comparison is made against, so "random" stands for several."""
    return [RandomLayout(seed) for seed in range(int(n_seeds))]


POLICIES: dict[str, PolicyFactory] = {
    "paper": PaperLayout,
    "random": random_layouts,
    "qr": QRLayout,
    **{name: partial(GreedyLayout, objective) for objective, name in GREEDY_OBJECTIVES.items()},
    "sequential": SequentialLayout,
    "ppo": PPOAdaptive,
}

#: The policies a ranking runs when none are named.
DEFAULT_POLICIES = ("paper", "random", "qr", "greedy")


def make_policies(names: Sequence[str | PlacementPolicy] | str, registry: Mapping[str, PolicyFactory] = POLICIES,
                  agents: str | Path | None = None) -> list[PlacementPolicy]:
    """Policies by name (comma-separated or a list), built by ``registry``, or given as
    :class:`PlacementPolicy` objects (your own, used as they are). A learned policy built here saves what it
    trains to ``agents`` unless its registry entry names another folder."""
    if isinstance(names, str):
        names = [n.strip() for n in names.split(",") if n.strip()]
    unknown = [n for n in names if not isinstance(n, PlacementPolicy) and n not in registry]
    if unknown or not names:
        raise ValueError(f"unknown policies {unknown}; choose from {', '.join(registry)} (comma-separated) "
                         "or pass PlacementPolicy objects")
    out: list[PlacementPolicy] = []
    unique = [n for i, n in enumerate(names) if isinstance(n, PlacementPolicy) or n not in names[:i]]
    for name in unique:
        if isinstance(name, PlacementPolicy):
            out.append(name)
            continue
        built = registry[name]()
        for policy in [built] if isinstance(built, PlacementPolicy) else built:
            if agents is not None:
                policy.save_agents_to(Path(agents))
            out.append(policy)
    names_seen = [p.name for p in out]
    clash = sorted({n for n in names_seen if names_seen.count(n) > 1})
    if clash:
        raise ValueError(f"two policies are named {clash}; give each policy a distinct name")
    return out


__all__ = ["DEFAULT_POLICIES", "POLICIES", "PolicyFactory", "make_policies", "random_layouts"]
