"""The sensor-placement policy interface: static layouts (one per episode) and adaptive ones (one per step).

A placement policy decides where the m sensors of a :class:`~dks_gym.envs.SensingEnv` read. It learns
only from a :class:`PlacementTask`: the benchmark, the dataset's *training* split, the latent model and
the filter settings it will be judged with. The evaluation harness (:mod:`dks_gym_agents.evaluate`) then runs
it on the test split.

* :class:`StaticPolicy`: ``fit(task)`` chooses a layout from the training data; ``episode_layouts(mus)``
  gives the layout of each test episode (by default the same one for all), read by a ``sensor_mode="fixed"``
  env. Example (a 4-sensor layout spaced evenly over the grid)::

      class Evenly(StaticPolicy):
          name = "evenly"

          def choose(self, task):                    # m fluid cells evenly spaced in C order
              cells = task.fluid_cells
              return cells[np.linspace(0, len(cells) - 1, task.n_sensors).astype(int)]

      layout = Evenly().fit(task).layout            # (m,) flat grid indices, fluid, distinct

* :class:`AdaptivePolicy`: picks, at every step, m cells out of ``candidates`` from the filter's belief
  ``[latent mean (r); log diag P (r)]``, read by a ``sensor_mode="select"`` env with the same candidates
  (the action is the row of candidate indices). Example (the first or the second half of the candidates,
  by the sign of the first latent coordinate)::

      class SignSwitch(AdaptivePolicy):
          name = "sign-switch"

          def act(self, belief):                     # (B, 2r) -> (B, m) indices into self.candidates
              half = len(self.candidates) // 2
              first = np.where(belief[:, :1] > 0, 0, half)
              return first + np.arange(self.n_sensors)[None, :]

      policy = SignSwitch().fit(task)               # fit() sets candidates and n_sensors from the task
      actions = policy.decide(belief)               # act() made distinct: m different cells per row

Every layout a policy returns holds m distinct fluid cells (:func:`check_layout`); repeated adaptive
picks are moved to the nearest free candidate (:func:`distinct_picks`), so a policy never reads one
cell twice.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dks_gym.benchmarks import Benchmark
from dks_gym.benchmarks.layout import surface_mask
from dks_gym.dataset import Dataset
from dks_gym.models import FilterableModel
from dks_gym.assimilation import AssimilationConfig


@dataclass
class PlacementTask:
    """What a placement policy may learn from: the training split, the model and the filter it is judged with.

    ``config`` holds the filter settings (filter kind, initial condition, noise level, P0, Q, noise seed,
    ``n_sensors``); its ``split`` is the split the policy is *evaluated* on, never read by ``fit``.
    ``candidates`` restricts the cells a policy may choose (default: every fluid cell). ``model_preset``: the
    preset the model was trained with, recorded with the results.
    """

    dataset: Dataset
    model: FilterableModel
    config: AssimilationConfig = field(default_factory=AssimilationConfig)
    candidates: np.ndarray | None = None
    seed: int = 0
    device: str = "cpu"
    model_preset: str = "lite"

    def __post_init__(self) -> None:
        if getattr(self.model, "benchmark", None) != self.benchmark.name:
            raise ValueError(
                f"the model is for {getattr(self.model, 'benchmark', None)!r} "
                f"but the dataset is {self.benchmark.name!r}"
            )
        if self.candidates is not None:
            cells = np.asarray(self.candidates)
            if cells.ndim != 1 or not np.issubdtype(cells.dtype, np.integer) or cells.size == 0:
                raise ValueError("candidates must be a non-empty 1D array of flat grid indices")
            if cells.min() < 0 or cells.max() >= self.benchmark.n_cells:
                raise ValueError(f"candidates must lie in [0, {self.benchmark.n_cells})")
            if np.unique(cells).size != cells.size:
                raise ValueError("candidates contain repeated cells; pass each grid index once")
            solid = ~self.fluid_mask.ravel()[cells]
            if solid.any():
                raise ValueError(f"candidates {cells[solid][:10].tolist()} lie inside a solid body; use fluid cells")
            self.candidates = cells.astype(np.int64)
        if self.n_sensors > len(self.allowed_cells):
            raise ValueError(f"{self.n_sensors} sensors asked for but only {len(self.allowed_cells)} cells allowed")

    @classmethod
    def load(cls, benchmark: str | None, model: str = "koopman", *, model_preset: str = "lite",
             data_preset: str = "paper", data_path: str | Path | None = None, r: int = 32, T: int = 1,
             device: str = "cpu", train_if_missing: bool = False, candidates: np.ndarray | None = None,
             seed: int = 0, **config: Any) -> "PlacementTask":
        """The task for a benchmark's dataset in the data home (or the schema file ``data_path``: with
        ``benchmark`` None, any flow, a custom benchmark included) and a cached model checkpoint.

        ``config`` sets fields of :class:`~dks_gym.assimilation.AssimilationConfig` and of its filter
        (``kind``, ``noise_level``, ``n_sensors``, ``noise_seed`` ...). ``train_if_missing=True`` trains a missing
        model (lite: minutes).
        """
        from dks_gym.dataset import load_dataset
        from dks_gym.assimilation import tune_if_missing
        from dks_gym.models import load_model

        dataset = load_dataset(benchmark, data_preset, data_path)
        latent = load_model(dataset.benchmark, model, r=r, preset=model_preset, T=T, dataset=dataset, device=device,
                            train_if_missing=train_if_missing, progress=False)
        if train_if_missing:  # a model trained here is tuned here too
            tune_if_missing(latent, dataset, progress=False)
        return cls(dataset, latent, AssimilationConfig().replace(**config), candidates=candidates, seed=seed,
                   device=device, model_preset=model_preset)

    @property
    def benchmark(self) -> Benchmark:
        return self.dataset.benchmark

    @property
    def n_sensors(self) -> int:
        return int(self.config.n_sensors)

    @property
    def fluid_mask(self) -> np.ndarray:
        """Boolean grid of cells that may carry a sensor (everything but bodies and obstacles)."""
        return self.benchmark.fluid_mask(self.dataset.cell_type)

    @property
    def fluid_cells(self) -> np.ndarray:
        """Flat indices of every fluid cell, ascending."""
        return np.flatnonzero(self.fluid_mask.ravel())

    @property
    def allowed_cells(self) -> np.ndarray:
        """The cells a policy may choose: ``candidates`` if given, else every fluid cell."""
        return self.fluid_cells if self.candidates is None else self.candidates


def check_layout(task: PlacementTask, layout: Any, name: str = "layout") -> np.ndarray:
    """Return ``layout`` as int64 (m,) or raise: m distinct flat indices of fluid cells inside the grid."""
    arr = np.asarray(layout)
    m = task.n_sensors
    if arr.shape != (m,) or not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"{name} must be {m} integer flat grid indices, got shape {arr.shape}, dtype {arr.dtype}")
    if arr.min() < 0 or arr.max() >= task.benchmark.n_cells:
        raise ValueError(f"{name}: indices must lie in [0, {task.benchmark.n_cells}), got {arr.min()}..{arr.max()}")
    if np.unique(arr).size != m:
        raise ValueError(f"{name} repeats cells: {arr.tolist()}")
    solid = ~task.fluid_mask.ravel()[arr]
    if solid.any():
        raise ValueError(f"{name}: cells {arr[solid].tolist()} lie inside a solid body")
    return arr.astype(np.int64)


def distinct_picks(picks: np.ndarray, n_candidates: int) -> np.ndarray:
    """Make every row of candidate indices distinct: a repeat moves to the nearest free index (lower first).

    ``picks`` (B, m) or (m,) integer indices into a candidate list of length ``n_candidates`` >= m.
    Rows are processed left to right, so the first occurrence of a cell keeps it. Candidate lists built
    by :func:`candidate_lattice` are ordered in space along the grid's last axis, so "nearest index"
    is a neighbouring cell.
    """
    arr = np.atleast_2d(np.asarray(picks, dtype=np.int64)).copy()
    m = arr.shape[1]
    if m > n_candidates:
        raise ValueError(f"cannot pick {m} distinct cells out of {n_candidates} candidates")
    if arr.min() < 0 or arr.max() >= n_candidates:
        raise ValueError(f"picks must lie in [0, {n_candidates}), got {arr.min()}..{arr.max()}")
    for row in arr:
        used = np.zeros(n_candidates, dtype=bool)
        for j, p in enumerate(row):
            if used[p]:
                for step in range(1, n_candidates):
                    lo, hi = p - step, p + step
                    if lo >= 0 and not used[lo]:
                        p = lo
                        break
                    if hi < n_candidates and not used[hi]:
                        p = hi
                        break
                row[j] = p
            used[p] = True
    return arr if np.ndim(picks) == 2 else arr[0]


#: Named candidate constraints: every fluid cell, the body's surface, or every wall and body surface.
CONSTRAINTS = ("fluid", "surface", "wall")


def constraint_candidates(dataset: Dataset, constraint: str | np.ndarray | None) -> np.ndarray | None:
    """The cells a constraint allows, as ``PlacementTask(candidates=...)`` takes them (None: every fluid cell).

    ``"fluid"`` (or None): every fluid cell. ``"surface"``: the fluid cells sharing a face with a solid cell
    (the cylinder, the dambreak's obstacle, the sphere): sensors on the body only. ``"wall"``: every solid
    boundary, the domain's wall cells (the dambreak tank's floor and sides, the cylinder channel's walls)
    and the body's surface, where pressure taps are mounted. A boolean array of the grid's shape: a keep-out
    mask (True = forbidden). An integer array: the allowed cells themselves.
    """
    bench = dataset.benchmark
    fluid = bench.fluid_mask(dataset.cell_type)
    if constraint is None or (isinstance(constraint, str) and constraint == "fluid"):
        return None
    if isinstance(constraint, str):
        if constraint not in CONSTRAINTS:
            raise ValueError(f"unknown constraint {constraint!r}; choose {', '.join(CONSTRAINTS)}, a keep-out mask "
                             "(a boolean array of the grid's shape, True = forbidden) or an array of allowed cells")
        allowed = surface_mask(~fluid, faces_only=True)  # the body's surface
        if constraint == "wall" and "wall" in bench.cell_type_codes:
            allowed |= fluid & (np.asarray(dataset.cell_type) == bench.cell_type_codes["wall"])
        cells = np.flatnonzero(allowed.ravel())
        if cells.size == 0:
            raise ValueError(f"{bench.name} has no solid body or wall, so no {constraint} to put sensors on; use "
                             "'fluid' or a keep-out mask")
        return cells
    arr = np.asarray(constraint)
    if arr.dtype == bool:
        if arr.shape != tuple(bench.grid):
            raise ValueError(f"a keep-out mask must have the grid's shape {tuple(bench.grid)}, got {arr.shape}")
        cells = np.flatnonzero((fluid & ~arr).ravel())
        if cells.size == 0:
            raise ValueError("the keep-out mask forbids every fluid cell")
        return cells
    return np.asarray(arr, dtype=np.int64).reshape(-1)  # PlacementTask checks them


def default_candidate_count(n_sensors: int) -> int:
    """The candidate set's default size for m sensors: 32 cells, or 2m when that is more, so that the greedy
    and learned policies still choose at large budgets (with m candidates they would take them all)."""
    return max(32, 2 * int(n_sensors))


def candidate_lattice(task: PlacementTask, n_target: int | None = None) -> np.ndarray:
    """About ``n_target`` allowed cells (default :func:`default_candidate_count`) on a regular sub-lattice of the
    grid (the same stride on every axis).

    The stride is the smallest one leaving at most ``n_target`` lattice points in allowed cells, offset by half
    a stride so the lattice is centred; the result is sorted (C order). When the allowed cells are too thin a
    set for a lattice (a wall or body surface: fewer than half of ``min(n_target, allowed cells)`` land on it),
    ``n_target`` allowed cells evenly spaced in C order are taken instead. Used as the candidate set of the
    greedy and learned policies, whose cost grows with the number of candidates.
    """
    bench = task.benchmark
    n_target = default_candidate_count(task.n_sensors) if n_target is None else int(n_target)
    if n_target < task.n_sensors:
        raise ValueError(f"a candidate set needs at least n_sensors={task.n_sensors} cells, got n_target={n_target}")
    allowed = np.zeros(bench.n_cells, dtype=bool)
    allowed[task.allowed_cells] = True
    for stride in range(1, max(bench.grid) + 1):
        axes = [np.arange(stride // 2, n, stride) for n in bench.grid]
        mesh = np.meshgrid(*axes, indexing="ij")
        flat = np.ravel_multi_index(tuple(a.ravel() for a in mesh), bench.grid)
        cells = np.sort(flat[allowed[flat]])
        if len(cells) <= n_target:
            break
    every = np.sort(np.asarray(task.allowed_cells, dtype=np.int64))
    if 2 * len(cells) < min(n_target, len(every)):  # a thin allowed set: spread the picks along it instead
        cells = every[np.unique(np.linspace(0, len(every) - 1, min(n_target, len(every))).round().astype(np.int64))]
    if len(cells) < task.n_sensors:
        raise ValueError(
            f"only {len(cells)} candidate cells are allowed, fewer than {task.n_sensors} sensors; "
            "allow more cells (a wider constraint)"
        )
    return cells


class PlacementPolicy(ABC):
    """Base class: a named policy fitted once on a :class:`PlacementTask`.

    ``fit_seconds`` is the offline cost (training data, model runs, RL training) and ``describe()`` the
    settings stored with its results.
    """

    name: str = "policy"
    adaptive: bool = False

    def __init__(self) -> None:
        self.task: PlacementTask | None = None
        self.fit_seconds: float = float("nan")

    def fit(self, task: PlacementTask) -> "PlacementPolicy":
        """Choose from the training data (timed into ``fit_seconds``); returns self."""
        start = time.perf_counter()
        self.task = task
        self._fit(task)
        self.fit_seconds = time.perf_counter() - start
        return self

    @abstractmethod
    def _fit(self, task: PlacementTask) -> None: ...

    @property
    def offline_seconds(self) -> float:
        """Offline cost: ``fit_seconds`` plus any training recorded in a checkpoint the policy loaded."""
        return self.fit_seconds

    def save_agents_to(self, folder: Path) -> None:
        """Where a learned policy saves the agent it trains when it was given no folder (default: nothing to save)."""

    def describe(self) -> dict[str, Any]:
        """Settings worth storing with the results (JSON-serializable)."""
        return {"name": self.name, "adaptive": self.adaptive}

    def _require_fit(self) -> PlacementTask:
        if self.task is None:
            raise RuntimeError(f"policy {self.name!r} is not fitted; call fit(task) first")
        return self.task


class StaticPolicy(PlacementPolicy):
    """A layout chosen once per episode from the training data; subclasses implement :meth:`choose`."""

    def __init__(self) -> None:
        super().__init__()
        self.layout: np.ndarray | None = None

    @abstractmethod
    def choose(self, task: PlacementTask) -> np.ndarray:
        """The layout: m distinct flat indices of fluid cells."""

    def _fit(self, task: PlacementTask) -> None:
        self.layout = check_layout(task, self.choose(task), f"{self.name} layout")

    def episode_layouts(self, mus: np.ndarray) -> np.ndarray:
        """The layout of each episode, (B, m), given the episodes' parameters (the filter knows mu).

        The default is the fitted layout for every episode; a parameter-aware policy overrides this.
        """
        self._require_fit()
        return np.repeat(self.layout[None], len(np.atleast_1d(mus)), axis=0)


class AdaptivePolicy(PlacementPolicy):
    """A layout per step from the filter's belief, over a candidate set (``sensor_mode="select"``)."""

    adaptive = True

    def __init__(self, candidates: np.ndarray | None = None) -> None:
        super().__init__()
        self.candidates = None if candidates is None else np.asarray(candidates, dtype=np.int64)
        self.n_sensors = 0

    def _fit(self, task: PlacementTask) -> None:
        if self.candidates is None:
            self.candidates = task.allowed_cells
        PlacementTask(task.dataset, task.model, task.config, candidates=self.candidates)  # validates them
        self.n_sensors = task.n_sensors
        self.train(task)

    def train(self, task: PlacementTask) -> None:
        """Learn from the training split (default: nothing to learn)."""

    def reset(self, batch: int) -> None:
        """Called at the start of each batch of episodes (default: no memory to clear)."""

    @abstractmethod
    def act(self, belief: np.ndarray) -> np.ndarray:
        """(B, 2r) beliefs -> (B, m) indices into ``candidates`` (repeats allowed; :meth:`decide` removes them)."""

    def decide(self, belief: np.ndarray) -> np.ndarray:
        """:meth:`act` with repeated picks moved to free candidates: (B, m) distinct indices into ``candidates``."""
        self._require_fit()
        return distinct_picks(np.atleast_2d(self.act(np.atleast_2d(belief))), len(self.candidates))
