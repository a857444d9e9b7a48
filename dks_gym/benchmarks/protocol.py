"""What makes two results comparable: one named, versioned :class:`Protocol` per benchmark (:data:`PROTOCOLS`).

A protocol fixes the evaluation a score means: the data (preset, split, test trajectories), the measurement
noise (level, seeds, faults), the sensors (the budgets and the default layout), the initial condition, what
is scored (channels and frames) and the model preset. Every results file names its protocol
(:mod:`dks_gym.evaluation.conformance`), and ``dks-gym compare`` refuses two files whose protocols or
protocol settings differ.

Versions: ``name`` names the suite (``dks-v1``), ``version`` its revision. A change of what a field means
or of its value (another noise level, other test trajectories) bumps ``version``; a change of an env's
semantics bumps its id's ``-v0`` suffix (Gymnasium's convention), which is the protocol's ``env_id``, so
results of the old and the new env never pair either.

It lives in the benchmarks stage, not among the stage-0 utilities: the scored channels and the env id are
the benchmark objects' own (restating them would let the two drift), and every writer of results
(evaluation, the placement harness) is a later stage.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from . import BENCHMARKS

PROTOCOL_NAME = "dks-v1"
PROTOCOL_VERSION = 1
#: The sensor budgets of the placement benchmark; reproduce and the demo run the paper's 16.
BUDGETS = (2, 4, 8, 16, 32)
#: The scored frames: every frame after the initial estimate (frame 0); the final-time MSE is the last one.
SCORED_FRAMES = "1..n_t-1"
#: ``trajectories`` when the protocol takes every trajectory of its split.
ALL = "all"


@dataclass(frozen=True)
class Protocol:
    """The settings a score is comparable under, for one benchmark (the module docstring says what and why).

    ``trajectories``: "all" of the split, or the listed indices. ``n_sensors``: the sensor budgets a run may
    use (``default_n_sensors`` where it does not study budgets), each on the benchmark's ``paper_layout(m)``
    unless the layout is what the run compares (a placement policy). ``faults``: None, no sensor faults.
    """

    benchmark: str
    env_id: str
    scored_channels: tuple[str, ...]
    name: str = PROTOCOL_NAME
    version: int = PROTOCOL_VERSION
    data_preset: str = "paper"
    split: str = "test"
    trajectories: str | tuple[int, ...] = ALL
    noise_level: float = 0.2
    noise_seeds: tuple[int, ...] = (0,)
    n_sensors: tuple[int, ...] = BUDGETS
    default_n_sensors: int = 16
    layout: str = "paper"
    initial: str = "approximate"
    faults: Mapping[str, Any] | None = None
    frames: str = SCORED_FRAMES
    model_preset: str = "lite"

    def to_dict(self) -> dict[str, Any]:
        """The JSON-ready protocol for a results file: ``name``, ``version``, then every field."""
        out: dict[str, Any] = {"name": self.name, "version": self.version}
        for name in FIELDS:
            value = getattr(self, name)
            out[name] = list(value) if isinstance(value, tuple) else value
        return out

    def describe(self) -> str:
        """One line for people: the protocol's name, version and settings."""
        seeds = ", ".join(map(str, self.noise_seeds))
        budgets = "/".join(map(str, self.n_sensors))
        return (f"{self.name} v{self.version} ({self.benchmark}, {self.env_id}): {self.data_preset} data, {self.split} "
                f"split, {self.trajectories} trajectories, {self.noise_level:.0%} noise (seeds {seeds}), "
                f"{'no faults' if self.faults is None else 'faults'}, m = {budgets} (default "
                f"{self.default_n_sensors}) on the {self.layout} layout, {self.initial} initial condition, scored "
                f"{', '.join(self.scored_channels)} over frames {self.frames}, {self.model_preset} models")

    def deviations(self, settings: Mapping[str, Any]) -> dict[str, Any]:
        """The settings of a run that fall outside this protocol, by field, with the run's value.

        Only the fields in ``settings`` are checked (a record knows its noise, not its split). ``n_sensors``
        conforms when it is one of the budgets; ``trajectories`` is "all" or the run's indices."""
        out = {}
        for name, value in settings.items():
            if name not in FIELDS:
                raise ValueError(f"{name!r} is not a protocol field; the fields are {', '.join(FIELDS)}")
            if not self._allows(name, value):
                out[name] = value
        return out

    def _allows(self, name: str, value: Any) -> bool:
        expected = getattr(self, name)
        if name == "n_sensors":
            return value in expected
        if name == "noise_level":
            return value is not None and math.isclose(float(value), expected, rel_tol=1e-9)
        if isinstance(expected, tuple):  # JSON gives lists back
            return isinstance(value, (list, tuple)) and tuple(value) == expected
        return value == expected


#: The protocol's fields besides its name and version, in the order results files list them.
FIELDS = ("benchmark", "env_id", "data_preset", "split", "trajectories", "noise_level", "noise_seeds", "n_sensors",
          "default_n_sensors", "layout", "initial", "faults", "scored_channels", "frames", "model_preset")

#: The protocol of each benchmark, by benchmark name.
PROTOCOLS: dict[str, Protocol] = {
    name: Protocol(benchmark=name, env_id=bench.env_id, scored_channels=tuple(bench.scored_channels))
    for name, bench in BENCHMARKS.items()
}


def get_protocol(benchmark: str) -> Protocol:
    """The protocol of ``benchmark`` (case-insensitive), or a ValueError naming the benchmarks."""
    key = str(benchmark).lower()
    if key not in PROTOCOLS:
        raise ValueError(f"no protocol for benchmark {benchmark!r}; choose one of {', '.join(PROTOCOLS)}")
    return PROTOCOLS[key]


__all__ = ["ALL", "BUDGETS", "FIELDS", "PROTOCOLS", "PROTOCOL_NAME", "PROTOCOL_VERSION", "SCORED_FRAMES", "Protocol",
           "get_protocol"]
