"""Training of the latent models (Eqs. 10-11) and the single entry point :func:`load_model`.

Loss (Eq. 10 with lambda_1 = lambda_2 = lambda_3 = 1, multi-step form Eq. 11), for a window
x_k, ..., x_{k+T} of one training trajectory with parameter mu::

    z_j   = E(x_{k+j}, mu)                      encodings of every frame of the window (targets)
    zh_0  = z_0,  zh_{j+1} = F(zh_j, mu)        unrolled from the first encoding only
    L     = mse(G(z_0), x_k)                                        reconstruction, initial step only
          + 1/T sum_{j=1..T} mse(G(zh_j), x_{k+j})                  decoded prediction
          + 1/T sum_{j=1..T} mse(zh_j, z_j)                         latent prediction

``mse`` is the mean of the squared differences over every element (batch, channels, grid cells; for
the latent term batch and the r latent coordinates), in normalized units: G is
``decode_normalized`` and the targets are ``reconstruction_target`` (per-channel standardized fields,
plus the cell type on the sphere, whose decoder outputs it). Per-element means put the three terms on
the same scale whatever the grid size and r; the paper's squared norms would weight the field terms by
N / r relative to the latent term. Gradients flow through the target encodings z_j (j >= 1) as well:
the paper does not say, this is the common choice, and the reconstruction term keeps the encoder from
collapsing to make the latent term trivial.

Batches are B windows (trajectory, k) drawn uniformly with replacement from the train split with a
seeded ``torch.Generator``; the train split is read into memory once when it fits (less than half the
available memory), otherwise every window is read from the HDF5 file (sphere, paper preset, on most
machines). Adam. The ``paper`` schedule is the paper's: a constant lr 1e-4, 1000 steps at batch 256
(burgers, cylinder, dambreak), 40000 at batch 32 (sphere), every training trajectory. The ``lite``
schedule (:data:`TRAINING_SCHEDULES`) is the one users meet: lr 1e-3 with a linear warm-up and a cosine
decay, a number of epochs (capped in steps), 10 % of the training trajectories held out for validation
(:func:`validation_trajectories`, by trajectory, seeded), the validation loss measured along the run
(:class:`ValidationMonitor`), the best-on-validation weights kept and early stopping. After training,
:func:`calibrate` measures the model's own errors on the held-out trajectories (the process noise Q of a
calibrated filter, the decoder's reconstruction variance per cell) and stores them with the weights, and
a loss-curve figure is written beside the checkpoint. Training is resumable: the checkpoint (written every
``checkpoint_every`` steps and at the end) holds the weights (best and last), the Adam state, the sampler's
generator state and the loss and validation history, so an interrupted run continues to exactly the
weights an uninterrupted one reaches (bit-identical on CPU). pDMD has no optimizer: its "training" is
``fit_dataset``.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..locks import file_lock
from ..threads import torch_threads
from .checkpoint import (
    CheckpointMissing,
    build_metadata,
    check_metadata,
    check_model_args,
    checkpoint_path,
    loss_curve_path,
    model_from_checkpoint,
    read_checkpoint,
    read_metadata,
    save_checkpoint,
    train_command,
)
from .build import build_model
from .latent_model import LatentModel, NeuralLatentModel
from .loss_curves import write_loss_curves
from .presets import benchmark_shape
from .shipped import find_shipped

logger = logging.getLogger(__name__)

LEARNING_RATE = 1e-4  # Adam, all models and benchmarks (the paper's training tables)
LOSS_TERMS = ("total", "reconstruction", "prediction", "latent")


@dataclass(frozen=True)
class TrainingSchedule:
    """Adam steps, batch size and learning rate of one benchmark in one training preset, and how the run is
    watched: a learning-rate schedule, a validation split and early stopping (all off by default, which is
    the paper's plain constant-rate training)."""

    steps: int  # Adam steps; with ``epochs``, the most steps
    batch_size: int
    lr: float
    epochs: float | None = None  # passes over the training windows (capped at ``steps``); None: ``steps``
    warmup: float = 0.0  # fraction of the steps with a linear warm-up to lr
    final_lr: float | None = None  # cosine decay from lr to final_lr at the last step; None keeps lr constant
    validation_fraction: float = 0.0  # training trajectories held out for validation (by trajectory, seeded)
    validations: int = 0  # validation losses per run, evenly spaced (0: no validation)
    patience: int = 0  # validations without a 1 % improvement before stopping early (0: never stop early)

    def resolve(self, n_windows: int) -> "TrainingSchedule":
        """This schedule with its step count fixed for ``n_windows`` training windows (``epochs`` applied)."""
        if self.epochs is None:
            return self
        steps = min(self.steps, max(1, math.ceil(self.epochs * n_windows / self.batch_size)))
        return dataclasses.replace(self, steps=steps, epochs=None)

    @property
    def warmup_steps(self) -> int:
        return round(self.warmup * self.steps)

    @property
    def eval_every(self) -> int:
        return max(1, self.steps // self.validations) if self.validations else 0

    def lr_at(self, step: int) -> float:
        """The learning rate of optimizer step ``step`` (0-based)."""
        warmup = self.warmup_steps
        if step < warmup:
            return self.lr * (step + 1) / warmup
        if self.final_lr is None:
            return self.lr
        progress = (step - warmup) / max(1, self.steps - warmup)
        return self.final_lr + 0.5 * (self.lr - self.final_lr) * (1.0 + math.cos(math.pi * min(progress, 1.0)))

    def record(self) -> dict[str, Any]:
        """The schedule as checkpoint metadata."""
        return dataclasses.asdict(self)


# paper: the paper's training tables, unchanged (its tables reproduce with it). lite: the narrow ``lite``
# architectures, trained until they converge on one CPU core in minutes (docs/training.md has the curves):
# lr 1e-3 (at 1e-4 the lite Burgers models are still at a loss of ~0.1 after 1000 steps), 5 % warm-up, cosine
# decay to 1e-5, 60 epochs of the training windows capped at 8000 steps (Burgers, ~0.03 s per step) or 3000
# (the 64 x 64 CFD grids, ~0.2 s per step at batch 16), best-on-validation weights and early stopping after
# 12 (8) validations without a 1 % gain. The sphere's lite schedule is sized by time (0.9 s per step at
# batch 4) and has no validation split.
TRAINING_SCHEDULES: dict[str, dict[str, TrainingSchedule]] = {
    "paper": {
        "burgers": TrainingSchedule(1000, 256, LEARNING_RATE),
        "cylinder": TrainingSchedule(1000, 256, LEARNING_RATE),
        "dambreak": TrainingSchedule(1000, 256, LEARNING_RATE),
        "sphere": TrainingSchedule(40000, 32, LEARNING_RATE),
    },
    "lite": {
        "burgers": TrainingSchedule(8000, 32, 1e-3, epochs=60, warmup=0.05, final_lr=1e-5, validation_fraction=0.1,
                                    validations=50, patience=12),
        "cylinder": TrainingSchedule(3000, 16, 1e-3, epochs=60, warmup=0.05, final_lr=1e-5, validation_fraction=0.1,
                                     validations=30, patience=8),
        "dambreak": TrainingSchedule(3000, 16, 1e-3, epochs=60, warmup=0.05, final_lr=1e-5, validation_fraction=0.1,
                                     validations=30, patience=8),
        "sphere": TrainingSchedule(300, 4, 1e-3),
    },
}


def training_schedule(benchmark: Any, preset: str) -> TrainingSchedule:
    """Default steps, batch size and learning rate of ``benchmark`` for the ``preset`` ("paper" or "lite")."""
    if preset not in TRAINING_SCHEDULES:
        raise ValueError(f"unknown preset {preset!r}; choose one of {', '.join(TRAINING_SCHEDULES)}")
    return TRAINING_SCHEDULES[preset][benchmark_shape(benchmark).name]


# Loss -----------------------------------------------------------------------------------------------
def training_loss(
    model: NeuralLatentModel, window: torch.Tensor, mu: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Eq. 10 (T = 1) / Eq. 11 on a batch of windows (B, T + 1, C, *grid) in physical units, mu (B,).

    Returns the scalar loss and the detached (4,) vector (total, reconstruction, prediction, latent).
    All frames are encoded, and the reconstruction and the T predictions decoded, in one batched call each.
    """
    if window.ndim < 3 or window.shape[1] < 2:
        raise ValueError(
            f"a training window must have shape (B, T + 1, C, *grid) with T >= 1, got {tuple(window.shape)}"
        )
    b, n = window.shape[:2]
    horizon = n - 1
    frames = window.reshape(b * n, *window.shape[2:])
    mu_frames = mu.repeat_interleave(n)
    z_true = model.encode(frames, mu_frames).view(b, n, model.r)
    target = model.reconstruction_target(frames).view(b, n, -1)
    z_hat = [z_true[:, 0]]
    for _ in range(horizon):  # Eq. 11: unrolled from one encoding, no re-injection
        z_hat.append(model.forecast(z_hat[-1], mu))
    z_pred = torch.stack(z_hat[1:], dim=1)  # (B, T, r)
    # Decode z_0 and zh_1..zh_T together: rows ordered (b, j) with j = 0..T.
    decoded = model.decode_normalized(torch.stack(z_hat, dim=1).reshape(b * n, model.r), mu_frames).view(b, n, -1)
    reconstruction = torch.mean((decoded[:, 0] - target[:, 0]) ** 2)
    prediction = torch.mean((decoded[:, 1:] - target[:, 1:]) ** 2)
    latent = torch.mean((z_pred - z_true[:, 1:]) ** 2)
    loss = reconstruction + prediction + latent
    return loss, torch.stack([loss, reconstruction, prediction, latent]).detach()


# Data -----------------------------------------------------------------------------------------------
def _available_memory() -> int | None:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


class WindowSampler:
    """Random windows of ``horizon + 1`` consecutive frames from one split of a dataset.

    ``sample(B)`` draws B (trajectory, k) pairs uniformly with replacement, k in [0, n_t - horizon - 1],
    with its own seeded ``torch.Generator`` (``state()``/``set_state()`` for resuming), and returns the
    windows (B, horizon + 1, C, *grid) float32 on the CPU in physical units and mu (B,) float64.
    ``in_memory=None`` reads the split into memory once if it takes less than half the available memory.
    """

    def __init__(
        self, dataset: Any, horizon: int = 1, *, seed: int = 0, split: str = "train",
        in_memory: bool | None = None, progress: bool = False, trajectories: Sequence[int] | None = None,
    ) -> None:
        self.dataset, self.split = dataset, split
        self.fields = dataset.fields(split)
        self.params = torch.as_tensor(dataset.params(split), dtype=torch.float64)
        n_split, self.n_t = int(self.fields.shape[0]), int(self.fields.shape[1])
        # The trajectories windows come from (``trajectories``, e.g. a training split without its validation
        # trajectories), and each one's row in the in-memory copy.
        self.trajectories = torch.arange(n_split) if trajectories is None else torch.as_tensor(
            sorted({int(i) for i in trajectories}), dtype=torch.long)
        if len(self.trajectories) == 0 or int(self.trajectories.min()) < 0 or int(self.trajectories.max()) >= n_split:
            raise ValueError(f"trajectories must be a non-empty subset of 0..{n_split - 1} of split {split!r}")
        self._row = torch.full((n_split,), -1, dtype=torch.long)
        self._row[self.trajectories] = torch.arange(len(self.trajectories))
        self.n_traj = len(self.trajectories)
        self.horizon = int(horizon)
        if self.horizon < 1 or self.horizon >= self.n_t:
            raise ValueError(
                f"horizon T must be in [1, {self.n_t - 1}] for trajectories of {self.n_t} frames, got {horizon}"
            )
        self.generator = torch.Generator().manual_seed(int(seed))
        nbytes = self.n_traj * int(np.prod(self.fields.shape[1:])) * 4
        if in_memory is None:
            available = _available_memory()
            in_memory = nbytes <= (available // 2 if available is not None else 4 << 30)
        self.in_memory = bool(in_memory)
        self.data: torch.Tensor | None = None
        if self.in_memory:
            self.data = torch.from_numpy(self._read_all(progress and nbytes > 1 << 30))
        self._offsets = torch.arange(self.horizon + 1)

    def _read_all(self, progress: bool) -> np.ndarray:
        from tqdm.auto import tqdm

        out = np.empty((self.n_traj, *self.fields.shape[1:]), dtype=np.float32)
        for row, i in enumerate(tqdm(self.trajectories.tolist(), desc="reading train split", unit="traj",
                                     disable=not progress)):
            out[row] = self.dataset.read(self.split, i)  # one trajectory (one set of chunks) at a time
        return out

    @property
    def n_windows(self) -> int:
        return self.n_traj * (self.n_t - self.horizon)

    def draw(self, batch_size: int) -> tuple[torch.Tensor, torch.Tensor]:
        """B (trajectory, start frame) index pairs; trajectories are indices into the split."""
        traj = self.trajectories[torch.randint(self.n_traj, (batch_size,), generator=self.generator)]
        start = torch.randint(self.n_t - self.horizon, (batch_size,), generator=self.generator)
        return traj, start

    def windows(self, traj: torch.Tensor, start: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The windows starting at the given (trajectory, frame) pairs and their parameters."""
        if self.data is not None:
            x = self.data[self._row[traj][:, None], start[:, None] + self._offsets]
        else:
            x = torch.from_numpy(np.stack([
                self.dataset.read(self.split, int(i), slice(int(k), int(k) + self.horizon + 1))
                for i, k in zip(traj, start)
            ]))
        return x, self.params[traj]

    def sample(self, batch_size: int) -> tuple[torch.Tensor, torch.Tensor]:
        return self.windows(*self.draw(batch_size))

    def state(self) -> torch.Tensor:
        return self.generator.get_state()

    def set_state(self, state: torch.Tensor) -> None:
        self.generator.set_state(state)


# Training loop --------------------------------------------------------------------------------------
def _device(device: str | torch.device) -> torch.device:
    try:
        device = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise ValueError(f"unknown device {device!r}; use 'cpu', 'cuda' or 'cuda:N'") from exc
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("device 'cuda' was requested but CUDA is not available; use device='cpu'")
    return device


def validation_trajectories(n_train: int, fraction: float, seed: int) -> list[int]:
    """The training trajectories held out for validation: ``round(fraction * n_train)`` of them (at least one
    when ``fraction`` > 0, and never all), drawn with ``seed``, sorted."""
    if fraction <= 0:
        return []
    n_val = min(n_train - 1, max(1, round(fraction * n_train)))
    if n_val < 1:
        raise ValueError(f"a validation split needs at least two training trajectories, got {n_train}")
    return sorted(np.random.default_rng(seed).permutation(n_train)[:n_val].tolist())


class ValidationMonitor:
    """The loss (Eq. 10/11 terms) on held-out trajectories every ``eval_every`` steps; keeps the best weights
    and says when to stop early (``patience`` validations without a 1 % improvement).

    The windows are fixed: every (trajectory, start) pair of the validation trajectories, or ``max_windows``
    of them drawn with ``seed``. Its state (``history``, the best weights) is saved with the checkpoint and
    replayed on resume, so a resumed run stops where an uninterrupted one would.
    """

    def __init__(self, dataset: Any, trajectories: Sequence[int], horizon: int, *, eval_every: int, patience: int,
                 batch_size: int, max_windows: int = 256, seed: int = 0) -> None:
        self.sampler = WindowSampler(dataset, horizon, seed=seed, trajectories=trajectories)
        self.trajectories = [int(i) for i in trajectories]
        n = self.sampler.n_windows
        index = torch.arange(n) if n <= max_windows else torch.randperm(
            n, generator=torch.Generator().manual_seed(seed))[:max_windows].sort().values
        span = self.sampler.n_t - horizon
        self._windows = (self.sampler.trajectories[index // span], index % span)
        self.eval_every, self.patience, self.batch_size = int(eval_every), int(patience), int(batch_size)
        self.history: list[torch.Tensor] = []  # (5,) per validation: step, total, reconstruction, prediction, latent
        self.best_state: dict[str, torch.Tensor] | None = None
        self.best_step, self.best_loss = 0, math.inf
        self._reference, self._since = math.inf, 0

    @property
    def stopped(self) -> bool:
        """Whether the patience has run out."""
        return bool(self.patience) and self._since >= self.patience

    def due(self, step: int) -> bool:
        return self.eval_every > 0 and step % self.eval_every == 0

    @torch.no_grad()
    def loss(self, model: NeuralLatentModel) -> torch.Tensor:
        """Mean (4,) loss terms over the validation windows, in eval mode."""
        was_training = model.training
        model.eval()
        device = model.stats_mean.device
        total, count = torch.zeros(4, dtype=torch.float64), 0
        traj, start = self._windows
        for lo in range(0, len(traj), self.batch_size):
            x, mu = self.sampler.windows(traj[lo: lo + self.batch_size], start[lo: lo + self.batch_size])
            _, terms = training_loss(model, x.to(device), mu.to(device))
            total += terms.double().cpu() * x.shape[0]
            count += x.shape[0]
        model.train(was_training)
        return (total / count).float()

    def evaluate(self, model: NeuralLatentModel, step: int) -> None:
        """Record the validation loss at ``step``; keep the weights if they are the best so far."""
        terms = self.loss(model)
        self._record(step, terms)
        if step == self.best_step:
            self.best_state = {k: v.detach().clone() for k, v in model.state_dict().items()}

    def _record(self, step: int, terms: torch.Tensor) -> None:
        self.history.append(torch.cat([torch.tensor([float(step)]), terms.float()]))
        value = float(terms[0])
        if value < self.best_loss:
            self.best_loss, self.best_step = value, step
        if value < 0.99 * self._reference:
            self._reference, self._since = value, 0
        else:
            self._since += 1

    def restore(self, history: torch.Tensor, best_state: dict[str, torch.Tensor]) -> None:
        """Replay a saved history (m, 5) and take the saved best weights."""
        for row in history.float():
            self._record(int(row[0]), row[1:])
        self.best_state = {k: v.clone() for k, v in best_state.items()}

    def stacked(self) -> torch.Tensor:
        """The history as an (m, 5) tensor (an empty (0, 5) one before the first validation)."""
        return torch.stack(self.history) if self.history else torch.zeros(0, 5)


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
) -> int:
    """Adam steps ``start`` .. ``steps`` - 1; ``losses`` gets one (4,) tensor per step (see LOSS_TERMS).

    ``lr_at(step)`` sets the learning rate of each step; ``monitor`` validates every ``eval_every`` steps and
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
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
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
            if checkpoint is not None and (done == steps or stop or (checkpoint_every and done % checkpoint_every == 0)):
                checkpoint(done)
            if stop:
                break
    finally:
        bar.close()
        model.eval()
    return done


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


@torch_threads("train")
def train_model(
    benchmark: Any,
    model: str = "koopman",
    r: int = 32,
    preset: str = "lite",
    T: int = 1,
    *,
    dataset: Any = None,
    data_preset: str = "paper",
    steps: int | None = None,
    batch_size: int | None = None,
    lr: float | None = None,
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

    ``steps``, ``batch_size`` and ``lr`` default to the ``preset``'s schedule (:data:`TRAINING_SCHEDULES`);
    ``steps`` is the total, so rerunning an interrupted (or shorter) run continues it. ``resume=False``
    starts afresh and overwrites the checkpoint. ``dataset`` defaults to ``load_dataset(benchmark,
    data_preset)``; ``path`` to :func:`checkpoint_path`. ``checkpoint_every`` defaults to a tenth of the
    steps (at most 1000). ``on_step(step, terms)`` is called after every optimizer step.
    """
    name = benchmark_shape(benchmark).name
    check_model_args(model, preset, r, T)
    device = _device(device)
    if dataset is None:
        from ..dataset import load_dataset

        dataset = load_dataset(name, data_preset)
    if dataset.benchmark.name != name:
        raise ValueError(f"dataset {dataset.path} is for {dataset.benchmark.name}, not {name}")
    if path is None:
        path = checkpoint_path(name, model, preset, r, T, data_preset=dataset.preset or "custom")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    start_time = time.perf_counter()
    with file_lock(path, "train"):  # concurrent trainers of one checkpoint wait instead of racing
        if model == "pdmd":
            return _fit_pdmd(name, r, dataset, path, seed, device, resume, start_time)
        schedule = training_schedule(name, preset)
        if steps is not None:  # an explicit step count replaces the preset's epochs and early stopping
            schedule = dataclasses.replace(schedule, steps=int(steps), epochs=None, patience=0)
        if batch_size is not None or lr is not None:
            schedule = dataclasses.replace(schedule, batch_size=schedule.batch_size if batch_size is None else
                                           int(batch_size), lr=schedule.lr if lr is None else float(lr))
        if schedule.steps < 1 or schedule.batch_size < 1:
            raise ValueError(f"steps and batch_size must be positive, got {schedule.steps} and {schedule.batch_size}")
        if not schedule.lr > 0:
            raise ValueError(f"learning rate must be positive, got {schedule.lr}")
        n_train = dataset.n_trajectories("train")
        held_out = validation_trajectories(n_train, schedule.validation_fraction, seed)
        fitted = [i for i in range(n_train) if i not in held_out] if held_out else None
        schedule = schedule.resolve((n_train - len(held_out)) * (dataset.n_frames - T))
        steps, batch_size, lr = schedule.steps, schedule.batch_size, schedule.lr
        if checkpoint_every is None:
            checkpoint_every = max(1, min(1000, steps // 10))

        settings = {"batch_size": batch_size, "lr": lr, "seed": seed, "schedule": schedule.record()}
        previous = None
        if resume and path.exists():
            previous = read_metadata(path)
            _check_resumable(previous, path, name, model, preset, r, T, dataset, settings)
            if previous["steps_done"] >= steps or previous.get("stopped_early"):  # done: load without the data
                ckpt = read_checkpoint(path, optimizer=False)
                history = ckpt.training["losses"].to(torch.float32).numpy()
                return TrainingResult(model_from_checkpoint(ckpt, device), path, int(previous["steps_done"]), 0,
                                      time.perf_counter() - start_time, history, loaded_only=True,
                                      best_validation_loss=previous.get("best_validation_loss"),
                                      stopped_early=bool(previous.get("stopped_early")))

        net = build_model(name, model, r, preset, dataset=dataset, seed=seed).to(device)
        optimizer = torch.optim.Adam(net.parameters(), lr=lr)
        sampler = WindowSampler(dataset, T, seed=seed, in_memory=in_memory, progress=progress, trajectories=fitted)
        monitor = ValidationMonitor(dataset, held_out, T, eval_every=schedule.eval_every, patience=schedule.patience,
                                    batch_size=batch_size, seed=seed) if held_out else None
        losses: list[torch.Tensor] = []
        start, elapsed_before = 0, 0.0
        if previous is not None:
            start = _restore(path, net, optimizer, sampler, losses, monitor)
            elapsed_before = float(previous.get("train_time_s", 0.0))

        loop_start = time.perf_counter()

        def write(done: int) -> None:
            stopped = monitor is not None and monitor.stopped
            meta = build_metadata(
                net, preset=preset, T=T, dataset=dataset, steps_done=done, steps=steps, batch_size=batch_size,
                lr=lr, seed=seed, complete=done >= steps or stopped, device=str(device), loss_terms=list(LOSS_TERMS),
                train_time_s=elapsed_before + time.perf_counter() - loop_start, schedule=schedule.record(),
                preset_schedule=training_schedule(name, preset).record(),
                validation_trajectories=held_out, stopped_early=stopped,
                calibrated_on="validation" if held_out else "train",
                best_step=monitor.best_step if monitor is not None else None,
                best_validation_loss=monitor.best_loss if monitor is not None and monitor.history else None,
            )
            tensors = {"generator": sampler.state(), "losses": torch.stack(losses).cpu()}
            weights = None
            if monitor is not None:  # the model section holds the best weights; resuming needs the last ones
                tensors["validation"] = monitor.stacked()
                tensors.update({_LAST + k: v for k, v in net.state_dict().items()})
                weights = monitor.best_state
            save_checkpoint(path, net, meta, optimizer_state=optimizer.state_dict(), training_tensors=tensors,
                            model_state=weights)

        done = fit_steps(
            net, optimizer, sampler, start=start, steps=steps, batch_size=batch_size, losses=losses,
            checkpoint=write, checkpoint_every=checkpoint_every, progress=progress,
            description=f"{name} {model} {preset} r={r} T={T}", on_step=on_step,
            lr_at=schedule.lr_at, monitor=monitor,
        )
        if monitor is not None and monitor.best_state is not None:
            net.load_state_dict(monitor.best_state)
        # fit_steps returns at the last step or an early stop: the run is complete. Its calibration is measured
        # with the final weights on the held-out trajectories (without a validation split, on at most 10
        # training ones spread over the split: in-sample, so an underestimate), then stored with them.
        net.calibration = calibrate(net, dataset, held_out or _spread(n_train, 10))
        write(done)
        net.checkpoint_path = path
        history = torch.stack(losses).cpu().numpy()
        write_loss_curves(history, None if monitor is None else monitor.stacked().numpy(),
                          loss_curve_path(path), f"{name} {model} {preset} r={r} T={T}")
        return TrainingResult(net, path, done, done - start, time.perf_counter() - start_time, history,
                              best_validation_loss=monitor.best_loss if monitor is not None and monitor.history
                              else None, stopped_early=monitor is not None and monitor.stopped)


def _check_resumable(meta: dict[str, Any], path: Path, name: str, model: str, preset: str, r: int, T: int,
                     dataset: Any, settings: dict[str, Any]) -> None:
    check_metadata(meta, path, benchmark=name, model=model, r=r, preset=preset, T=T, dataset=dataset)
    for key, value in settings.items():
        if meta.get(key) != value:
            raise ValueError(
                f"checkpoint {path} was trained with {key} = {meta.get(key)!r}, not {value!r}, so it cannot be "
                f"resumed with these settings; use the same settings, or start afresh with --restart "
                f"(resume=False), which overwrites it"
            )


_LAST = "last."  # training-tensor prefix of the last weights, when the model section holds the best ones


def _restore(path: Path, net: NeuralLatentModel, optimizer: torch.optim.Optimizer, sampler: WindowSampler,
             losses: list[torch.Tensor], monitor: ValidationMonitor | None = None) -> int:
    """Load weights, Adam state, sampler state, loss and validation history; return the number of steps done."""
    ckpt = read_checkpoint(path)
    last = {k[len(_LAST):]: v for k, v in ckpt.training.items() if k.startswith(_LAST)}
    net.load_state_dict(last or ckpt.model_state)
    if monitor is not None:
        monitor.restore(ckpt.training.get("validation", torch.zeros(0, 5)), ckpt.model_state)
    state = optimizer.state_dict()
    optimizer.load_state_dict({"state": ckpt.optimizer_state, "param_groups": state["param_groups"]})
    sampler.set_state(ckpt.training["generator"])
    losses.extend(ckpt.training["losses"].to(net.stats_mean.device, torch.float32).unbind(0))
    return int(ckpt.metadata["steps_done"])


def _fit_pdmd(name: str, r: int, dataset: Any, path: Path, seed: int, device: torch.device, resume: bool,
              start_time: float) -> TrainingResult:
    if resume and path.exists():
        ckpt = read_checkpoint(path, optimizer=False, training=False)
        check_metadata(ckpt.metadata, path, benchmark=name, model="pdmd", r=r, dataset=dataset)
        if ckpt.metadata.get("seed") != seed:
            raise ValueError(
                f"checkpoint {path} was fitted with seed {ckpt.metadata.get('seed')}, not {seed}; "
                "use the same seed or refit with --restart (resume=False)"
            )
        model = model_from_checkpoint(ckpt, device)
        return TrainingResult(model, path, 0, 0, time.perf_counter() - start_time, np.zeros((0, 4), np.float32),
                              loaded_only=True)
    model = build_model(name, "pdmd", r, dataset=dataset).to(device)
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


# The single entry point -------------------------------------------------------------------------------
def is_stale(meta: dict[str, Any], benchmark: str, model: str, preset: str) -> bool:
    """Whether a finished checkpoint (its ``meta``) was trained with another schedule than ``preset``'s current
    one (an older dks-gym, custom steps): :func:`load_model` retrains such a cached checkpoint."""
    return (bool(meta.get("complete")) and model != "pdmd"
            and meta.get("preset_schedule") != training_schedule(benchmark, preset).record())


@dataclass(frozen=True)
class ModelLookup:
    """Where :func:`load_model` finds a trained model without training, and what to say when it does not."""

    found: Path | None  # the file to load: the user's checkpoint or the shipped one; None when neither serves
    checkpoint: Path  # the user's checkpoint path (where training writes)
    reason: str  # why nothing was found (empty when found)
    command: str  # the `dks-gym train` command that makes it
    stale: bool  # the user's checkpoint exists but was trained with another schedule


def locate_model(benchmark: Any, model: str, r: int = 32, preset: str = "lite", T: int = 1, *, dataset: Any = None,
                 data_preset: str = "paper", path: Path | str | None = None) -> ModelLookup:
    """The lookup of :func:`load_model`, without loading or training: the user's own complete checkpoint
    (``path``, or the data home's), else the shipped model when ``dataset`` matches its training data.
    Raises ValueError for a checkpoint of another benchmark, r, preset, T or dataset."""
    name = benchmark_shape(benchmark).name
    check_model_args(model, preset, r, T)
    if dataset is not None and dataset.benchmark.name != name:
        raise ValueError(f"dataset {dataset.path} is for {dataset.benchmark.name}, not {name}")
    data_preset = (dataset.preset or "custom") if dataset is not None else data_preset
    cached = path is None  # the data home's checkpoint must follow the preset; an explicit path is taken as is
    path = Path(path) if path is not None else checkpoint_path(name, model, preset, r, T, data_preset=data_preset)
    command = train_command(name, model, preset, r, T, data_preset)
    stale = False
    if path.exists():
        meta = read_metadata(path)
        check_metadata(meta, path, benchmark=name, model=model, r=r, preset=preset, T=T, dataset=dataset)
        stale = cached and is_stale(meta, name, model, preset)
        if meta.get("complete") and not stale:
            return ModelLookup(path, path, "", command, False)
        if stale:  # trained by an older dks-gym, or with other settings than the preset's
            reason = (f"{path} was trained with another schedule than the current {preset} preset's "
                      f"({meta.get('steps_done')} steps; schedule {meta.get('schedule')})")
            command += " --restart"
        else:
            reason = f"training in {path} stopped at step {meta.get('steps_done')} of {meta.get('steps')}"
    else:
        reason = f"no trained {name} {model} model (preset {preset}, r={r}, T={T}) at {path}"
    shipped = find_shipped(name, model, preset, r, T) if cached else None
    if shipped is not None:
        differences = [] if dataset is None else shipped.differences(dataset)
        if not differences:
            return ModelLookup(shipped.path, path, "", command, stale)
        reason += (f"; the {name} {model} model that ships with dks-gym was trained on other data than "
                   f"{dataset.path}: {'; '.join(differences)}")
    return ModelLookup(None, path, reason, command, stale)


def load_model(
    benchmark: Any,
    model: str,
    r: int = 32,
    preset: str = "lite",
    T: int = 1,
    *,
    dataset: Any = None,
    data_preset: str = "paper",
    train_if_missing: bool = False,
    device: str | torch.device = "cpu",
    progress: bool = True,
    path: Path | str | None = None,
) -> LatentModel:
    """The trained ``model`` of ``benchmark``, in eval mode on ``device``.

    Looked up in this order: the user's own checkpoint (``path``, or the data home's
    ``models/`` for (benchmark, model, preset, r, T) and the dataset preset of ``dataset`` or
    ``data_preset``); then the model that ships with dks-gym (:mod:`dks_gym.models.shipped`), used only
    when ``dataset`` matches the data it was trained on; then, with ``train_if_missing=True``, training
    (or resuming) it with the preset's schedule and a progress bar. Otherwise :class:`CheckpointMissing`
    (a FileNotFoundError) says what was looked for, what differs from a shipped model, and names the
    ``dks-gym train`` command. A cached checkpoint trained with another schedule than the preset's (an
    older dks-gym, custom steps) is passed over; one given by ``path`` is loaded as it is. A checkpoint
    for another benchmark, r, preset or T, or trained on another dataset than ``dataset``, raises
    ValueError. Nothing is written unless ``train_if_missing`` trains.
    """
    name = benchmark_shape(benchmark).name
    lookup = locate_model(name, model, r, preset, T, dataset=dataset, data_preset=data_preset, path=path)
    if lookup.found is not None:
        return model_from_checkpoint(lookup.found, _device(device))
    data_preset = (dataset.preset or "custom") if dataset is not None else data_preset
    path, reason, command, stale = lookup.checkpoint, lookup.reason, lookup.command, lookup.stale
    if not train_if_missing:
        raise CheckpointMissing(
            f"{reason}. Train it with `{command}`{'' if stale else ' (it resumes an unfinished run)'}, or call "
            "load_model(..., train_if_missing=True)."
        )
    what = ("retraining it with the current schedule" if stale else
            "resuming its unfinished training" if path.exists() else "training it on first use")
    logger.info("%s %s model (%s, r=%d, T=%d): %s, as `%s` would; it is kept at %s for later runs",
                name, model, preset, r, T, what, command, path)
    result = train_model(name, model, r, preset, T, dataset=dataset, data_preset=data_preset, device=device,
                         path=path, progress=progress, resume=not stale)
    return result.model


# Calibration ----------------------------------------------------------------------------------------
def _spread(n: int, most: int) -> list[int]:
    """At most ``most`` of the indices 0..n-1, evenly spread (all of them when n <= most)."""
    return sorted({int(round(i)) for i in np.linspace(0, n - 1, min(n, most))})


def _definite(cov: torch.Tensor, floor: float = 1e-6) -> torch.Tensor:
    """``cov`` + ``floor`` * (its mean variance) * I: definite in float32 too, whatever its rank."""
    return cov + floor * float(cov.trace()) / cov.shape[0] * torch.eye(cov.shape[0], dtype=cov.dtype)


@torch.no_grad()
def calibrate(model: LatentModel, dataset: Any, trajectories: Sequence[int], split: str = "train",
              chunk: int = 16) -> dict[str, torch.Tensor]:
    """What the filters need to know about a model's own errors, measured on ``trajectories`` of ``split``.

    ``Q`` (r, r) float64: the second moment of the latent one-step residuals z_{k+1} - F(z_k, mu) with
    z_k = E(x_k, mu) over every frame pair, the process noise a filter should assume (its mean, if any, is
    part of the error the filter must cover). ``P0`` (r, r) float64: the error covariance of the approximate
    initial condition, the spread of the encoded first frames of every training trajectory around their
    mean, plus ``Q``; ``P0_exact`` that of the exact one, ``Q``. Both with a floor of 1e-6 times their mean
    variance, so that they stay definite in float32. ``reconstruction_variance`` (C, *grid) float32: the mean over
    frames of (decode(encode(x)) - x)^2 per cell in physical units, the error a decoded estimate carries even
    with an exact latent state. ``trajectories`` (int64): the trajectories measured on, where the filter's scale
    of ``Q`` is tuned later (:func:`dks_gym.assimilation.tune_process_noise`). Frames are encoded ``chunk`` at a time.
    """
    device = model.stats_mean.device
    params = dataset.params(split)
    r = model.r
    q = torch.zeros(r, r, dtype=torch.float64)
    squares: torch.Tensor | None = None
    pairs = frames = 0
    for i in trajectories:
        x = torch.as_tensor(dataset.read(split, int(i)))
        mu = torch.full((x.shape[0],), float(params[int(i)]), dtype=torch.float64, device=device)
        z = torch.cat([model.encode(x[k:k + chunk].to(device), mu[k:k + chunk]) for k in range(0, len(x), chunk)])
        residual = (z[1:] - model.forecast(z[:-1], mu[1:])).double().cpu()
        q += residual.T @ residual
        pairs += residual.shape[0]
        for k in range(0, len(x), chunk):
            err = (model.decode(z[k:k + chunk], mu[k:k + chunk]).cpu() - x[k:k + chunk]).double() ** 2
            squares = err.sum(0) if squares is None else squares + err.sum(0)
        frames += x.shape[0]
    if not pairs:
        raise ValueError("calibrate needs at least one trajectory of at least two frames")
    q = q / pairs
    # The approximate initial condition is the mean encoded first frame of the training trajectories: its
    # error covariance is their spread around that mean (plus one step of model error, which keeps it
    # definite when the trajectories differ in few directions).
    train_params = dataset.params("train")
    n_train = len(train_params)
    z0 = []
    for k in range(0, n_train, chunk):
        first = np.stack([dataset.read("train", i, 0) for i in range(k, min(k + chunk, n_train))])
        z0.append(model.encode(torch.as_tensor(first).to(device), torch.as_tensor(train_params[k:k + chunk],
                                                                                   device=device)).double().cpu())
    z0 = torch.cat(z0)
    spread = z0 - z0.mean(0)
    p0 = _definite(spread.T @ spread / n_train + q)
    return {"Q": q, "P0": p0, "P0_exact": _definite(q), "reconstruction_variance": (squares / frames).float(),
            "trajectories": torch.tensor([int(i) for i in trajectories], dtype=torch.int64)}


# Diagnostics ----------------------------------------------------------------------------------------
@torch.no_grad()
def one_step_error(
    model: LatentModel, dataset: Any, split: str = "train", *, max_pairs: int = 2048, batch_size: int = 128,
    seed: int = 0,
) -> dict[str, float]:
    """Mean squared one-step error of decode(forecast(encode(x_k))) against x_{k+1}, and of persistence.

    Physical units, over the dataset's scored channels and all grid cells, averaged over (trajectory, k)
    pairs of ``split``: all of them, or ``max_pairs`` drawn with ``seed`` if there are more. The
    persistence ("no change") error is that of predicting x_{k+1} = x_k on the same pairs;
    ``reconstruction_mse`` is that of decode(encode(x_k)) against x_k, the floor under the model's
    decoded error (an encoder-decoder cannot predict better than it reconstructs).
    """
    sampler = WindowSampler(dataset, 1, seed=seed, split=split, in_memory=False)
    n_pairs = sampler.n_windows
    if n_pairs <= max_pairs:
        index = torch.arange(n_pairs)
    else:
        index = torch.randperm(n_pairs, generator=torch.Generator().manual_seed(seed))[:max_pairs].sort().values
    traj, start = sampler.trajectories[index // (sampler.n_t - 1)], index % (sampler.n_t - 1)
    scored = [dataset.channels.index(c) for c in dataset.scored_channels]
    device = model.stats_mean.device
    sums = torch.zeros(3, dtype=torch.float64)

    def total(a: torch.Tensor, b: torch.Tensor) -> float:
        return float(((a - b) ** 2).double().mean(dim=tuple(range(1, a.ndim))).sum())

    for lo in range(0, len(index), batch_size):
        x, mu = sampler.windows(traj[lo: lo + batch_size], start[lo: lo + batch_size])
        x, mu = x.to(device), mu.to(device)
        z = model.encode(x[:, 0], mu)
        pred = model.decode(model.forecast(z, mu), mu)
        target = x[:, 1, scored]
        sums[0] += total(pred[:, scored], target)
        sums[1] += total(x[:, 0, scored], target)
        sums[2] += total(model.decode(z, mu)[:, scored], x[:, 0, scored])
    n = len(index)
    return {"model_mse": float(sums[0]) / n, "persistence_mse": float(sums[1]) / n,
            "reconstruction_mse": float(sums[2]) / n, "pairs": n}


__all__ = [
    "LEARNING_RATE",
    "LOSS_TERMS",
    "TRAINING_SCHEDULES",
    "TrainingResult",
    "TrainingSchedule",
    "ValidationMonitor",
    "WindowSampler",
    "calibrate",
    "fit_steps",
    "load_model",
    "one_step_error",
    "train_model",
    "training_loss",
    "training_schedule",
    "validation_trajectories",
]
