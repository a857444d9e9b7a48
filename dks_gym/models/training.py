"""Training of the latent models (Eqs. 10-11): :func:`train_model` and its phases.

A run has three phases, each a function here: it is set up (:func:`plan_training` fixes the schedule and the
validation split, :func:`set_up_training` builds the model, Adam, the batch sampler and the validation monitor,
and restores them from the checkpoint when resuming), it loops (:func:`fit_steps`: Adam steps on the loss of
:mod:`dks_gym.models.loss`, the batches of :mod:`dks_gym.models.windows`, validation and early stopping by
:mod:`dks_gym.models.validation`, a checkpoint every ``checkpoint_every`` steps), and it is finished
(:func:`finish_training`: the best-on-validation weights taken, the model calibrated on the held-out
trajectories (:mod:`dks_gym.models.calibration`), the final checkpoint and a loss-curve figure written beside
it). The schedule (steps, batch size, learning rate and how the run is watched) is one
:class:`~dks_gym.models.schedule.TrainingSchedule`; what the checkpoint holds to resume a run bit-identically
is :mod:`dks_gym.models.resume`'s. pDMD has no optimizer: its "training" is ``fit_dataset``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..dataset import Dataset
from ..locks import file_lock
from ..threads import torch_threads
from .build import build_model
from .calibration import calibrate, evenly_spread
from .checkpoint import (
    build_metadata,
    check_metadata,
    check_model_args,
    checkpoint_path,
    loss_curve_path,
    model_from_checkpoint,
    read_checkpoint,
    read_metadata,
    save_checkpoint,
)
from .latent_model import LatentModel, NeuralLatentModel
from .loss import LOSS_TERMS, training_loss
from .loss_curves import write_loss_curves
from .presets import BenchmarkShape, benchmark_shape
from .resume import TrainingState, check_resumable
from .schedule import TrainingSchedule, training_schedule
from .validation import ValidationMonitor, validation_trajectories
from .windows import WindowSampler


def resolve_device(device: str | torch.device) -> torch.device:
    """``device`` as a torch.device; ValueError for an unknown one or CUDA without CUDA."""
    try:
        device = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise ValueError(f"unknown device {device!r}; use 'cpu', 'cuda' or 'cuda:N'") from exc
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("device 'cuda' was requested but CUDA is not available; use device='cpu'")
    return device


def adam(net: torch.nn.Module, lr: float) -> torch.optim.Adam:
    """The optimizer of every training run: Adam at ``lr`` with torch's multi-tensor (``foreach``) update.

    Its operators take every parameter at once and loop over the tensors in C++ instead of Python: the same
    update to float round-off; Adam's Python loop over the 54 tensors of the lite Koopman model was 8 % of a
    Burgers step (docs/performance.md). Not the ``fused`` kernel: on the CPU it does not bump the parameters'
    version counters (torch 2.13), which the Koopman model's operator cache relies on (tests/test_models.py).
    """
    return torch.optim.Adam(net.parameters(), lr=lr, foreach=True)


def adam_step(model: torch.nn.Module, optimizer: torch.optim.Optimizer, loss: torch.Tensor,
              clip_norm: float | None = None) -> None:
    """One optimizer step on ``loss``: the gradients, clipped to the global norm ``clip_norm`` where given
    (the lite schedules': it lets them run at a higher learning rate without the loss spikes that collapsed
    some runs to the mean field, docs/training.md), then the update."""
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    if clip_norm is not None:
        torch.nn.utils.clip_grad_norm_(model.parameters(), clip_norm, foreach=True)
    optimizer.step()


@dataclass
class TrainingResult:
    """What :func:`train_model` returns."""

    model: LatentModel
    path: Path
    steps_done: int
    new_steps: int  # steps run by this call (0 when the checkpoint was already complete)
    wall_time_s: float  # of this call
    losses: np.ndarray  # (steps_done, 4): total, reconstruction, prediction, latent (normalized units)
    loaded_only: bool = False  # the checkpoint was already complete: nothing was trained or fitted
    best_validation_loss: float | None = None  # of the weights returned (None without a validation split)
    stopped_early: bool = False


@dataclass(frozen=True)
class TrainingPlan:
    """What one run trains, on what data, where, and how: fixed before its first step."""

    benchmark: BenchmarkShape
    model: str
    r: int
    preset: str
    T: int
    dataset: Dataset
    path: Path  # the checkpoint
    schedule: TrainingSchedule  # resolved: its step count fixed (epochs applied)
    seed: int
    device: torch.device
    held_out: list[int]  # the validation trajectories (empty without a validation split)
    checkpoint_every: int

    @property
    def name(self) -> str:
        """The benchmark's name."""
        return self.benchmark.name

    @property
    def label(self) -> str:
        """The run's name in the progress bar and the loss-curve figure."""
        return f"{self.name} {self.model} {self.preset} r={self.r} T={self.T}"

    def settings(self) -> dict[str, Any]:
        """The settings a checkpoint must have been trained with to be resumed by this run."""
        s = self.schedule
        return {"batch_size": s.batch_size, "lr": s.lr, "seed": self.seed, "schedule": s.record()}


@dataclass
class TrainingRun:
    """A run under way: its plan, its state, and the time and steps it started from."""

    plan: TrainingPlan
    state: TrainingState
    start: int  # steps done before this call (0 unless resumed)
    elapsed_before: float  # training time of the earlier calls, seconds
    loop_start: float  # perf_counter() when this call's loop began

    def checkpoint(self, done: int) -> None:
        """Write the checkpoint after ``done`` steps (complete at the last step or an early stop)."""
        plan, monitor = self.plan, self.state.monitor
        stopped = monitor is not None and monitor.stopped
        validated = monitor is not None and bool(monitor.history)
        meta = build_metadata(
            self.state.net, preset=plan.preset, T=plan.T, dataset=plan.dataset, steps_done=done,
            steps=plan.schedule.steps, batch_size=plan.schedule.batch_size, lr=plan.schedule.lr, seed=plan.seed,
            complete=done >= plan.schedule.steps or stopped, device=str(plan.device), loss_terms=list(LOSS_TERMS),
            train_time_s=self.elapsed_before + time.perf_counter() - self.loop_start,
            schedule=plan.schedule.record(), preset_schedule=training_schedule(plan.benchmark, plan.preset).record(),
            validation_trajectories=plan.held_out, stopped_early=stopped,
            calibrated_on="validation" if plan.held_out else "train",
            best_step=monitor.best_step if monitor is not None else None,
            best_validation_loss=monitor.best_loss if validated else None,
        )
        self.state.save(plan.path, meta)


def fit_steps(
    model: NeuralLatentModel,
    optimizer: torch.optim.Optimizer,
    sampler: WindowSampler,
    *,
    start: int,
    steps: int,
    batch_size: int,
    losses: list[torch.Tensor],
    checkpoint: Callable[[int], None] | None = None,
    checkpoint_every: int = 0,
    progress: bool = True,
    description: str = "",
    on_step: Callable[[int, torch.Tensor], None] | None = None,
    lr_at: Callable[[int], float] | None = None,
    monitor: ValidationMonitor | None = None,
    clip_norm: float | None = None,
) -> int:
    """Adam steps ``start`` .. ``steps`` - 1; ``losses`` gets one (4,) tensor per step (see LOSS_TERMS).

    ``lr_at(step)`` sets the learning rate of each step; ``clip_norm`` clips the gradients (:func:`adam_step`);
    ``monitor`` validates every ``eval_every`` steps and
    ends the run early when its patience runs out. Returns the number of steps done.
    """
    from tqdm.auto import tqdm

    device = model.stats_mean.device
    model.train()
    bar = tqdm(total=steps, initial=start, desc=description, unit="step", disable=not progress, dynamic_ncols=True)
    done = start
    try:
        for step in range(start, steps):
            if lr_at is not None:
                for group in optimizer.param_groups:
                    group["lr"] = lr_at(step)
            x, mu = sampler.sample(batch_size)
            x = x.to(device, non_blocking=True)
            mu = mu.to(device)
            loss, terms = training_loss(model, x, mu)
            adam_step(model, optimizer, loss, clip_norm)
            losses.append(terms)
            done = step + 1
            if on_step is not None:
                on_step(done, terms)
            if monitor is not None and monitor.due(done):
                monitor.evaluate(model, done)
            if progress and (done % 10 == 0 or done == steps):
                postfix = {"loss": f"{float(terms[0]):.3e}"}
                if monitor is not None and monitor.history:
                    postfix["val"] = f"{float(monitor.history[-1][1]):.3e}"
                bar.set_postfix(postfix, refresh=False)
            bar.update(1)
            stop = monitor is not None and monitor.stopped
            due = done == steps or stop or (checkpoint_every and done % checkpoint_every == 0)
            if checkpoint is not None and due:
                checkpoint(done)
            if stop:
                break
    finally:
        bar.close()
        model.eval()
    return done


@torch_threads("train")
def train_model(
    benchmark: Any,
    model: str = "koopman",
    r: int = 32,
    preset: str = "lite",
    T: int = 1,
    *,
    dataset: Dataset | None = None,
    data_preset: str = "paper",
    schedule: TrainingSchedule | None = None,
    seed: int = 0,
    device: str | torch.device = "cpu",
    resume: bool = True,
    checkpoint_every: int | None = None,
    path: Path | str | None = None,
    in_memory: bool | None = None,
    progress: bool = True,
    on_step: Callable[[int, torch.Tensor], None] | None = None,
) -> TrainingResult:
    """Train (or fit, for pDMD) a latent model and write its checkpoint; resume from it when present.

    ``schedule`` (steps, batch size, learning rate, validation) defaults to the ``preset``'s
    (:func:`~dks_gym.models.training_schedule`, which also makes one with other steps, batch size or lr); its
    ``steps`` is the total, so rerunning an interrupted (or shorter) run continues it. ``resume=False``
    starts afresh and overwrites the checkpoint. ``dataset`` defaults to ``load_dataset(benchmark,
    data_preset)``; ``path`` to :func:`checkpoint_path`. ``checkpoint_every`` defaults to a tenth of the
    steps (at most 1000). ``on_step(step, terms)`` is called after every optimizer step.
    """
    shape = benchmark_shape(benchmark, dataset)
    name = shape.name
    check_model_args(model, preset, r, T)
    device = resolve_device(device)
    if dataset is None:
        from ..dataset import load_dataset

        dataset = load_dataset(name, data_preset)
    if dataset.benchmark.name != name:
        raise ValueError(f"dataset {dataset.path} is for {dataset.benchmark.name}, not {name}")
    if path is None:
        path = checkpoint_path(shape, model, preset, r, T, data_preset=dataset.preset or "custom")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    start_time = time.perf_counter()
    with file_lock(path, "train"):  # concurrent trainers of one checkpoint wait instead of racing
        if model == "pdmd":
            return _fit_pdmd(shape, r, dataset, path, seed, device, resume, start_time)
        plan = plan_training(shape, model, r, preset, T, dataset=dataset, path=path, schedule=schedule, seed=seed,
                             device=device, checkpoint_every=checkpoint_every)
        previous = None
        if resume and path.exists():
            previous = read_metadata(path)
            check_resumable(previous, path, shape, model, preset, r, T, dataset, plan.settings(), plan.schedule)
            if previous["steps_done"] >= plan.schedule.steps or previous.get("stopped_early"):
                return _load_finished(plan, previous, start_time)  # done: load without the data
        run = set_up_training(plan, previous, in_memory=in_memory, progress=progress)
        done = fit_steps(
            run.state.net, run.state.optimizer, run.state.sampler, start=run.start, steps=plan.schedule.steps,
            batch_size=plan.schedule.batch_size, losses=run.state.losses, checkpoint=run.checkpoint,
            checkpoint_every=plan.checkpoint_every, progress=progress, description=plan.label, on_step=on_step,
            lr_at=plan.schedule.lr_at, monitor=run.state.monitor, clip_norm=plan.schedule.clip_norm,
        )
        return finish_training(run, done, start_time)


def plan_training(benchmark: Any, model: str, r: int, preset: str, T: int, *, dataset: Dataset, path: Path,
                  schedule: TrainingSchedule | None, seed: int, device: torch.device,
                  checkpoint_every: int | None) -> TrainingPlan:
    """The plan of a run: the schedule (the preset's unless given) checked and resolved for the training
    windows left after the validation split, and the checkpoint interval. ``benchmark``: a name, a benchmark
    object or its shape."""
    shape = benchmark_shape(benchmark, dataset)
    schedule = training_schedule(shape, preset) if schedule is None else schedule
    schedule.check()
    n_train = dataset.n_trajectories("train")
    held_out = validation_trajectories(n_train, schedule.validation_fraction, seed)
    schedule = schedule.resolve((n_train - len(held_out)) * (dataset.n_frames - T))
    if checkpoint_every is None:
        checkpoint_every = max(1, min(1000, schedule.steps // 10))
    return TrainingPlan(shape, model, r, preset, T, dataset, path, schedule, seed, device, held_out, checkpoint_every)


def set_up_training(plan: TrainingPlan, previous: dict[str, Any] | None, *, in_memory: bool | None,
                    progress: bool) -> TrainingRun:
    """Build the model, Adam, the batch sampler and the validation monitor of ``plan``; restore them from its
    checkpoint when ``previous`` (its metadata) says the run is resumed."""
    schedule, held_out = plan.schedule, plan.held_out
    net = build_model(plan.benchmark, plan.model, plan.r, plan.preset, dataset=plan.dataset, seed=plan.seed)
    net = net.to(plan.device)
    optimizer = adam(net, schedule.lr)
    fitted = [i for i in range(plan.dataset.n_trajectories("train")) if i not in held_out] if held_out else None
    sampler = WindowSampler(plan.dataset, plan.T, seed=plan.seed, in_memory=in_memory, progress=progress,
                            trajectories=fitted)
    monitor = ValidationMonitor(plan.dataset, held_out, plan.T, eval_every=schedule.eval_every,
                                patience=schedule.patience, batch_size=schedule.batch_size,
                                seed=plan.seed) if held_out else None
    state = TrainingState(net, optimizer, sampler, monitor)
    start, elapsed_before = 0, 0.0
    if previous is not None:
        start = state.restore(plan.path)
        elapsed_before = float(previous.get("train_time_s", 0.0))
    return TrainingRun(plan, state, start, elapsed_before, time.perf_counter())


def finish_training(run: TrainingRun, done: int, start_time: float) -> TrainingResult:
    """End a run after ``done`` steps: take the best weights, calibrate, write the final checkpoint and the
    loss-curve figure."""
    plan, net, monitor = run.plan, run.state.net, run.state.monitor
    if monitor is not None and monitor.best_state is not None:
        net.load_state_dict(monitor.best_state)
    # fit_steps returns at the last step or an early stop: the run is complete. Its calibration is measured
    # with the final weights on the held-out trajectories (without a validation split, on at most 10
    # training ones spread over the split: in-sample, so an underestimate), then stored with them.
    n_train = plan.dataset.n_trajectories("train")
    net.calibration = calibrate(net, plan.dataset, plan.held_out or evenly_spread(n_train, 10))
    run.checkpoint(done)
    net.checkpoint_path = plan.path
    history = torch.stack(run.state.losses).cpu().numpy()
    write_loss_curves(history, None if monitor is None else monitor.stacked().numpy(),
                      loss_curve_path(plan.path), plan.label)
    validated = monitor is not None and bool(monitor.history)
    return TrainingResult(net, plan.path, done, done - run.start, time.perf_counter() - start_time, history,
                          best_validation_loss=monitor.best_loss if validated else None,
                          stopped_early=monitor is not None and monitor.stopped)


def _load_finished(plan: TrainingPlan, previous: dict[str, Any], start_time: float) -> TrainingResult:
    """The result of a run whose checkpoint is complete already: its model, loaded without reading the data."""
    ckpt = read_checkpoint(plan.path, optimizer=False)
    history = ckpt.training["losses"].to(torch.float32).numpy()
    return TrainingResult(model_from_checkpoint(ckpt, plan.device), plan.path, int(previous["steps_done"]), 0,
                          time.perf_counter() - start_time, history, loaded_only=True,
                          best_validation_loss=previous.get("best_validation_loss"),
                          stopped_early=bool(previous.get("stopped_early")))


def _fit_pdmd(shape: BenchmarkShape, r: int, dataset: Dataset, path: Path, seed: int, device: torch.device,
              resume: bool, start_time: float) -> TrainingResult:
    """pDMD's "training": its closed-form fit on every training trajectory (or the fitted checkpoint, loaded)."""
    if resume and path.exists():
        ckpt = read_checkpoint(path, optimizer=False, training=False)
        check_metadata(ckpt.metadata, path, benchmark=shape, model="pdmd", r=r, dataset=dataset)
        if ckpt.metadata.get("seed") != seed:
            raise ValueError(
                f"checkpoint {path} was fitted with seed {ckpt.metadata.get('seed')}, not {seed}; "
                "use the same seed or refit with --restart (resume=False)"
            )
        model = model_from_checkpoint(ckpt, device)
        return TrainingResult(model, path, 0, 0, time.perf_counter() - start_time, np.zeros((0, 4), np.float32),
                              loaded_only=True)
    model = build_model(shape, "pdmd", r, dataset=dataset).to(device)
    model.fit_dataset(dataset, seed=seed)
    # pDMD has no validation split (its fit is closed-form on every training trajectory): calibrated in-sample.
    model.calibration = calibrate(model, dataset, range(dataset.n_trajectories("train")))
    fit_time = time.perf_counter() - start_time
    meta = build_metadata(model, preset="", T=1, dataset=dataset, steps_done=0, steps=0, batch_size=None,
                          lr=None, seed=seed, complete=True, device=str(device), train_time_s=fit_time,
                          calibrated_on="train")
    save_checkpoint(path, model, meta)
    model.checkpoint_path = path
    return TrainingResult(model.eval(), path, 0, 0, time.perf_counter() - start_time, np.zeros((0, 4), np.float32))


__all__ = [
    "TrainingPlan",
    "TrainingResult",
    "TrainingRun",
    "adam",
    "adam_step",
    "finish_training",
    "fit_steps",
    "plan_training",
    "resolve_device",
    "set_up_training",
    "train_model",
]
