"""Your own estimator under the protocol: score any method that maps sensor readings to a field, beside ours.

An :class:`Estimator` is any object with ``estimate(readings, sensors, mu)`` (a plain function of the same three
arguments is accepted too) and optionally ``fit(train)``. :func:`score_estimator` runs it over the test episodes of
a benchmark's :class:`~dks_gym.benchmarks.protocol.Protocol` and returns a results document with one record, in
the schema of :mod:`~dks_gym.evaluation.results` and stamped with the protocol
(:mod:`~dks_gym.evaluation.conformance`), so ``dks-gym compare`` and ``dks-gym leaderboard`` take it beside the
filters' files of ``dks-gym reproduce``.

* **What it sees.** Each episode (test trajectory, noise seed) is read through the same
  :func:`~dks_gym.assimilation.episode_envs` as the filters', so the readings are the filters' to the bit: the
  protocol's noise level and seeds, its m sensors on the benchmark's paper layout, its faults. At frame k
  (1..n_t-1, the protocol's scored frames) ``estimate`` gets the episode's readings of frames 1..k, ``(k, m)``
  (NaN where a reading is missing), the sensors' flat cell indices ``(m,)`` and the parameter ``mu``; never a
  later reading and never the truth. Like the filters (which start from an approximate initial state and skip
  frame 0's reading) it gets no reading of frame 0; frame 0 is not scored, and the record stores its error as
  ``null``. A stateless method reads ``readings[-1]``, a sequential one the whole history.
* **What it returns.** The field ``(C, *grid)`` in physical units (every channel of the benchmark; the scored
  ones are scored), or ``(field, std)`` with a predictive standard deviation of the same shape, which is then
  scored too (95 % coverage, NEES, CRPS).
* **Training.** ``fit(train)`` gets a :class:`TrainingData`: the training split's fields and parameters, the
  sensors the test episodes read, the noise level and faults, and noisy training readings made like the test
  ones (other noise seeds). It may train on nothing else of the test split.
* **Scores.** The filters' error functions (:mod:`~dks_gym.assimilation.errors`: Eq. 18's MSE, the relative L2
  error and its score, per scored channel; :func:`~dks_gym.assimilation.gaussian_scores` for a std) at every frame,
  aggregated into the record's fields by the same builders as ours (:func:`~dks_gym.evaluation.results.relative_fields`,
  :func:`~dks_gym.evaluation.intervals.interval_fields`). ``da_step_seconds`` is the mean time of one frame's
  ``estimate`` calls over all episodes (the filters': one batched step of all episodes); ``wall_time`` includes
  ``fit``.

The record: experiment ``"estimator"``, model ``name``, filter ``"none"``, r the estimator's ``rank`` attribute
(its output rank) or 1 where it declares none, T 1. The document's ``preset`` is the protocol's model preset (an
estimator brings its own model; the preset is that of the filters it is compared with) and its ``config``
describes the estimator (``describe()`` where it has one).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch

from ..assimilation import (
    AssimilationConfig,
    close_envs,
    episode_envs,
    field_errors,
    gaussian_scores,
    relative_l2_errors,
)
from ..benchmarks.protocol import ALL, get_protocol
from ..benchmarks.protocol import Protocol as ScoringProtocol
from ..dataset import Dataset, load_dataset
from ..envs import SensorFaults
from ..models.checkpoint import dataset_identity
from ..models.shred import read_episodes
from .conformance import stamp_protocol
from .intervals import interval_fields
from .reproduce import shared_config
from .results import (
    RESULTS_FILE,
    UNCERTAINTY_SCORES,
    Record,
    ResultsDocument,
    _number,
    _numbers,
    new_results,
    relative_fields,
    save_results,
)

#: The record's experiment.
EXPERIMENT = "estimator"
#: The default noise seed of :meth:`TrainingData.readings` (far from the protocol's test seeds).
TRAIN_NOISE_SEED = 1_000_003
#: What ``estimate`` returns: the field, or the field and its predictive std.
FieldEstimate = np.ndarray | tuple[np.ndarray, np.ndarray]


@dataclass(frozen=True)
class TrainingData:
    """What ``fit`` may learn from: the training split, and how the test episodes are sensed.

    ``sensors``: the flat cell indices ``(m,)`` the test episodes read (the protocol's paper layout);
    ``noise_level``, ``faults``: the protocol's.
    """

    dataset: Dataset
    sensors: np.ndarray
    noise_level: float
    faults: SensorFaults | None = None

    @property
    def fields(self) -> np.ndarray:
        """The training fields ``(N, n_t, C, *grid)``, float32, physical units."""
        return np.asarray(self.dataset.fields("train"), dtype=np.float32)

    @property
    def params(self) -> np.ndarray:
        """The training trajectories' parameters ``(N,)``."""
        return np.asarray(self.dataset.params("train"), dtype=np.float64)

    @property
    def field_shape(self) -> tuple[int, ...]:
        """``(C, *grid)``: the shape ``estimate`` returns."""
        return (len(self.dataset.benchmark.channels), *self.dataset.grid)

    def readings(self, noise_seed: int = TRAIN_NOISE_SEED) -> np.ndarray:
        """Noisy readings of every training trajectory at :attr:`sensors`, ``(N, n_t, m)`` float32 (NaN where
        missing), made as the test episodes' are but with noise seed ``noise_seed`` (call it with other seeds
        for more noise realizations). Frame 0 included: the test history starts at frame 1."""
        n = self.dataset.n_trajectories("train")
        return read_episodes(self.dataset, self.sensors, np.arange(n), np.full(n, int(noise_seed)), split="train",
                             noise_level=self.noise_level, faults=self.faults)


@runtime_checkable
class Estimator(Protocol):
    """A method scored by :func:`score_estimator` (see the module docstring). Optionally also ``fit(train)``
    (:class:`TrainingData`), ``rank`` (int: its output rank, the record's r) and ``describe() -> dict``."""

    def estimate(self, readings: np.ndarray, sensors: np.ndarray, mu: float) -> FieldEstimate:
        """The field ``(C, *grid)`` at frame k, or ``(field, std)``, from the readings of frames 1..k ``(k, m)``."""
        ...


class _Function:
    """A plain function ``f(readings, sensors, mu)`` as an :class:`Estimator`."""

    def __init__(self, function: Callable[[np.ndarray, np.ndarray, float], FieldEstimate]) -> None:
        self.function = function

    def estimate(self, readings: np.ndarray, sensors: np.ndarray, mu: float) -> FieldEstimate:
        return self.function(readings, sensors, mu)

    def describe(self) -> dict[str, Any]:
        return {"function": getattr(self.function, "__qualname__", type(self.function).__name__)}


def as_estimator(obj: Any) -> Estimator:
    """``obj`` if it has an ``estimate`` method, a plain function wrapped as one, else a TypeError."""
    if callable(getattr(obj, "estimate", None)):
        return obj
    if callable(obj):
        return _Function(obj)
    raise TypeError(f"an estimator needs a method estimate(readings, sensors, mu) or must be such a function; "
                    f"got {type(obj).__name__}")


def _checked(out: Any, shape: tuple[int, ...], k: int) -> tuple[np.ndarray, np.ndarray | None]:
    """The (field, std or None) ``estimate`` returned at frame ``k``, or a ValueError saying what is wrong."""
    field, std = (out[0], out[1]) if isinstance(out, tuple) and len(out) == 2 else (out, None)
    field = np.asarray(field, dtype=np.float64)
    if field.shape != shape:
        raise ValueError(f"estimate() returned a field of shape {field.shape} at frame {k}; return the whole field "
                         f"(C, *grid) = {shape} in physical units (or a tuple (field, std))")
    if std is not None:
        std = np.asarray(std, dtype=np.float64)
        if std.shape != shape or np.any(std < 0):
            raise ValueError(f"estimate() returned a std of shape {std.shape} at frame {k}; it must be the field's "
                             f"shape {shape} and non-negative")
    return field, std


@dataclass
class _Scores:
    """Per episode (E) and frame (n_t; frame 0 NaN, not scored): the errors, and the std's scores if any."""

    mse: np.ndarray
    rel_l2: np.ndarray
    uncertainty: dict[str, np.ndarray] | None
    final_channel: dict[str, np.ndarray]  # "mse", "nmse", "rel_l2": (E, n_scored) at the final frame
    step_seconds: np.ndarray  # (n_t - 1,) the time of each frame's estimate() calls, summed over episodes


def _run_episode(estimator: Estimator, env: Any, shape: tuple[int, ...]) -> tuple[np.ndarray, ...]:
    """Step one reset env to its last frame; per frame 1..n_t-1 the estimate, its std (or None), the truth
    and the seconds ``estimate`` took."""
    n_t, m = env.dataset.n_frames, env.n_sensors
    history = np.empty((n_t - 1, m), dtype=np.float64)
    fields, truth = np.empty((n_t - 1, *shape)), np.empty((n_t - 1, *shape))
    stds: list[np.ndarray | None] = []
    seconds = np.empty(n_t - 1)
    for k in range(1, n_t):
        history[k - 1] = env.step(None)[0]
        truth[k - 1] = env.true_state
        past = history[:k]
        past.flags.writeable = False  # the estimator may read the history, not rewrite it
        tic = time.perf_counter()
        out = estimator.estimate(past, env.sensors.copy(), float(env.mu))
        seconds[k - 1] = time.perf_counter() - tic
        fields[k - 1], std = _checked(out, shape, k)
        stds.append(std)
    if any(s is None for s in stds) and not all(s is None for s in stds):
        raise ValueError("estimate() returned a std at some frames and not at others; return it always or never")
    return fields, None if stds[0] is None else np.stack(stds), truth, seconds


def _score(estimator: Estimator, dataset: Dataset, episodes: Sequence[tuple[int, int]], protocol: ScoringProtocol,
           progress: bool) -> _Scores:
    """Run ``estimator`` over the (trajectory, noise seed) ``episodes`` of the protocol's split and score it."""
    from tqdm.auto import tqdm

    bench, n_t = dataset.benchmark, dataset.n_frames
    shape, scored = (len(bench.channels), *dataset.grid), bench.scored_indices
    channel_std = torch.as_tensor(np.asarray(dataset.stats_std, dtype=np.float64))
    mse, rel = np.full((len(episodes), n_t), np.nan), np.full((len(episodes), n_t), np.nan)
    uncertainty: dict[str, np.ndarray] = {}
    final = {name: np.empty((len(episodes), len(scored))) for name in ("mse", "nmse", "rel_l2")}
    seconds = np.zeros(n_t - 1)
    for e, (t, s) in enumerate(tqdm(episodes, desc="estimator", unit="episode", disable=not progress)):
        envs = episode_envs(dataset, [t], [s], split=protocol.split, noise_level=protocol.noise_level,
                            faults=protocol.faults, n_sensors=protocol.default_n_sensors)
        try:
            fields, std, truth, took = _run_episode(estimator, envs[0], shape)
        finally:
            close_envs(envs)
        seconds += took
        x_hat, x = torch.from_numpy(fields), torch.from_numpy(truth)
        mse[e, 1:] = field_errors(x_hat, x, scored).numpy()
        rel[e, 1:], per_channel = relative_l2_errors(x_hat, x, scored)
        final["rel_l2"][e] = per_channel[-1]
        for j, c in enumerate(scored):
            final["mse"][e, j] = float(field_errors(x_hat[-1:], x[-1:], (c,)))
            final["nmse"][e, j] = float(field_errors(x_hat[-1:], x[-1:], (c,), channel_std))
        if std is not None:
            for name, values in gaussian_scores(x_hat, torch.from_numpy(std), x, scored, channel_std).items():
                uncertainty.setdefault(name, np.full((len(episodes), n_t), np.nan))[e, 1:] = values
        elif uncertainty:
            raise ValueError("estimate() returned a std in some episodes and not in others")
    return _Scores(mse, rel, uncertainty or None, final, seconds)


def _record(name: str, rank: int, protocol: ScoringProtocol, episodes: Sequence[tuple[int, int]],
            params: np.ndarray, scores: _Scores, channels: Sequence[str], wall_time: float,
            fit_seconds: float | None) -> Record:
    """The results record of a scored estimator (the schema's fields, as :func:`make_record` writes a filter's)."""
    final = scores.mse[:, -1]
    record: Record = {
        "experiment": EXPERIMENT, "model": name, "filter": "none", "initial": protocol.initial,
        "noise": float(protocol.noise_level), "r": int(rank), "T": 1, "n_members": None, "batch": len(episodes),
        "final_mse_mean": _number(np.mean(final)),
        "final_mse_std": _number(np.std(final, ddof=1)) if len(final) > 1 else None,
        "per_step_mse_mean": _numbers(np.mean(scores.mse, axis=0)),
        "per_trajectory_final_mse": _numbers(final), "max_forecast_norm": None,
        "da_step_seconds": _number(np.mean(scores.step_seconds)), "wall_time": _number(wall_time),
        "trajectories": [int(t) for t, _ in episodes], "params": _numbers(params),
    }
    for score in UNCERTAINTY_SCORES:
        steps = None if scores.uncertainty is None else scores.uncertainty[score]
        record[f"final_{score}_mean"] = None if steps is None else _number(np.mean(steps[:, -1]))
        record[f"per_step_{score}_mean"] = None if steps is None else _numbers(np.mean(steps, axis=0))
    record["final_channel_mse_mean"] = {c: _number(v) for c, v in zip(channels, scores.final_channel["mse"].mean(0))}
    record["final_channel_nmse_mean"] = {c: _number(v) for c, v in zip(channels, scores.final_channel["nmse"].mean(0))}
    record.update(relative_fields(scores.rel_l2, scores.final_channel["rel_l2"], channels))
    record.update(interval_fields(record))
    record["per_trajectory_step_mse"] = _numbers(scores.mse)
    record["fit_seconds"] = fit_seconds  # a field of this harness's own, as the placement records add theirs
    return record


def _episodes(dataset: Dataset, protocol: ScoringProtocol, trajectories: Sequence[int] | None) -> list[tuple[int, int]]:
    """The (trajectory, noise seed) episodes: every noise seed of the protocol over its trajectories, or over
    ``trajectories`` (a subset is marked as a deviation in the record)."""
    n = dataset.n_trajectories(protocol.split)
    if trajectories is None:
        trajectories = range(n) if protocol.trajectories == ALL else protocol.trajectories
    index = [int(t) for t in trajectories]
    if not index or min(index) < 0 or max(index) >= n:
        raise ValueError(f"trajectories must be indices in [0, {n}) of the {protocol.split!r} split, got {index!r}")
    return [(t, int(s)) for s in protocol.noise_seeds for t in index]


def _config(estimator: Estimator, name: str, rank: int, dataset: Dataset, protocol: ScoringProtocol,
            sensors: np.ndarray, fit_seconds: float | None, wall_time: float) -> dict[str, Any]:
    """The document's config: the shared fields of reproduce's (without the filter's), the estimator's."""
    base = AssimilationConfig(noise_level=protocol.noise_level, n_sensors=protocol.default_n_sensors,
                              split=protocol.split, faults=protocol.faults)
    config = {k: v for k, v in shared_config(base, dataset, "cpu").items()
              if k not in ("P0", "Q", "filter_seed", "noise_seed", "dtype")}
    described = estimator.describe() if callable(getattr(estimator, "describe", None)) else {}
    config.update(
        estimator={**described, "name": name, "class": f"{type(estimator).__module__}.{type(estimator).__qualname__}",
                   "rank": rank, "fit_seconds": fit_seconds},
        noise_seeds=[int(s) for s in protocol.noise_seeds], noise_level=float(protocol.noise_level),
        sensors=[int(c) for c in sensors], faults=None if protocol.faults is None else dict(protocol.faults),
        created=datetime.now(timezone.utc).isoformat(timespec="seconds"), wall_time_s=wall_time)
    return config


def score_estimator(estimator: Estimator | Callable[..., FieldEstimate], benchmark: str, *, name: str,
                    dataset: Dataset | str | Path | None = None, protocol: ScoringProtocol | None = None,
                    trajectories: Sequence[int] | None = None, out: str | Path | None = None,
                    progress: bool = False) -> ResultsDocument:
    """Fit ``estimator`` on the training split (if it has ``fit``), score it on the test episodes of
    ``protocol`` (default: the benchmark's, :data:`~dks_gym.benchmarks.protocol.PROTOCOLS`) and return the
    results document (see the module docstring); with ``out``, also write it to ``out/results.json.gz``.

    ``name``: the record's model name. ``dataset``: the data (default: the protocol's preset in the data home).
    ``trajectories``: a subset of the test split (default: the protocol's); the record then names
    ``trajectories`` among its protocol deviations, and so does a ``protocol`` other than the benchmark's.
    """
    start = time.perf_counter()
    protocol = get_protocol(benchmark) if protocol is None else protocol
    if protocol.benchmark != benchmark.lower():
        raise ValueError(f"the protocol is {protocol.benchmark!r}'s, not {benchmark!r}'s")
    if protocol.layout != "paper":
        raise ValueError(f"score_estimator reads the paper layout; the protocol asks for {protocol.layout!r}")
    if not isinstance(name, str) or not name.strip():
        raise ValueError("name must be a non-empty string: the record's model name")
    estimator = as_estimator(estimator)
    if dataset is None:
        dataset = load_dataset(protocol.benchmark, protocol.data_preset)
    elif not isinstance(dataset, Dataset):
        dataset = Dataset(dataset)
    if dataset.benchmark.name != protocol.benchmark:
        raise ValueError(f"{dataset.path} holds {dataset.benchmark.name!r} data, not {protocol.benchmark!r}")
    sensors = dataset.benchmark.paper_layout(protocol.default_n_sensors)  # the envs' default layout
    fit_seconds = None
    if callable(getattr(estimator, "fit", None)):
        tic = time.perf_counter()
        estimator.fit(TrainingData(dataset, sensors, float(protocol.noise_level),
                                   SensorFaults.from_any(protocol.faults)))
        fit_seconds = time.perf_counter() - tic
    rank = int(getattr(estimator, "rank", 1))
    episodes = _episodes(dataset, protocol, trajectories)
    scores = _score(estimator, dataset, episodes, protocol, progress)
    params = dataset.params(protocol.split)[[t for t, _ in episodes]]
    wall_time = time.perf_counter() - start
    record = _record(name, rank, protocol, episodes, params, scores, dataset.benchmark.scored_channels, wall_time,
                     fit_seconds)
    config = _config(estimator, name, rank, dataset, protocol, sensors, fit_seconds, wall_time)
    doc = stamp_protocol(new_results(protocol.benchmark, protocol.model_preset, dataset_identity(dataset), config,
                                     [record]))
    if out is not None:
        save_results(doc, Path(out) / RESULTS_FILE)
    return doc


__all__ = ["EXPERIMENT", "TRAIN_NOISE_SEED", "Estimator", "FieldEstimate", "TrainingData", "as_estimator",
           "score_estimator"]
