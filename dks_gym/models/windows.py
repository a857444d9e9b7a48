"""Batches of training windows: :class:`WindowSampler` draws (trajectory, start frame) pairs from one split.

Batches are B windows (trajectory, k) drawn uniformly with replacement from the train split with a
seeded ``torch.Generator`` (its state is saved in the checkpoint, so a resumed run draws the batches an
uninterrupted one would); the split is read into memory once when it fits (less than half the available
memory), otherwise every window is read from the HDF5 file (sphere, paper preset, on most machines).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from ..dataset import Dataset


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
        self, dataset: Dataset, horizon: int = 1, *, seed: int = 0, split: str = "train",
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
        """The number of distinct windows the sampler draws from."""
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
        """``batch_size`` random windows and their parameters (see the class docstring)."""
        return self.windows(*self.draw(batch_size))

    def state(self) -> torch.Tensor:
        """The generator's state, saved in the checkpoint for resuming."""
        return self.generator.get_state()

    def set_state(self, state: torch.Tensor) -> None:
        """Continue drawing from a saved generator state."""
        self.generator.set_state(state)


__all__ = ["WindowSampler"]
