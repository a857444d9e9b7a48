"""The one loop that runs a latent filter over whole sensing episodes, and its result.

:func:`run_episodes` steps B episodes (``SensingEnv`` objects, already reset) from frame 0 to the last
frame through one :class:`~dks_gym.assimilation.core.Assimilation`: the filter starts at frame 0 from the
initial latent state (no update with the frame-0 reading), and every later frame is a forecast followed,
unless it is the forward run, by an update with that frame's readings. The sensors come from one of:

* the envs' own layouts (default; ``sensor_mode="fixed"`` envs);
* ``layouts`` (B, m): a fixed layout per episode, read from envs whose sensors hold every cell of it
  (several episodes may share one env object: it is stepped once per frame and read at each layout);
* ``decide(belief (B, 2r)) -> actions (B, m)``: a layout chosen every step (``sensor_mode="select"`` envs).

:func:`run_assimilation` runs it over the trajectories of a dataset split (paper Section IV); the
placement harness (``dks_gym_agents.scoring``) over (layout, trajectory) pairs and adaptive policies.
Per episode and frame it records the Eq. 18 MSE of the decoded mean (frame 0 is the initial estimate) and
its relative L2 error (:func:`~dks_gym.assimilation.relative_l2_errors`),
the forecast Jacobian norm ``||F_k||_2`` of each step (EKF and forward run) and the wall time of each
batched filter step (CUDA synchronized); with ``uncertainty=True`` (default) also the scores of the
predictive std per frame (95 % coverage, mean NEES per cell, Gaussian CRPS, the MSE it predicts: the
spread-skill ratio), the final std field and, for the EnKF, the rank histograms of the truth among the
decoded members at the sensors and at fixed cells over frames 1..n_t-1 (:mod:`~dks_gym.assimilation.spread`).

The loop is also how ``Q="calibrated"`` gets its scale (:mod:`~dks_gym.assimilation.tuning`, run at the end of
training and by ``dks-gym calibrate``, never by the loop itself).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch

from ..dataset import Dataset
from ..envs.sensing import SensingEnv
from ..models import FilterableModel
from .config import AssimilationConfig
from .core import Assimilation
from .errors import field_errors
from .spread import rank_histogram, spread_skill


@dataclass
class AssimilationResult:
    """Everything one batched run measured; per-episode arrays are ordered like ``trajectories``."""

    model: str  # the model's kind
    r: int
    config: AssimilationConfig
    trajectories: np.ndarray  # (B,) indices into the split
    params: np.ndarray  # (B,) physical parameter of each trajectory
    step_mse: np.ndarray  # (B, n_t) Eq. 18 at every frame, physical units; frame 0 = initial estimate
    forecast_norm: np.ndarray | None  # (n_t - 1, B) ||F_k||_2 per step; None for the EnKF (no Jacobian)
    step_seconds: np.ndarray  # (n_t - 1,) wall time of each batched filter step
    divergence_resets: np.ndarray  # (B,) how many times each trajectory was restarted
    final_estimate: np.ndarray  # (B, C, *grid) decoded mean at the final frame, physical units
    final_truth: np.ndarray  # (B, C, *grid)
    wall_time: float  # seconds for the whole run (readings, filter, decoding, errors)
    extras: dict[str, Any] = field(default_factory=dict)
    # With uncertainty (else None), over the scored channels, (B, n_t) like step_mse: the fraction of cells
    # inside the central 95 % interval, the mean NEES per cell, the mean Gaussian CRPS (physical units).
    step_coverage: np.ndarray | None = None
    step_nees: np.ndarray | None = None
    step_crps: np.ndarray | None = None
    # The MSE the std predicts, the mean over the scored cells of std^2, (B, n_t): see ``spread_skill``.
    step_predicted_mse: np.ndarray | None = None
    # EnKF with uncertainty (else None): how often the truth ranked 0..n among the n decoded members, (n + 1,),
    # over every episode and frame 1..n_t-1, at the sensors read and at the fixed cells ``rank_cells`` (k,)
    # (flat indices into (C, *grid), :func:`~dks_gym.assimilation.spread.rank_cells`).
    rank_histogram_sensors: np.ndarray | None = None
    rank_histogram_cells: np.ndarray | None = None
    rank_cells: np.ndarray | None = None
    final_estimate_std: np.ndarray | None = None  # (B, C, *grid) predictive std at the final frame
    # Per scored channel (named in ``channels``), at the final frame: Eq. 18 in physical units and over the
    # standardized channel (divided by the channel's data std), (B, n_scored). Their mean over channels is
    # ``final_mse`` (and its standardized twin): channels in Pa and in m/s compare only once normalized.
    channels: tuple[str, ...] = ()
    final_channel_mse: np.ndarray | None = None
    final_channel_nmse: np.ndarray | None = None
    # Per filter step (n_t - 1, B): ||K_k||_2 (0 for the forward run) and the spread sqrt(tr P / r) (EnKF: of
    # the ensemble): whether the filter still listens to the sensors (a collapsed ensemble does not).
    gain_norm: np.ndarray | None = None
    spread: np.ndarray | None = None
    # The relative L2 error ||x^ - x|| / ||x|| over the scored channels (same cells, channels and units as
    # step_mse; NaN where the truth is 0), (B, n_t), and per scored channel at the final frame, (B, n_scored).
    step_rel_l2: np.ndarray | None = None
    final_channel_rel_l2: np.ndarray | None = None
    # With an estimated parameter (FilterConfig(parameter="estimate"), else None): per frame (B, n_t) the
    # scores of :attr:`~dks_gym.assimilation.Snapshot.parameter` (mu_estimate, mu_std, mu_low, mu_high,
    # mu_out_of_range, mu_relative_error, mu_in_interval).
    step_parameter: dict[str, np.ndarray] | None = None

    @property
    def final_mse(self) -> np.ndarray:
        """(B,) final-time MSE per trajectory."""
        return self.step_mse[:, -1]

    @property
    def final_mse_mean(self) -> float:
        return float(np.mean(self.final_mse))

    @property
    def final_mse_std(self) -> float:
        """Sample standard deviation across trajectories (NaN for a single trajectory)."""
        return float(np.std(self.final_mse, ddof=1)) if len(self.final_mse) > 1 else float("nan")

    @property
    def per_step_mse_mean(self) -> np.ndarray:
        """(n_t,) MSE at every frame averaged over trajectories."""
        return self.step_mse.mean(axis=0)

    @property
    def final_rel_l2(self) -> np.ndarray | None:
        """(B,) final-frame relative L2 error per trajectory (None if not measured)."""
        return None if self.step_rel_l2 is None else self.step_rel_l2[:, -1]

    @property
    def max_forecast_norm(self) -> np.ndarray | None:
        """(B,) max_k ||F_k||_2 per trajectory (the paper's operator-norm table); None for the EnKF."""
        # fmax ignores the NaN of steps the filter did not take (late readings)
        return None if self.forecast_norm is None else np.fmax.reduce(self.forecast_norm, axis=0)

    @property
    def da_step_seconds(self) -> float:
        """Mean wall time of one filter step of the whole batch."""
        return float(np.mean(self.step_seconds))

    @property
    def batch(self) -> int:
        return len(self.trajectories)

    def _final_mean(self, name: str) -> float | None:
        values = getattr(self, name)
        return None if values is None else float(np.mean(values[:, -1]))

    @property
    def final_coverage_mean(self) -> float | None:
        """95 % coverage at the final frame, mean over trajectories (None without uncertainty)."""
        return self._final_mean("step_coverage")

    @property
    def final_nees_mean(self) -> float | None:
        """Mean NEES per cell at the final frame, mean over trajectories (None without uncertainty)."""
        return self._final_mean("step_nees")

    @property
    def final_crps_mean(self) -> float | None:
        """Gaussian CRPS at the final frame, mean over trajectories (None without uncertainty)."""
        return self._final_mean("step_crps")

    @property
    def spread_skill(self) -> np.ndarray | None:
        """(n_t,) the spread-skill ratio at every frame, ``sqrt(mean_b predicted MSE / mean_b MSE)`` over the
        trajectories (:func:`~dks_gym.assimilation.spread.spread_skill`; None without uncertainty)."""
        return None if self.step_predicted_mse is None else spread_skill(self.step_predicted_mse, self.step_mse)


def episode_envs(dataset: Dataset, trajectories: np.ndarray, noise_seeds: np.ndarray, *, split: str,
                 noise_level: float, share: bool = False, **env_kwargs: Any) -> list[SensingEnv]:
    """One SensingEnv per episode (trajectory of ``split``, noise seed), reset to it.

    ``share=True``: episodes with the same (trajectory, noise seed) get the same env object, so a fixed
    layout per episode can be read from one env holding the union of the layouts. ``env_kwargs`` go to
    :class:`~dks_gym.envs.SensingEnv` (``sensors``, ``n_sensors``, ``sensor_mode``, ``candidates``).
    """
    made: dict[tuple[int, int], SensingEnv] = {}
    envs = []
    for t, s in zip(np.asarray(trajectories).reshape(-1), np.asarray(noise_seeds).reshape(-1)):
        key = (int(t), int(s))
        if not share or key not in made:
            env = SensingEnv(dataset.benchmark, preset=dataset.preset or "paper", data_path=str(dataset.path),
                             split=split, noise_level=noise_level, **env_kwargs)
            env.reset(options={"trajectory": key[0], "noise_seed": key[1]})
            made[key] = env
            envs.append(env)
        else:
            envs.append(made[key])
    return envs


def close_envs(envs: Sequence[SensingEnv]) -> None:
    """Close each distinct env once."""
    for env in {id(e): e for e in envs}.values():
        env.close()


def _distinct(envs: Sequence[SensingEnv]) -> tuple[list[SensingEnv], np.ndarray]:
    """The distinct env objects and, per episode, the index of its env among them."""
    index: dict[int, int] = {}
    readers: list[SensingEnv] = []
    which = []
    for env in envs:
        if id(env) not in index:
            index[id(env)] = len(readers)
            readers.append(env)
        which.append(index[id(env)])
    return readers, np.asarray(which, dtype=np.int64)


def _layout_positions(readers: list[SensingEnv], which: np.ndarray, layouts: np.ndarray) -> np.ndarray:
    """Where each episode's sensor reading sits in its env's readings, (B, m)."""
    if layouts.ndim != 2 or layouts.shape[0] != len(which):
        raise ValueError(f"layouts must be (B, m) with one row per episode ({len(which)}), got {layouts.shape}")
    positions = np.empty_like(layouts)
    for b, i in enumerate(which):
        read = np.asarray(readers[i].sensors)
        order = np.argsort(read)
        pos = np.searchsorted(read, layouts[b], sorter=order)
        pos = order[np.minimum(pos, len(read) - 1)]
        if not np.array_equal(read[pos], layouts[b]):
            raise ValueError(f"episode {b}'s layout has cells its env does not read; build the env with "
                             "sensors= holding every cell of the layouts (see episode_envs(share=True))")
        positions[b] = pos
    return positions


class _SensorReadings:
    """Where each step's readings come from (see the module docstring): the envs' own layouts, fixed
    ``layouts`` read out of envs that several episodes may share, or the layouts ``decide`` chooses."""

    def __init__(self, envs: Sequence[SensingEnv], layouts: np.ndarray | None,
                 decide: Callable[[np.ndarray], np.ndarray] | None) -> None:
        self.envs, self.decide = envs, decide
        self.readers, self.which = _distinct(envs)
        if decide is not None and len(self.readers) != len(envs):
            raise ValueError("with decide, every episode needs an env of its own")
        self.layouts = None
        if layouts is not None:
            self.layouts = np.atleast_2d(np.asarray(layouts, dtype=np.int64))
            self.positions = _layout_positions(self.readers, self.which, self.layouts)

    def start(self, n_t: int) -> None:
        """Make room for the layouts ``decide`` chooses at frames 1..n_t-1 and the time it takes."""
        if self.decide is not None:
            self.chosen = np.empty((len(self.envs), n_t - 1, self.envs[0].n_sensors), dtype=np.int64)
            self.decision_seconds = np.empty(n_t - 1)

    def step(self, k: int, core: Assimilation) -> tuple[np.ndarray, np.ndarray]:
        """Step the envs to frame ``k``; return the readings (B, m) and the sensors they come from (B, m)."""
        if self.decide is not None:
            tic = time.perf_counter()
            actions = np.asarray(self.decide(core.belief()))
            self.decision_seconds[k - 1] = time.perf_counter() - tic
            steps = [env.step(a) for env, a in zip(self.envs, actions)]
            readings = np.stack([s[0] for s in steps])
            sensors = self.chosen[:, k - 1] = np.stack([s[4]["sensors"] for s in steps])
            return readings, sensors
        steps = [env.step(None) for env in self.readers]
        if self.layouts is None:
            return np.stack([steps[i][0] for i in self.which]), np.stack([steps[i][4]["sensors"] for i in self.which])
        return np.stack([s[0] for s in steps])[self.which[:, None], self.positions], self.layouts

    def extras(self) -> dict[str, Any]:
        """The result's ``extras``: the layouts read (and with ``decide`` the time it took), if not the envs'."""
        if self.decide is not None:
            return {"layouts": self.chosen, "decision_seconds": self.decision_seconds}
        return {} if self.layouts is None else {"layouts": self.layouts}


def run_episodes(
    model: FilterableModel,
    envs: Sequence[SensingEnv],
    config: AssimilationConfig,
    *,
    layouts: np.ndarray | None = None,
    decide: Callable[[np.ndarray], np.ndarray] | None = None,
    dtype: torch.dtype = torch.float32,
    progress: bool = False,
    description: str | None = None,
    uncertainty: bool = True,
    reconstruction_var: Any = None,
) -> AssimilationResult:
    """Filter B reset episodes ``envs`` to their last frame with ``config.filter`` as one batch.

    ``layouts`` or ``decide`` (at most one) say which sensors the filter reads (see the module docstring).
    ``uncertainty``, ``reconstruction_var``: see :class:`~dks_gym.assimilation.Assimilation` (False skips
    the predictive std and its scores; the result's ``step_coverage``, ``step_nees``, ``step_crps`` are None).
    ``extras`` of the result: ``layouts`` (the fixed layouts, or (B, n_t - 1, m) the layouts read at frames
    1..n_t-1 with ``decide``) and, with ``decide``, ``decision_seconds`` (n_t - 1,).
    """
    from tqdm.auto import tqdm

    if layouts is not None and decide is not None:
        raise ValueError("give layouts (fixed per episode) or decide (chosen per step), not both")
    start = time.perf_counter()
    source = _SensorReadings(envs, layouts, decide)
    n_t = envs[0].dataset.n_frames
    if n_t < 2:
        raise ValueError(f"{envs[0].dataset.path} has {n_t} frame(s); assimilation needs at least 2")
    core = Assimilation(model, config.filter, dtype=dtype, uncertainty=uncertainty,
                        reconstruction_var=reconstruction_var)
    snap = core.start(envs, seed=config.filter.seed, sensors=source.layouts)
    batch = len(envs)
    step_mse, step_rel_l2 = np.empty((batch, n_t), dtype=np.float64), np.empty((batch, n_t), dtype=np.float64)
    step_mse[:, 0], step_rel_l2[:, 0] = snap.mse, snap.relative_l2
    scores = {name: np.empty((batch, n_t), dtype=np.float64) for name in ("coverage", "nees", "crps",
                                                                           "predicted_mse")} if uncertainty else {}
    ranks: dict[str, list[np.ndarray]] = {"sensor_ranks": [], "cell_ranks": []}
    for name, values in scores.items():
        values[:, 0] = getattr(snap, name)
    parameter = None if snap.parameter is None else {
        name: np.empty((batch, n_t), dtype=value.dtype) for name, value in snap.parameter.items()}
    for name, values in (parameter or {}).items():
        values[:, 0] = snap.parameter[name]
    source.start(n_t)
    bar = tqdm(range(1, n_t), desc=description or f"{model.kind} {config.filter.kind}", unit="step", leave=False,
               disable=not progress, dynamic_ncols=True)
    for k in bar:
        snap = core.step(envs, *source.step(k, core))
        step_mse[:, k], step_rel_l2[:, k] = snap.mse, snap.relative_l2
        for name, values in scores.items():
            values[:, k] = getattr(snap, name)
        for name, values in (parameter or {}).items():
            values[:, k] = snap.parameter[name]
        for name, seen in ranks.items():
            if getattr(snap, name) is not None:
                seen.append(getattr(snap, name))
    bar.close()
    histograms = {}
    if ranks["sensor_ranks"]:  # the EnKF's (with uncertainty): counted into n + 1 bins
        n = config.filter.n_members
        histograms = {"rank_histogram_sensors": rank_histogram(np.stack(ranks["sensor_ranks"]), n),
                      "rank_histogram_cells": rank_histogram(np.stack(ranks["cell_ranks"]), n),
                      "rank_cells": core.rank_cells}
    result = _result(model, config, envs, core, snap, (step_mse, step_rel_l2), scores, histograms,
                     source.extras(), start)
    result.step_parameter = parameter
    return result


def _result(model: FilterableModel, config: AssimilationConfig, envs: Sequence[SensingEnv], core: Assimilation,
            snap: Any, errors: tuple[np.ndarray, np.ndarray], scores: dict[str, np.ndarray],
            histograms: dict[str, np.ndarray], extras: dict[str, Any], start: float) -> AssimilationResult:
    """The :class:`AssimilationResult` of a finished loop: the records, the final fields and their errors
    (``errors``: the MSE and the relative L2 error per episode and frame; ``histograms``: the EnKF's rank
    histograms and their fixed cells, or nothing)."""
    step_mse, step_rel_l2 = errors
    history = core.history()
    bench, truth = envs[0].benchmark, core.truth(envs)
    channel_std = torch.as_tensor(envs[0].dataset.stats_std)
    estimate_cpu, truth_cpu = snap.estimate.detach().cpu().double(), torch.as_tensor(truth).double()
    per_channel = [(field_errors(estimate_cpu, truth_cpu, (c,)).numpy(),
                    field_errors(estimate_cpu, truth_cpu, (c,), channel_std).numpy()) for c in bench.scored_indices]
    return AssimilationResult(
        model=model.kind, r=int(model.r), config=config,
        trajectories=np.array([e.trajectory for e in envs], dtype=np.int64),
        params=np.array([e.mu for e in envs], dtype=np.float64), step_mse=step_mse,
        forecast_norm=history["forecast_norm"], step_seconds=history["step_seconds"],
        divergence_resets=history["divergence_resets"],
        final_estimate=snap.estimate.cpu().numpy().astype(np.float32), final_truth=truth,
        wall_time=time.perf_counter() - start, extras=extras,
        step_coverage=scores.get("coverage"), step_nees=scores.get("nees"), step_crps=scores.get("crps"),
        step_predicted_mse=scores.get("predicted_mse"),
        **histograms,
        final_estimate_std=None if snap.estimate_std is None else snap.estimate_std.cpu().numpy().astype(np.float32),
        channels=tuple(bench.scored_channels), final_channel_mse=np.stack([m for m, _ in per_channel], axis=1),
        final_channel_nmse=np.stack([n for _, n in per_channel], axis=1),
        gain_norm=history["gain_norm"], spread=history["spread"],
        step_rel_l2=step_rel_l2, final_channel_rel_l2=snap.channel_relative_l2,
    )


def _open(dataset: Dataset | str | Path) -> Dataset:
    return dataset if isinstance(dataset, Dataset) else Dataset(dataset)


def run_assimilation(
    model: FilterableModel,
    dataset: Dataset | str | Path,
    config: AssimilationConfig | None = None,
    *,
    trajectories: list[int] | np.ndarray | None = None,
    dtype: torch.dtype = torch.float32,
    progress: bool = False,
    description: str | None = None,
    uncertainty: bool = True,
    reconstruction_var: Any = None,
    **overrides: Any,
) -> AssimilationResult:
    """Run ``config.filter`` for ``model`` over the trajectories of ``dataset``'s split as one batch.

    Every model and filter reads the same noise realization (SPEC section 2, keyed by ``noise_seed``).
    ``model`` is a trained latent model (see :mod:`dks_gym.models`) on the device to run on;
    ``trajectories`` defaults to the whole split; keyword ``overrides`` change settings of ``config`` or
    of its filter (e.g. ``kind="enkf", n_members=40``). ``uncertainty``, ``reconstruction_var``: see
    :func:`run_episodes`.
    """
    config = config or AssimilationConfig()
    if overrides:
        config = config.replace(**overrides)
    ds = _open(dataset)
    bench = ds.benchmark
    if getattr(model, "benchmark", None) != bench.name:
        raise ValueError(f"the model is for {getattr(model, 'benchmark', None)!r} but the dataset is {bench.name!r}")
    n_split = ds.n_trajectories(config.split)
    index = np.arange(n_split) if trajectories is None else np.asarray(trajectories, dtype=np.int64)
    if index.ndim != 1 or index.size == 0 or index.min() < 0 or index.max() >= n_split:
        raise ValueError(
            f"trajectories must be a non-empty list of indices in [0, {n_split}) of the {config.split!r} split, "
            f"got {trajectories!r}"
        )
    return run_dataset(model, ds, index, np.full(len(index), config.noise_seed), config, dtype=dtype,
                       progress=progress, description=description, uncertainty=uncertainty,
                       reconstruction_var=reconstruction_var, n_sensors=config.n_sensors)


def run_dataset(model: FilterableModel, dataset: Dataset, trajectories: np.ndarray, noise_seeds: np.ndarray,
                config: AssimilationConfig, *, split: str | None = None, share: bool = False,
                layouts: np.ndarray | None = None, decide: Callable[[np.ndarray], np.ndarray] | None = None,
                dtype: torch.dtype = torch.float32, progress: bool = False, description: str | None = None,
                uncertainty: bool = True, reconstruction_var: Any = None, **env_kwargs: Any) -> AssimilationResult:
    """:func:`run_episodes` over episodes (trajectory, noise seed) of ``split`` (default ``config.split``):
    builds their envs (:func:`episode_envs`), runs them and closes them; ``wall_time`` includes the set-up."""
    start = time.perf_counter()
    envs = episode_envs(dataset, trajectories, noise_seeds, split=split or config.split,
                        noise_level=config.noise_level, share=share, faults=config.faults, **env_kwargs)
    try:
        result = run_episodes(model, envs, config, layouts=layouts, decide=decide, dtype=dtype, progress=progress,
                              description=description, uncertainty=uncertainty,
                              reconstruction_var=reconstruction_var)
    finally:
        close_envs(envs)
    result.wall_time = time.perf_counter() - start
    return result
