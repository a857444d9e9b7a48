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
machines). Adam. The ``paper`` schedule is the paper's: lr 1e-4, 1000 steps at batch 256 (burgers,
cylinder, dambreak), 40000 at batch 32 (sphere); the ``lite`` schedule uses lr 1e-3 and fewer steps
(:data:`TRAINING_SCHEDULES`). Training is resumable: the checkpoint (written every
``checkpoint_every`` steps and at the end) holds the weights, the Adam state, the sampler's generator
state and the loss history, so an interrupted run continues to exactly the weights an uninterrupted one
reaches (bit-identical on CPU). pDMD has no optimizer: its "training" is ``fit_dataset``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
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
    model_from_checkpoint,
    read_checkpoint,
    read_metadata,
    save_checkpoint,
    train_command,
)
from .build import build_model
from .latent_model import LatentModel, NeuralLatentModel
from .presets import benchmark_shape

LEARNING_RATE = 1e-4  # Adam, all models and benchmarks (the paper's training tables)
LOSS_TERMS = ("total", "reconstruction", "prediction", "latent")


@dataclass(frozen=True)
class TrainingSchedule:
    """Adam steps, batch size and learning rate of one benchmark in one training preset."""

    steps: int
    batch_size: int
    lr: float


# paper: the paper's training tables. lite: the narrow ``lite`` architectures on two CPU cores in
# minutes. At the paper's lr of 1e-4 the lite Burgers models still have a loss of ~0.1 after 1000 steps
# (batch 32), at 1e-3 they reach ~2e-4 (measured; docs/training.md), so lite uses lr 1e-3 and the steps
# at which the Burgers loss levels off. The CFD lite schedules are sized by time per step (0.2 s at batch
# 16 in 2D, 0.9 s at batch 4 on the sphere, one loaded core).
TRAINING_SCHEDULES: dict[str, dict[str, TrainingSchedule]] = {
    "paper": {
        "burgers": TrainingSchedule(1000, 256, LEARNING_RATE),
        "cylinder": TrainingSchedule(1000, 256, LEARNING_RATE),
        "dambreak": TrainingSchedule(1000, 256, LEARNING_RATE),
        "sphere": TrainingSchedule(40000, 32, LEARNING_RATE),
    },
    "lite": {
        "burgers": TrainingSchedule(1000, 32, 1e-3),
        "cylinder": TrainingSchedule(600, 16, 1e-3),
        "dambreak": TrainingSchedule(600, 16, 1e-3),
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
        in_memory: bool | None = None, progress: bool = False,
    ) -> None:
        self.dataset, self.split = dataset, split
        self.fields = dataset.fields(split)
        self.params = torch.as_tensor(dataset.params(split), dtype=torch.float64)
        self.n_traj, self.n_t = int(self.fields.shape[0]), int(self.fields.shape[1])
        self.horizon = int(horizon)
        if self.horizon < 1 or self.horizon >= self.n_t:
            raise ValueError(
                f"horizon T must be in [1, {self.n_t - 1}] for trajectories of {self.n_t} frames, got {horizon}"
            )
        self.generator = torch.Generator().manual_seed(int(seed))
        nbytes = int(np.prod(self.fields.shape)) * 4
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

        out = np.empty(self.fields.shape, dtype=np.float32)
        for i in tqdm(range(self.n_traj), desc="reading train split", unit="traj", disable=not progress):
            out[i] = self.dataset.read(self.split, i)  # one trajectory (one set of chunks) at a time
        return out

    @property
    def n_windows(self) -> int:
        return self.n_traj * (self.n_t - self.horizon)

    def draw(self, batch_size: int) -> tuple[torch.Tensor, torch.Tensor]:
        """B (trajectory, start frame) index pairs."""
        traj = torch.randint(self.n_traj, (batch_size,), generator=self.generator)
        start = torch.randint(self.n_t - self.horizon, (batch_size,), generator=self.generator)
        return traj, start

    def windows(self, traj: torch.Tensor, start: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The windows starting at the given (trajectory, frame) pairs and their parameters."""
        if self.data is not None:
            x = self.data[traj[:, None], start[:, None] + self._offsets]
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
) -> None:
    """Adam steps ``start`` .. ``steps`` - 1; ``losses`` gets one (4,) tensor per step (see LOSS_TERMS)."""
    from tqdm.auto import tqdm

    device = model.stats_mean.device
    model.train()
    bar = tqdm(total=steps, initial=start, desc=description, unit="step", disable=not progress, dynamic_ncols=True)
    try:
        for step in range(start, steps):
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
            if progress and (done % 10 == 0 or done == steps):
                bar.set_postfix(loss=f"{float(terms[0]):.3e}", refresh=False)
            bar.update(1)
            if checkpoint is not None and (done == steps or (checkpoint_every and done % checkpoint_every == 0)):
                checkpoint(done)
    finally:
        bar.close()
        model.eval()


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
        steps = schedule.steps if steps is None else int(steps)
        batch_size = schedule.batch_size if batch_size is None else int(batch_size)
        lr = schedule.lr if lr is None else float(lr)
        if steps < 1 or batch_size < 1:
            raise ValueError(f"steps and batch_size must be positive, got {steps} and {batch_size}")
        if checkpoint_every is None:
            checkpoint_every = max(1, min(1000, steps // 10))
        if not lr > 0:
            raise ValueError(f"learning rate must be positive, got {lr}")

        settings = {"batch_size": batch_size, "lr": lr, "seed": seed}
        previous = None
        if resume and path.exists():
            previous = read_metadata(path)
            _check_resumable(previous, path, name, model, preset, r, T, dataset, settings)
            if previous["steps_done"] >= steps:  # nothing to train: load without reading the data
                ckpt = read_checkpoint(path, optimizer=False)
                history = ckpt.training["losses"].to(torch.float32).numpy()
                return TrainingResult(model_from_checkpoint(ckpt, device), path, int(previous["steps_done"]), 0,
                                      time.perf_counter() - start_time, history, loaded_only=True)

        net = build_model(name, model, r, preset, dataset=dataset, seed=seed).to(device)
        optimizer = torch.optim.Adam(net.parameters(), lr=lr)
        sampler = WindowSampler(dataset, T, seed=seed, in_memory=in_memory, progress=progress)
        losses: list[torch.Tensor] = []
        start, elapsed_before = 0, 0.0
        if previous is not None:
            start = _restore(path, net, optimizer, sampler, losses)
            elapsed_before = float(previous.get("train_time_s", 0.0))

        loop_start = time.perf_counter()

        def write(done: int) -> None:
            meta = build_metadata(
                net, preset=preset, T=T, dataset=dataset, steps_done=done, steps=steps, batch_size=batch_size,
                lr=lr, seed=seed, complete=done >= steps, device=str(device), loss_terms=list(LOSS_TERMS),
                train_time_s=elapsed_before + time.perf_counter() - loop_start,
            )
            save_checkpoint(
                path, net, meta, optimizer_state=optimizer.state_dict(),
                training_tensors={"generator": sampler.state(), "losses": torch.stack(losses).cpu()},
            )

        fit_steps(
            net, optimizer, sampler, start=start, steps=steps, batch_size=batch_size, losses=losses,
            checkpoint=write, checkpoint_every=checkpoint_every, progress=progress,
            description=f"{name} {model} {preset} r={r} T={T}", on_step=on_step,
        )
        history = torch.stack(losses).cpu().numpy()
        return TrainingResult(net, path, steps, steps - start, time.perf_counter() - start_time, history)


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


def _restore(path: Path, net: NeuralLatentModel, optimizer: torch.optim.Optimizer, sampler: WindowSampler,
             losses: list[torch.Tensor]) -> int:
    """Load weights, Adam state, sampler state and loss history; return the number of steps done."""
    ckpt = read_checkpoint(path)
    net.load_state_dict(ckpt.model_state)
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
    fit_time = time.perf_counter() - start_time
    meta = build_metadata(model, preset="", T=1, dataset=dataset, steps_done=0, steps=0, batch_size=None,
                          lr=None, seed=seed, complete=True, device=str(device), train_time_s=fit_time)
    save_checkpoint(path, model, meta)
    return TrainingResult(model.eval(), path, 0, 0, time.perf_counter() - start_time, np.zeros((0, 4), np.float32))


# The single entry point -------------------------------------------------------------------------------
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
    """The trained ``model`` of ``benchmark`` from its checkpoint, in eval mode on ``device``.

    The checkpoint is looked up by (benchmark, model, preset, r, T) under ``data_home()/models`` for the
    dataset preset of ``dataset`` (or ``data_preset``). If it is missing or unfinished, ``train_if_missing``
    trains (or resumes) it with the preset's schedule and a progress bar; otherwise CheckpointMissing (a
    FileNotFoundError) names the ``dks-gym train`` command. A checkpoint for another benchmark, r,
    preset or T, or trained on another dataset than ``dataset``, raises ValueError.
    """
    name = benchmark_shape(benchmark).name
    check_model_args(model, preset, r, T)
    if dataset is not None and dataset.benchmark.name != name:
        raise ValueError(f"dataset {dataset.path} is for {dataset.benchmark.name}, not {name}")
    data_preset = (dataset.preset or "custom") if dataset is not None else data_preset
    path = Path(path) if path is not None else checkpoint_path(name, model, preset, r, T, data_preset=data_preset)
    command = train_command(name, model, preset, r, T, data_preset)
    if path.exists():
        meta = read_metadata(path)
        check_metadata(meta, path, benchmark=name, model=model, r=r, preset=preset, T=T, dataset=dataset)
        if meta.get("complete"):
            return model_from_checkpoint(path, _device(device))
        reason = f"training in {path} stopped at step {meta.get('steps_done')} of {meta.get('steps')}"
    else:
        reason = f"no trained {name} {model} model (preset {preset}, r={r}, T={T}) at {path}"
    if not train_if_missing:
        raise CheckpointMissing(
            f"{reason}. Train it with `{command}` (it resumes an unfinished run), or call "
            "load_model(..., train_if_missing=True)."
        )
    if progress:  # plain words: this is the expected first use, not an error
        what = "resuming its unfinished training" if path.exists() else "training it on first use"
        print(f"dks-gym: {name} {model} model ({preset}, r={r}, T={T}): {what}, as `{command}` would; it is "
              f"kept at {path} for later runs", flush=True)
    result = train_model(name, model, r, preset, T, dataset=dataset, data_preset=data_preset, device=device,
                         path=path, progress=progress)
    return result.model


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
    traj, start = index // (sampler.n_t - 1), index % (sampler.n_t - 1)
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
    "WindowSampler",
    "fit_steps",
    "load_model",
    "one_step_error",
    "train_model",
    "training_loss",
    "training_schedule",
]
