"""SensingEnv: noisy sparse sensors over a stored flow trajectory (Eq. 4, SPEC section 2).

``benchmark`` names one of the four paper benchmarks (its data from the data home, or ``data_path``), or is
None (``DKS/Custom-v0``): the benchmark the schema file at ``data_path`` describes, your own flow on any grid
(:class:`~dks_gym.benchmarks.CustomBenchmark`), with the same sensing, noise, faults and rendering.

One episode walks the frames of one trajectory of a dataset split. The observation is the m noisy sensor
readings of the observed channel; the internal state is the true field ``env.unwrapped.true_state``
(C x grid, physical units). The bare environment gives reward 0: estimation rewards come from the
filter wrappers, which own the estimate.

Two sensor modes:

* ``"fixed"``: the layout is set at construction or by ``reset(options={"sensors": ...})``; the action
  space is ``Discrete(1)`` and the action is ignored (``None`` is accepted too).
* ``"select"``: the action is the layout to read at the next step, ``MultiDiscrete([n_candidates] * m)``
  indices into the candidate set (default: every fluid grid cell). Repeated picks are allowed and read
  the same cell, noise included.

``faults`` (a :class:`~dks_gym.envs.faults.SensorFaults` or a dict of its fields) adds dropout, failures,
bias drift, saturation, quantization, latency and slow sensors, seeded like the noise: a missing reading is
NaN in the observation (which a Box cannot contain: the filter wrappers observe the belief instead) and
``info["mask"]`` (True = present, always given) says which. Latency reads the current layout's cells.

``parameter="hidden"`` leaves the trajectory's physical parameter mu out of ``info`` (default "known": in
``info["mu"]``), so that an agent or a filter must estimate it; the env keeps it (``env.unwrapped.mu``) to
score estimates.

An episode ends with ``truncated=True`` when the last frame is reached: the flow goes on, the record stops.
"""

from __future__ import annotations

import numbers
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from ..benchmarks import Benchmark, get_benchmark
from ..dataset import SPLITS, Dataset, load_dataset
from .faults import FaultRealization, SensorFaults
from .noise import measurement_noise, noise_sigma

SENSOR_MODES = ("fixed", "select")
#: Whether info carries the episode's mu ("known") or not ("hidden").
PARAMETER_MODES = ("known", "hidden")
_RESET_OPTIONS = {"trajectory", "sensors", "noise_seed"}
_WHOLE_TRAJECTORY_BYTES = 64 << 20  # smaller trajectories are read once per episode, larger ones frame by frame


def _check_settings(split: str, sensor_mode: str, noise_level: Any, render_mode: str | None, parameter: str,
                    render_modes: list[str]) -> None:
    """The env's plain settings, each refused with what to use instead."""
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; choose 'train' or 'test'")
    if sensor_mode not in SENSOR_MODES:
        raise ValueError(f"unknown sensor_mode {sensor_mode!r}; choose 'fixed' or 'select'")
    if not (isinstance(noise_level, numbers.Real) and not isinstance(noise_level, bool)
            and np.isfinite(noise_level) and noise_level >= 0):
        raise ValueError(f"noise_level must be a finite number >= 0, got {noise_level!r}")
    if render_mode is not None and render_mode not in render_modes:
        raise ValueError(f"unsupported render_mode {render_mode!r}; choose 'rgb_array' or None")
    if parameter not in PARAMETER_MODES:
        raise ValueError(f"parameter must be 'known' (mu in info) or 'hidden' (mu kept for scoring only), "
                         f"got {parameter!r}")


def _check_latency(faults: SensorFaults | None, n_frames: int) -> None:
    """Refuse a latency after which no reading reaches a filter before the episode ends."""
    if faults is not None and faults.latency >= n_frames - 1:
        raise ValueError(
            f"faults latency {faults.latency} leaves every episode of {n_frames} frames without a reading to "
            f"assimilate: the readings of frame k arrive at frame k + latency, and the first one a filter uses "
            f"(frame 1's) would come after the last frame ({n_frames - 1}); use a latency of at most {n_frames - 2}")


class SensingEnv(gym.Env):
    """Noisy sparse sensing of a stored benchmark trajectory."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        benchmark: str | Benchmark | None = None,
        *,
        preset: str = "paper",
        data_path: str | None = None,
        split: str = "test",
        n_sensors: int = 16,
        sensors: np.ndarray | list[int] | None = None,
        sensor_mode: str = "fixed",
        candidates: np.ndarray | list[int] | None = None,
        noise_level: float = 0.2,
        faults: SensorFaults | dict[str, Any] | None = None,
        render_mode: str | None = None,
        render_channel: str | None = None,
        parameter: str = "known",
    ) -> None:
        named = None if benchmark is None else get_benchmark(benchmark)
        _check_settings(split, sensor_mode, noise_level, render_mode, parameter, self.metadata["render_modes"])
        self.parameter = parameter
        self.faults = SensorFaults.from_any(faults)
        self.dataset: Dataset = load_dataset(named, preset, data_path)
        # No benchmark named (DKS/Custom-v0): the one the file describes.
        self.benchmark: Benchmark = self.dataset.benchmark if named is None else named
        _check_latency(self.faults, self.dataset.n_frames)
        self.split = split
        self.sensor_mode = sensor_mode
        self.noise_level = float(noise_level)
        self.render_mode = render_mode
        self.render_channel = render_channel or self.benchmark.observed_channel
        if self.render_channel not in self.benchmark.channels:
            raise ValueError(f"render_channel {self.render_channel!r} is not one of {self.benchmark.channels}")

        cell_type = self.dataset.cell_type
        self.fluid_mask = self.benchmark.fluid_mask(cell_type)
        self.n_cells = self.benchmark.n_cells
        fluid = np.flatnonzero(self.fluid_mask.ravel())
        self.candidates = fluid if candidates is None else self._check_cells(candidates, "candidates")
        if len(np.unique(self.candidates)) != len(self.candidates):
            raise ValueError("candidates contain repeated cells; pass each grid index once")
        if not (isinstance(n_sensors, (int, np.integer)) and n_sensors >= 1):
            raise ValueError(f"n_sensors must be a positive integer, got {n_sensors!r}")
        if sensors is not None:
            sensors = self._check_cells(sensors, "sensors")
            n_sensors = len(sensors)
        pool = len(self.candidates) if sensor_mode == "select" else len(fluid)
        if n_sensors > pool:
            raise ValueError(
                f"{n_sensors} sensors requested but only {pool} "
                f"{'candidate' if sensor_mode == 'select' else 'fluid'} cells exist; use fewer sensors"
            )
        self.n_sensors = int(n_sensors)
        if self.faults is not None:
            self.faults.check_layout(self.n_sensors)
        self._default_sensors = sensors if sensors is not None else self.benchmark.paper_layout(self.n_sensors)

        # Gaussian readings are unbounded; the largest float32 says so without tripping check_env's infinity warning.
        big = np.finfo(np.float32).max
        self.observation_space = spaces.Box(-big, big, shape=(self.n_sensors,), dtype=np.float32)
        if sensor_mode == "select":
            self.action_space = spaces.MultiDiscrete(np.full(self.n_sensors, len(self.candidates), dtype=np.int64))
        else:
            self.action_space = spaces.Discrete(1)

        self._sigma_cache: dict[int, float] = {}
        self._trajectory = -1
        self._mu = float("nan")
        self._k = -1
        self._sensors = self._default_sensors
        self._frames: np.ndarray | None = None
        self._observed: np.ndarray | None = None
        self._noise_seed = 0
        self._fault_draws: FaultRealization | None = None
        self._present = np.ones(self.n_sensors, dtype=bool)

    # Validation ------------------------------------------------------------------------------------
    def _check_cells(self, cells: Any, what: str) -> np.ndarray:
        arr = np.asarray(cells)
        if arr.ndim == 2 and arr.shape[1] == self.benchmark.ndim:
            if np.any(arr < 0) or np.any(arr >= np.asarray(self.benchmark.grid)):
                raise ValueError(f"{what}: grid coordinates outside the grid {self.benchmark.grid}")
            arr = np.ravel_multi_index(tuple(arr.T), self.benchmark.grid)
        if arr.ndim != 1 or arr.size == 0 or not np.issubdtype(arr.dtype, np.integer):
            raise ValueError(
                f"{what} must be a non-empty 1D array of flat grid indices or an (m, {self.benchmark.ndim}) array "
                f"of grid coordinates, got shape {arr.shape} and dtype {arr.dtype}"
            )
        if np.any(arr < 0) or np.any(arr >= self.n_cells):
            raise ValueError(f"{what}: indices must lie in [0, {self.n_cells}), got {arr.min()}..{arr.max()}")
        solid = ~self.fluid_mask.ravel()[arr]
        if np.any(solid):
            raise ValueError(f"{what}: cells {arr[solid].tolist()} lie inside a solid body; sensors must be in fluid")
        return arr.astype(np.int64)

    def _check_action(self, action: Any) -> np.ndarray:
        if self.sensor_mode == "fixed":
            fixed_ok = action is None or (
                np.ndim(action) == 0 and np.issubdtype(np.asarray(action).dtype, np.integer) and int(action) == 0
            )
            if not fixed_ok:
                raise ValueError(f"sensor_mode='fixed' takes action 0 (or None), got {action!r}")
            return self._sensors
        arr = np.asarray(action)
        if arr.shape != (self.n_sensors,) or not np.issubdtype(arr.dtype, np.integer):
            raise ValueError(
                f"sensor_mode='select' takes {self.n_sensors} integer candidate indices, got shape {arr.shape} "
                f"and dtype {arr.dtype}"
            )
        if np.any(arr < 0) or np.any(arr >= len(self.candidates)):
            raise ValueError(f"action indices must lie in [0, {len(self.candidates)}), got {arr.min()}..{arr.max()}")
        return self.candidates[arr]

    # Gymnasium API ---------------------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        options = dict(options or {})
        unknown = set(options) - _RESET_OPTIONS
        if unknown:
            raise ValueError(f"unknown reset options {sorted(unknown)}; known: {sorted(_RESET_OPTIONS)}")
        n_traj = self.dataset.n_trajectories(self.split)
        if "trajectory" in options:
            traj = options["trajectory"]
            if not (isinstance(traj, (int, np.integer)) and 0 <= traj < n_traj):
                raise ValueError(f"options['trajectory'] must be an integer in [0, {n_traj}), got {traj!r}")
        else:
            traj = int(self.np_random.integers(n_traj))
        if "noise_seed" in options:
            self._noise_seed = int(options["noise_seed"])
        elif seed is not None:
            self._noise_seed = int(seed)
        else:
            self._noise_seed = int(self.np_random.integers(2**63 - 1))
        if "sensors" in options:
            sensors = self._check_cells(options["sensors"], "options['sensors']")
            if len(sensors) != self.n_sensors:
                raise ValueError(
                    f"options['sensors'] has {len(sensors)} sensors but the observation space has {self.n_sensors}; "
                    "make a new env for another sensor count"
                )
            self._sensors = sensors
        else:
            self._sensors = self._default_sensors
        self._load_trajectory(int(traj))
        if self.faults is not None:
            self._fault_draws = self.faults.realize(self._noise_seed, self.split, self._trajectory,
                                                    self.dataset.n_frames)
        self._k = 0
        return self._observe(), self._info()

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        if self._k < 0:
            raise RuntimeError("call reset() before step()")
        if self._k >= self.dataset.n_frames - 1:
            raise RuntimeError("the episode has ended (last frame reached); call reset()")
        self._sensors = self._check_action(action)
        self._k += 1
        obs = self._observe()
        truncated = self._k == self.dataset.n_frames - 1
        return obs, 0.0, False, truncated, self._info()

    # State -----------------------------------------------------------------------------------------
    def _load_trajectory(self, traj: int) -> None:
        # A damaged block raises DataError from the read, NaN or inf in the data DataError from the check:
        # both name the file, the split and the trajectory (and the channel), before any reading is served.
        self._k = -1  # until the trajectory is in, step() asks for a (successful) reset
        fields = self.dataset.fields(self.split)
        nbytes = 4 * int(np.prod(fields.shape[1:]))
        observed = self.benchmark.observed_index
        if nbytes <= _WHOLE_TRAJECTORY_BYTES:
            frames = self.dataset.trajectory(self.split, traj)
            self.dataset.check_finite(frames, self.split, traj)  # every channel: the true state feeds the rewards
            self._frames, self._observed = frames, frames[:, observed]
        else:
            values = self.dataset.read(self.split, traj, slice(None), observed)
            self.dataset.check_finite(values, self.split, traj, channels=(observed,))
            self._frames, self._observed = None, values
        self._trajectory = traj
        self._mu = float(self.dataset.params(self.split)[traj])
        if traj not in self._sigma_cache:
            self._sigma_cache[traj] = noise_sigma(self._observed, self.fluid_mask, self.noise_level)

    @property
    def true_state(self) -> np.ndarray:
        """The true field at the current frame, (C, *grid), physical units."""
        if self._k < 0:
            raise RuntimeError("call reset() first")
        if self._frames is not None:
            return self._frames[self._k]
        return self.dataset.frame(self.split, self._trajectory, self._k)

    @property
    def sensors(self) -> np.ndarray:
        """Flat grid indices of the sensors read at the current frame."""
        return self._sensors

    @property
    def sigma(self) -> float:
        """Noise standard deviation of the current trajectory."""
        return self._sigma_cache[self._trajectory]

    @property
    def mu(self) -> float:
        """Physical parameter of the current trajectory."""
        return self._mu

    @property
    def time_index(self) -> int:
        return self._k

    @property
    def trajectory(self) -> int:
        return self._trajectory

    @property
    def noise_seed(self) -> int:
        return self._noise_seed

    def _reading(self, k: int) -> np.ndarray:
        """The noisy readings of the current layout at frame ``k`` (Eq. 4), float64."""
        clean = self._observed[k].ravel()[self._sensors]
        return clean + measurement_noise(
            self._noise_seed, self.split, self._trajectory, k, self._sensors, self.sigma, self.n_cells)

    def _observe(self) -> np.ndarray:
        if self._fault_draws is None:
            return self._reading(self._k).astype(np.float32)
        source = self._fault_draws.source_frame(self._k)
        obs, self._present = self._fault_draws.apply(self._k, self._sensors,
                                                     None if source is None else self._reading(source))
        return obs

    def _info(self) -> dict[str, Any]:
        info = {
            "mu": self.mu,
            "param_name": self.benchmark.param_name,
            "time_index": self._k,
            "time": float(self.dataset.time[self._k]),
            "trajectory": self._trajectory,
            "split": self.split,
            "sensors": self._sensors.copy(),
            "mask": self._present.copy(),
            # the frame the readings measure: time_index - latency (-1 while late readings have not arrived)
            "reading_time_index": self._k - (0 if self.faults is None else self.faults.latency),
            "sigma": self.sigma,
            "noise_seed": self._noise_seed,
        }
        if self.parameter == "hidden":  # an agent must not read it; the env keeps it for scoring
            del info["mu"]
        return info

    # Rendering -------------------------------------------------------------------------------------
    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            gym.logger.warn("render() called without render_mode; pass render_mode='rgb_array' to gym.make")
            return None
        from .render import render_field

        channel = self.benchmark.channels.index(self.render_channel)
        return render_field(
            self.benchmark,
            self.dataset.coords,
            self.true_state[channel],
            self._sensors,
            fluid_mask=self.fluid_mask,
            title=f"{self.benchmark.name} {self.render_channel}  {self.benchmark.param_name}={self.mu:.4g}  "
            f"t={self.dataset.time[self._k]:.3g}",
        )

    def close(self) -> None:
        self.dataset.close()
