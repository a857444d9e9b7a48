"""The training schedule: every setting of a training run's optimization, in one :class:`TrainingSchedule`.

:data:`TRAINING_SCHEDULES` holds the ``paper`` and ``lite`` presets per benchmark; :func:`training_schedule`
returns one, optionally with an explicit step count, batch size or learning rate in place of the preset's
(what ``dks-gym train --steps/--batch-size/--lr`` and the tests pass to :func:`dks_gym.models.train_model`).
A checkpoint stores the schedule it was trained with (:meth:`TrainingSchedule.record`), which is how a cached
checkpoint trained with another schedule is recognised and retrained.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from .presets import benchmark_shape

LEARNING_RATE = 1e-4  # Adam, all models and benchmarks (the paper's training tables)


@dataclass(frozen=True)
class TrainingSchedule:
    """Adam steps, batch size and learning rate of one benchmark in one training preset, and how the run is
    watched: a learning-rate schedule, a validation split and early stopping (all off by default, which is
    the paper's plain constant-rate training).

    The field names are part of the checkpoint metadata (``schedule``, ``preset_schedule``): renaming one makes
    every existing checkpoint look trained with another schedule; a new one needs its default in
    :data:`_LATER_FIELDS`.
    """

    steps: int
    """Adam steps of the run; with ``epochs``, the most steps."""
    batch_size: int
    """Training windows per Adam step."""
    lr: float
    """Adam learning rate: constant, or the peak of the warm-up and cosine decay."""
    epochs: float | None = None
    """Passes over the training windows (capped at ``steps``); None: exactly ``steps``."""
    warmup: float = 0.0
    """Fraction of the steps with a linear warm-up to ``lr``."""
    final_lr: float | None = None
    """Learning rate at the last step, reached along a cosine from ``lr``; None keeps ``lr`` constant."""
    validation_fraction: float = 0.0
    """Training trajectories held out for validation (by trajectory, seeded); 0: no validation split."""
    validations: int = 0
    """Validation losses per run, evenly spaced (0: no validation)."""
    patience: int = 0
    """Validations without a 1 % improvement before stopping early (0: never stop early)."""
    clip_norm: float | None = None
    """Largest global L2 norm of a step's gradients: a larger one is scaled down to it before Adam's update
    (``torch.nn.utils.clip_grad_norm_``); None: no clipping."""

    def resolve(self, n_windows: int) -> "TrainingSchedule":
        """This schedule with its step count fixed for ``n_windows`` training windows (``epochs`` applied)."""
        if self.epochs is None:
            return self
        steps = min(self.steps, max(1, math.ceil(self.epochs * n_windows / self.batch_size)))
        return dataclasses.replace(self, steps=steps, epochs=None)

    def check(self) -> None:
        """Raise ValueError unless the step count, batch size, learning rate and clipping norm are positive."""
        if self.steps < 1 or self.batch_size < 1:
            raise ValueError(f"steps and batch_size must be positive, got {self.steps} and {self.batch_size}")
        if not self.lr > 0:
            raise ValueError(f"learning rate must be positive, got {self.lr}")
        if self.clip_norm is not None and not self.clip_norm > 0:
            raise ValueError(f"clip_norm must be positive or None (no clipping), got {self.clip_norm}")

    def extends(self, record: dict[str, Any]) -> bool:
        """Whether a run with this schedule may continue a checkpoint trained with the schedule ``record``
        (:meth:`record`) to more steps, bit for bit as if it had run them at once: the two differ in ``steps``
        alone, this one has at least as many, and nothing else depends on the step count (a constant learning
        rate, no warm-up, no validation cadence, no epochs)."""
        mine = self.record()
        if set(record) != set(mine) or any(record[k] != mine[k] for k in mine if k != "steps"):
            return False
        constant = self.final_lr is None and self.warmup == 0 and not self.validations and self.epochs is None
        return constant and self.steps >= int(record["steps"])

    @property
    def warmup_steps(self) -> int:
        """The number of warm-up steps."""
        return round(self.warmup * self.steps)

    @property
    def eval_every(self) -> int:
        """Steps between validations (0: no validation)."""
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
        """The schedule as checkpoint metadata. A field added after checkpoints were written is left out at its
        default (:data:`_LATER_FIELDS`), so those checkpoints' schedules still read as current and resume."""
        record = dataclasses.asdict(self)
        for name, default in _LATER_FIELDS.items():
            if record[name] == default:
                del record[name]
        return record


#: Fields added after the first checkpoints, with their defaults (the value that behaves as before they existed).
_LATER_FIELDS: dict[str, Any] = {"clip_norm": None}


# paper: the paper's training tables, unchanged (its tables reproduce with it). lite: the narrow ``lite``
# architectures, trained until they converge on one CPU core in minutes (docs/training.md has the curves): 5 %
# warm-up, cosine decay to 1e-5, best-on-validation weights and early stopping after 12 (8) validations
# without a 1 % gain. Burgers: lr 2e-3 with the gradients' global norm clipped at 0.1, 60 epochs of the training
# windows capped at 4000 steps; it reaches the best validation loss of the former 8000 steps at lr 1e-3
# (unclipped), and forward runs as good. Faster ones did not: 3000 steps at lr 5e-3 matched the validation
# loss but left the Koopman model's 99-step forward runs 2-4x worse (docs/training.md, "Shorter schedules"). The
# cylinder and the dambreak: lr 1e-3 for 3000 steps at batch 16. On the cylinder, lr 5e-3 for 1500 steps reaches
# the same best validation loss but its Koopman forward runs are 1.7-2.2x worse with every seed, and 2000 steps
# at lr 2e-3 clipped 1.0-2.9x (1e-2 collapses to the mean field). The sphere's lite schedule is sized by time
# (0.9 s per step at batch 4) and has no validation split.
TRAINING_SCHEDULES: dict[str, dict[str, TrainingSchedule]] = {
    "paper": {
        "burgers": TrainingSchedule(1000, 256, LEARNING_RATE),
        "cylinder": TrainingSchedule(1000, 256, LEARNING_RATE),
        "dambreak": TrainingSchedule(1000, 256, LEARNING_RATE),
        "sphere": TrainingSchedule(40000, 32, LEARNING_RATE),
    },
    "lite": {
        "burgers": TrainingSchedule(4000, 32, 2e-3, epochs=60, warmup=0.05, final_lr=1e-5, validation_fraction=0.1,
                                    validations=50, patience=12, clip_norm=0.1),
        "cylinder": TrainingSchedule(3000, 16, 1e-3, epochs=60, warmup=0.05, final_lr=1e-5, validation_fraction=0.1,
                                     validations=30, patience=8),
        "dambreak": TrainingSchedule(3000, 16, 1e-3, epochs=60, warmup=0.05, final_lr=1e-5, validation_fraction=0.1,
                                     validations=30, patience=8),
        "sphere": TrainingSchedule(300, 4, 1e-3),
    },
}


#: A benchmark without a schedule of its own (a custom one) trains with the schedule of the paper benchmark
#: with as many axes: the lite ones are sized by epochs of the training windows, so they fit any data size.
SCHEDULE_OF_NDIM = {1: "burgers", 2: "cylinder", 3: "sphere"}


def training_schedule(benchmark: Any, preset: str, *, steps: int | None = None, batch_size: int | None = None,
                      lr: float | None = None) -> TrainingSchedule:
    """The schedule of ``benchmark`` for the ``preset`` ("paper" or "lite"), with ``steps``, ``batch_size`` or
    ``lr`` in place of the preset's where given. An explicit step count trains exactly that many steps: it
    replaces the preset's epochs and early stopping (its learning-rate schedule and validation stay). A custom
    benchmark takes the schedule of :data:`SCHEDULE_OF_NDIM`."""
    if preset not in TRAINING_SCHEDULES:
        raise ValueError(f"unknown preset {preset!r}; choose one of {', '.join(TRAINING_SCHEDULES)}")
    shape = benchmark_shape(benchmark)
    table = TRAINING_SCHEDULES[preset]
    schedule = table.get(shape.name) or table[SCHEDULE_OF_NDIM[shape.ndim]]
    if steps is not None:
        schedule = dataclasses.replace(schedule, steps=int(steps), epochs=None, patience=0)
    if batch_size is not None or lr is not None:
        schedule = dataclasses.replace(schedule, batch_size=schedule.batch_size if batch_size is None else
                                       int(batch_size), lr=schedule.lr if lr is None else float(lr))
    return schedule


__all__ = ["LEARNING_RATE", "SCHEDULE_OF_NDIM", "TRAINING_SCHEDULES", "TrainingSchedule", "training_schedule"]
