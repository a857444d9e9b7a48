"""The resumable state of a training run: what changes along the run, saved in its checkpoint and restored.

A training checkpoint holds, besides the weights, the Adam state, the sampler's generator state, the loss
history and (with a validation split) the validation history, with the best weights in the model section and
the last ones under the ``last.`` prefix of the training tensors. Restoring all of it makes an interrupted run
continue to exactly the weights an uninterrupted one reaches (bit-identical on CPU). The file format itself is
:mod:`dks_gym.models.checkpoint`'s; this module only says what a training run puts in it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from ..dataset import Dataset
from .checkpoint import check_metadata, read_checkpoint, save_checkpoint
from .latent_model import NeuralLatentModel
from .schedule import TrainingSchedule
from .validation import ValidationMonitor
from .windows import WindowSampler

LAST = "last."  # training-tensor prefix of the last weights, when the model section holds the best ones


@dataclass
class TrainingState:
    """The parts of a training run that change with every step, all of them saved in its checkpoint."""

    net: NeuralLatentModel
    optimizer: torch.optim.Optimizer
    sampler: WindowSampler
    monitor: ValidationMonitor | None  # None without a validation split
    losses: list[torch.Tensor] = field(default_factory=list)  # one (4,) tensor per step (see LOSS_TERMS)

    def save(self, path: Path, metadata: dict[str, Any]) -> None:
        """Write the checkpoint: the best weights (the last ones without validation), the Adam, sampler, loss
        and validation state, and ``metadata``."""
        tensors = {"generator": self.sampler.state(), "losses": torch.stack(self.losses).cpu()}
        weights = None
        if self.monitor is not None:  # the model section holds the best weights; resuming needs the last ones
            tensors["validation"] = self.monitor.stacked()
            tensors.update({LAST + k: v for k, v in self.net.state_dict().items()})
            weights = self.monitor.best_state
        save_checkpoint(path, self.net, metadata, optimizer_state=self.optimizer.state_dict(),
                        training_tensors=tensors, model_state=weights)

    def restore(self, path: Path) -> int:
        """Load weights, Adam state, sampler state, loss and validation history; return the number of steps done."""
        ckpt = read_checkpoint(path)
        last = {k[len(LAST):]: v for k, v in ckpt.training.items() if k.startswith(LAST)}
        self.net.load_state_dict(last or ckpt.model_state)
        if self.monitor is not None:
            self.monitor.restore(ckpt.training.get("validation", torch.zeros(0, 5)), ckpt.model_state)
        state = self.optimizer.state_dict()
        self.optimizer.load_state_dict({"state": ckpt.optimizer_state, "param_groups": state["param_groups"]})
        self.sampler.set_state(ckpt.training["generator"])
        self.losses.extend(ckpt.training["losses"].to(self.net.stats_mean.device, torch.float32).unbind(0))
        return int(ckpt.metadata["steps_done"])


def check_resumable(meta: dict[str, Any], path: Path, benchmark: Any, model: str, preset: str, r: int, T: int,
                    dataset: Dataset, settings: dict[str, Any], schedule: TrainingSchedule | None = None) -> None:
    """Refuse (ValueError) to resume the checkpoint with metadata ``meta`` for another model or dataset, or with
    other ``settings`` (batch size, lr, seed, schedule) than it was trained with. A longer ``schedule`` that
    :meth:`~dks_gym.models.schedule.TrainingSchedule.extends` the stored one may continue it (more steps of a
    constant-rate run, e.g. the paper preset's, in stages)."""
    check_metadata(meta, path, benchmark=benchmark, model=model, r=r, preset=preset, T=T, dataset=dataset)
    for key, value in settings.items():
        if meta.get(key) == value or (key == "schedule" and schedule is not None
                                      and isinstance(meta.get(key), dict) and schedule.extends(meta[key])):
            continue
        hint = (" (a run continues a checkpoint to more steps only with a constant learning rate and no "
                "validation: the lite schedules' warm-up, cosine decay and validations depend on the step count)"
                if key == "schedule" else "")
        raise ValueError(
            f"checkpoint {path} was trained with {key} = {meta.get(key)!r}, not {value!r}, so it cannot be "
            f"resumed with these settings{hint}; use the same settings, or start afresh with --restart "
            f"(resume=False), which overwrites it"
        )


__all__ = ["LAST", "TrainingState", "check_resumable"]
