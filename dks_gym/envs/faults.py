"""Sensor faults (SPEC section 2 extended): what real probes do besides Gaussian noise, seeded like the noise.

:class:`SensorFaults` names the faults and their sizes; composable, every one off by default. Each episode's
:class:`FaultRealization` draws a cell's faults from a generator keyed by (noise seed, split, trajectory,
cell), so the faults are reproducible from the seed, do not depend on the model, the filter, the rest of the
layout or the other faults' settings, and a cell read by two layouts has the same faults in both (as it has
the same noise). Only the slow sensors are named by their slot in the layout.

A reading at frame k, in this order (units of the observed channel):

1. **latency** ``d``: a sensor reports what it measured ``d`` frames earlier (its value and its noise at
   frame ``k - d``); nothing for ``k < d``;
2. **bias drift**: plus a random walk ``b_k = b_{k-1} + drift * N(0, 1)`` per sensor, ``b_0 = 0``;
3. **saturation** ``(low, high)``: clipped to the range;
4. **quantization** ``q``: rounded to the nearest multiple of ``q``;
5. **missing**, as NaN (with ``info["mask"]`` False): **dropout** (each reading lost with probability ``p``),
   **failure** (each sensor fails for good at a step drawn with hazard ``failure_rate`` per step), or a
   **slow sensor** (the slots in ``slow_sensors`` read only at frames ``k`` divisible by ``slow_every``).

The true state is untouched; the filters update with the readings present
(:class:`~dks_gym.filters.EKF` ``mask=``).
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass
from typing import Any

import numpy as np

from .noise import _SPLIT_KEYS

_FAULT_KEY = 0x5EA5  # a fourth key word: the faults' stream never meets the noise fields' (seed, split, traj, frame)


def _number(value: Any, name: str, *, low: float = 0.0, high: float = math.inf, integer: bool = False) -> None:
    ok = isinstance(value, numbers.Integral if integer else numbers.Real) and not isinstance(value, bool)
    if not ok or not (low <= float(value) <= high) or not math.isfinite(float(value)):
        kind = "an integer" if integer else "a finite number"
        raise ValueError(f"{name} must be {kind} in [{low:g}, {high:g}], got {value!r}")


@dataclass(frozen=True)
class SensorFaults:
    """Which faults the sensors have, and how strongly (see the module docstring for each model).

    ``dropout``: probability that a reading is missing, per reading. ``failure_rate``: per-step probability
    that a working sensor fails for good. ``drift``: standard deviation of the bias random walk's step per frame.
    ``saturation``: ``(low, high)`` range the readings are clipped to. ``quantization``: the reading's
    resolution. ``latency``: frames of delay. ``slow_sensors`` / ``slow_every``: slots (indices into the
    layout) that read only every ``slow_every`` frames.
    """

    dropout: float = 0.0
    failure_rate: float = 0.0
    drift: float = 0.0
    saturation: tuple[float, float] | None = None
    quantization: float = 0.0
    latency: int = 0
    slow_sensors: tuple[int, ...] = ()
    slow_every: int = 1

    def __post_init__(self) -> None:
        _number(self.dropout, "dropout", high=1.0)
        _number(self.failure_rate, "failure_rate", high=1.0)
        _number(self.drift, "drift")
        _number(self.quantization, "quantization")
        _number(self.latency, "latency", integer=True)
        _number(self.slow_every, "slow_every", low=1, integer=True)
        if self.saturation is not None:
            if len(self.saturation) != 2:
                raise ValueError(f"saturation must be a (low, high) pair, got {self.saturation!r}")
            low, high = self.saturation
            _number(low, "saturation low", low=-math.inf)
            _number(high, "saturation high", low=-math.inf)
            if not low < high:
                raise ValueError(f"saturation must have low < high, got {self.saturation!r}")
            object.__setattr__(self, "saturation", (float(low), float(high)))
        slots = tuple(self.slow_sensors)
        if any(isinstance(i, bool) or not isinstance(i, numbers.Integral) or i < 0 for i in slots):
            raise ValueError(f"slow_sensors must be non-negative slot indices into the layout, got {slots!r}")
        object.__setattr__(self, "slow_sensors", tuple(int(i) for i in slots))

    @classmethod
    def from_any(cls, value: "SensorFaults | dict[str, Any] | None") -> "SensorFaults | None":
        """A SensorFaults from itself or a dict of its fields (unknown names refused); None when no fault is on."""
        if value is not None and not isinstance(value, (SensorFaults, dict)):
            raise ValueError(f"faults must be a SensorFaults, a dict of its fields or None, got {type(value).__name__}")
        if isinstance(value, dict):
            known = {f.name for f in dataclasses.fields(cls)}
            unknown = set(value) - known
            if unknown:
                raise ValueError(f"unknown sensor faults {sorted(unknown)}; known: {sorted(known)}")
            value = cls(**value)
        return None if value is None or value == SensorFaults() else value

    def changed(self) -> dict[str, Any]:
        """The fields that differ from no faults, by name."""
        none = SensorFaults()
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if getattr(self, f.name) != getattr(none, f.name)}

    def check_layout(self, n_sensors: int) -> None:
        """Refuse slow sensors named beyond a layout of ``n_sensors`` slots."""
        if any(i >= n_sensors for i in self.slow_sensors):
            raise ValueError(f"faults.slow_sensors {self.slow_sensors} name slots beyond the {n_sensors} sensors; "
                             "give indices into the layout")

    def realize(self, seed: int, split: str, trajectory: int, n_frames: int) -> FaultRealization:
        """This episode's faults, drawn per cell as the cells are read."""
        return FaultRealization(self, (int(seed) & (2**63 - 1), _SPLIT_KEYS[split], int(trajectory)), n_frames)


class FaultRealization:
    """One episode's faults. The draws of a cell (its dropouts, its failure step, its bias walk over every frame)
    come from a generator keyed by (noise seed, split, trajectory, cell), made when the cell is first read: a
    cell has the same faults whatever the rest of the layout, as it has the same noise, so layouts compared on
    one episode meet the same faulty sensors where they share cells."""

    def __init__(self, faults: SensorFaults, key: tuple[int, int, int], n_frames: int) -> None:
        self.faults, self.key, self.n_frames = faults, key, n_frames
        self._cells: dict[int, tuple[np.ndarray, float, np.ndarray]] = {}

    def _draws(self, cell: int) -> tuple[np.ndarray, float, np.ndarray]:
        """(lost (n_frames,) bool, failure step, bias (n_frames,)) of one cell."""
        if cell not in self._cells:
            rng = np.random.default_rng(np.random.SeedSequence([*self.key, _FAULT_KEY, int(cell)]))
            # Every draw is made whatever the settings, so one fault's draws do not move with another's size.
            lost = rng.random(self.n_frames) < self.faults.dropout
            u = rng.random()
            rate = self.faults.failure_rate
            # The geometric law by its inverse: the first step s >= 1 at which the sensor fails (rate 0: never).
            with np.errstate(divide="ignore"):
                failure = float(np.floor(np.log1p(-u) / np.log1p(-rate)) + 1) if rate > 0 else np.inf
            steps = rng.standard_normal(self.n_frames)
            steps[0] = 0.0  # b_0 = 0
            self._cells[cell] = (lost, failure, np.cumsum(steps) * self.faults.drift)
        return self._cells[cell]

    def source_frame(self, k: int) -> int | None:
        """The frame whose measurement the sensors report at frame ``k`` (None: nothing yet, latency)."""
        return k - self.faults.latency if k >= self.faults.latency else None

    def apply(self, k: int, cells: np.ndarray, readings: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """The faulty readings of ``cells`` at frame ``k`` (NaN where missing) and the mask of those present,
        from their noisy readings of :meth:`source_frame` (None when there is none)."""
        m = len(cells)
        if readings is None:
            return np.full(m, np.nan, dtype=np.float32), np.zeros(m, dtype=bool)
        draws = [self._draws(int(c)) for c in cells]
        values = np.asarray(readings, dtype=np.float64) + np.array([bias[k] for _, _, bias in draws])
        if self.faults.saturation is not None:
            values = np.clip(values, *self.faults.saturation)
        if self.faults.quantization > 0:
            values = np.round(values / self.faults.quantization) * self.faults.quantization
        missing = np.array([lost[k] or k >= failure for lost, failure, _ in draws])
        if k % self.faults.slow_every != 0:
            missing |= np.isin(np.arange(m), self.faults.slow_sensors)
        present = ~missing
        return np.where(present, values, np.nan).astype(np.float32), present
