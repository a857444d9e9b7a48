"""Forward run, EKF and EnKF of one latent model over a whole dataset split as one batched filter (paper Section IV).

:func:`run_assimilation` builds one :class:`~dks_gym.envs.SensingEnv` per trajectory of the split (every
model and filter reads the same noise realization: SPEC section 2, keyed by ``noise_seed``), stacks their
readings into one ``(B, m)`` measurement per step and advances a single batched filter
(:class:`~dks_gym.wrappers.LatentAssimilator`) over ``B =`` the number of trajectories. The loop is the
one of :class:`~dks_gym.wrappers.LatentFilter`: the filter starts at frame 0 from the initial latent
state (no update with the frame-0 reading), and every later frame is a forecast followed, unless it is a
forward run, by an update with that frame's readings.

Per trajectory and frame it records the Eq. 18 MSE of the decoded mean against the truth (physical
units, scored channels, all cells; frame 0 is the initial estimate), the forecast Jacobian norm
``||F_k||_2`` used by the step (EKF and forward run; for the forward run this is the model's
``forecast_jacobian`` along the rollout), and the wall time of each filter step (forecast plus update
for the whole batch, CUDA synchronized).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..dataset import SPLITS, Dataset
from ..envs.sensing import SensingEnv
from ..wrappers.assimilator import FilterConfig, LatentAssimilator

FILTERS = ("forward", "ekf", "enkf")  # "forward" is the wrappers' filter="none": the update switched off
INITIAL_CONDITIONS = ("approximate", "exact")
DIVERGENCE_POLICIES = ("reset", "raise")


@dataclass(frozen=True)
class AssimilationConfig:
    """What a run holds fixed besides the model (defaults: the paper's main setting, SPEC section 4).

    ``filter``: "forward", "ekf" or "enkf"; ``initial``: "approximate" (mean encoded first training frame)
    or "exact" (encoded first frame); ``noise_level``: sigma as a fraction of max |observed channel|;
    ``n_members``: EnKF ensemble size; ``P0``, ``Q``: initial and process-noise variances (times I);
    ``noise_seed``: seed of the measurement noise, shared by every model and filter; ``filter_seed``:
    seed of the EnKF's draws; ``on_divergence``: "reset" restarts a diverged trajectory from its initial
    state and counts it in :attr:`AssimilationResult.divergence_resets`, "raise" stops the run.
    """

    filter: str = "ekf"
    initial: str = "approximate"
    noise_level: float = 0.2
    n_members: int = 20
    n_sensors: int = 16
    P0: float = 1.0
    Q: float = 1e-4
    noise_seed: int = 0
    filter_seed: int = 0
    split: str = "test"
    on_divergence: str = "reset"

    def __post_init__(self) -> None:
        if self.filter not in FILTERS:
            raise ValueError(f"unknown filter {self.filter!r}; choose one of {', '.join(FILTERS)}")
        if self.initial not in INITIAL_CONDITIONS:
            raise ValueError(f"unknown initial condition {self.initial!r}; choose 'approximate' or 'exact'")
        if not (np.isfinite(self.noise_level) and self.noise_level > 0):
            raise ValueError(
                f"noise_level must be a positive fraction of the observed channel's maximum (e.g. 0.2), "
                f"got {self.noise_level!r}"
            )
        if int(self.n_members) != self.n_members or self.n_members < 2:
            raise ValueError(f"n_members must be an integer >= 2, got {self.n_members!r}")
        if int(self.n_sensors) != self.n_sensors or self.n_sensors < 1:
            raise ValueError(f"n_sensors must be a positive integer, got {self.n_sensors!r}")
        if not (self.P0 > 0 and self.Q >= 0):
            raise ValueError(f"P0 must be > 0 and Q >= 0, got P0={self.P0!r}, Q={self.Q!r}")
        if self.split not in SPLITS:
            raise ValueError(f"unknown split {self.split!r}; choose 'train' or 'test'")
        if self.on_divergence not in DIVERGENCE_POLICIES:
            raise ValueError(f"on_divergence must be 'reset' or 'raise', got {self.on_divergence!r}")


@dataclass
class AssimilationResult:
    """Everything one batched run measured; per-trajectory arrays are ordered like ``trajectories``."""

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
    def max_forecast_norm(self) -> np.ndarray | None:
        """(B,) max_k ||F_k||_2 per trajectory (the paper's operator-norm table); None for the EnKF."""
        return None if self.forecast_norm is None else self.forecast_norm.max(axis=0)

    @property
    def da_step_seconds(self) -> float:
        """Mean wall time of one filter step of the whole batch."""
        return float(np.mean(self.step_seconds))

    @property
    def batch(self) -> int:
        return len(self.trajectories)


def _model_device(model: Any) -> torch.device:
    buffer = getattr(model, "stats_mean", None)
    if isinstance(buffer, torch.Tensor):
        return buffer.device
    first = next(iter(model.parameters()), None) if hasattr(model, "parameters") else None
    return first.device if first is not None else torch.device("cpu")


def _open(dataset: Dataset | str | Path) -> Dataset:
    return dataset if isinstance(dataset, Dataset) else Dataset(dataset)


def sensing_envs(dataset: Dataset, trajectories: np.ndarray, config: AssimilationConfig) -> list[SensingEnv]:
    """One SensingEnv per trajectory, reset to it with the shared noise seed."""
    envs = []
    for i in trajectories:
        env = SensingEnv(dataset.benchmark, preset=dataset.preset or "paper", data_path=str(dataset.path),
                         split=config.split, n_sensors=config.n_sensors, noise_level=config.noise_level)
        env.reset(options={"trajectory": int(i), "noise_seed": config.noise_seed})
        envs.append(env)
    return envs


def run_assimilation(
    model: Any,
    dataset: Dataset | str | Path,
    config: AssimilationConfig | None = None,
    *,
    trajectories: list[int] | np.ndarray | None = None,
    dtype: torch.dtype = torch.float32,
    progress: bool = False,
    description: str | None = None,
    **overrides: Any,
) -> AssimilationResult:
    """Run ``config.filter`` for ``model`` over the trajectories of ``dataset``'s split as one batch.

    ``model`` is a trained latent model (see :mod:`dks_gym.models`) on the device to run on;
    ``trajectories`` defaults to the whole split; keyword ``overrides`` replace fields of ``config``
    (e.g. ``filter="enkf", n_members=40``).
    """
    config = replace(config or AssimilationConfig(), **overrides) if overrides else (config or AssimilationConfig())
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
    device = _model_device(model)
    start = time.perf_counter()
    envs = sensing_envs(ds, index, config)
    try:
        result = _loop(model, ds, envs, index, config, device, dtype, progress, description)
    finally:
        for env in envs:
            env.close()
    result.wall_time = time.perf_counter() - start
    return result


def _loop(model: Any, ds: Dataset, envs: list[SensingEnv], index: np.ndarray, config: AssimilationConfig,
          device: torch.device, dtype: torch.dtype, progress: bool, description: str | None) -> AssimilationResult:
    from tqdm.auto import tqdm

    batch, n_t = len(envs), ds.n_frames
    if n_t < 2:
        raise ValueError(f"{ds.path} has {n_t} frame(s); assimilation needs at least 2")
    filter_config = FilterConfig(
        filter="none" if config.filter == "forward" else config.filter, initial=config.initial, P0=config.P0,
        Q=config.Q, n_members=config.n_members, on_divergence=config.on_divergence,
    )
    assimilator = LatentAssimilator(model, filter_config, device=device, dtype=dtype)
    assimilator.start(envs, seed=config.filter_seed)
    step_mse = np.empty((batch, n_t), dtype=np.float64)
    estimate = assimilator.estimate()
    step_mse[:, 0] = assimilator.errors(estimate, envs)[0]
    bar = tqdm(range(1, n_t), desc=description or f"{model.kind} {config.filter}", unit="step", leave=False,
               disable=not progress, dynamic_ncols=True)
    for k in bar:
        steps = [e.step(None) for e in envs]
        assimilator.step(np.stack([s[0] for s in steps]), np.stack([s[4]["sensors"] for s in steps]))
        estimate = assimilator.estimate()
        step_mse[:, k] = assimilator.errors(estimate, envs)[0]
    bar.close()

    d = assimilator.filter.diagnostics
    forecast_norm = None if config.filter == "enkf" else d.stacked("forecast_norm").cpu().double().numpy()
    return AssimilationResult(
        model=model.kind,
        r=int(model.r),
        config=config,
        trajectories=index,
        params=np.array([e.mu for e in envs], dtype=np.float64),
        step_mse=step_mse,
        forecast_norm=forecast_norm,
        step_seconds=np.asarray(d.wall_time, dtype=np.float64),
        divergence_resets=d.stacked("reset").sum(0).cpu().numpy().astype(np.int64),
        final_estimate=estimate.cpu().numpy().astype(np.float32),
        final_truth=assimilator.truth(envs).cpu().numpy().astype(np.float32),
        wall_time=0.0,
    )


__all__ = [
    "DIVERGENCE_POLICIES",
    "FILTERS",
    "INITIAL_CONDITIONS",
    "AssimilationConfig",
    "AssimilationResult",
    "run_assimilation",
    "sensing_envs",
]
