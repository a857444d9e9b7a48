"""What a filter records at every step (SPEC section 5): the diagnostics, the step's wall time, matrix norms."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import torch
from torch import Tensor


def spectral_norm(M: Tensor) -> Tensor:
    """Largest singular value of each matrix in a ``(B, a, b)`` stack.

    The square root of the largest eigenvalue of the smaller Gram matrix: the same number as an SVD to a few
    units of round-off relative to it (only the small singular values lose accuracy in the Gram), 3-4x faster
    for the stacks the filters record every step (benchmarks/perf.py).
    """
    gram = M.mT @ M if M.shape[-1] <= M.shape[-2] else M @ M.mT
    return torch.linalg.eigvalsh(gram)[..., -1].clamp_min(0.0).sqrt()


@dataclass
class Diagnostics:
    """Per-step filter diagnostics (SPEC section 5): each list entry is one ``step`` call.

    ``forecast_norm`` ``(B,)``: ``||F_k||_2`` (EKF; NaN for the EnKF, which uses no Jacobian);
    ``gain_norm`` ``(B,)``: ``||K_k||_2`` (0 when the step did not assimilate); ``spread`` ``(B,)``:
    ``sqrt(tr P / r)`` after the step (EnKF: sample covariance); ``reset`` ``(B,)`` bool: elements
    restarted by ``on_divergence='reset'``; ``wall_time``: seconds for the step; ``assimilated``.
    """

    forecast_norm: list[Tensor] = field(default_factory=list)
    gain_norm: list[Tensor] = field(default_factory=list)
    spread: list[Tensor] = field(default_factory=list)
    reset: list[Tensor] = field(default_factory=list)
    wall_time: list[float] = field(default_factory=list)
    assimilated: list[bool] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.wall_time)

    def stacked(self, name: str) -> Tensor:
        """One diagnostic over all steps: ``(T, B)`` per element, ``(T,)`` for ``wall_time``/``assimilated``."""
        values = getattr(self, name)
        if name in ("wall_time", "assimilated"):
            return torch.tensor(values)
        if not values:
            raise ValueError(f"no steps recorded yet for {name!r}")
        return torch.stack(values)

    @property
    def max_forecast_norm(self) -> Tensor:
        """``max_k ||F_k||_2`` per batch element (the paper's operator-norm table)."""
        return self.stacked("forecast_norm").amax(0)

    @property
    def mean_wall_time(self) -> float:
        """Average seconds per step."""
        return sum(self.wall_time) / max(len(self.wall_time), 1)

    def as_dict(self) -> dict[str, list]:
        """Plain lists (JSON-ready): per-element diagnostics as ``[T][B]`` nested lists."""
        out: dict[str, list] = {"wall_time": list(self.wall_time), "assimilated": list(self.assimilated)}
        for name in ("forecast_norm", "gain_norm", "spread", "reset"):
            values = getattr(self, name)
            out[name] = torch.stack(values).cpu().tolist() if values else []
        return out


class StepTimer:
    """Wall-clock time of one filter step, synchronizing CUDA so that queued kernels are counted."""

    def __init__(self, device: torch.device) -> None:
        self.device = device

    def __enter__(self) -> StepTimer:
        self._start = time.perf_counter()
        return self

    def __exit__(self, *exc: object) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        self.seconds = time.perf_counter() - self._start
