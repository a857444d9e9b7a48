"""A filter's divergence: the error raised, and the policy that decides between raising and resetting."""

from __future__ import annotations

from typing import Literal

from torch import Tensor

from .batch_elements import element_list

DivergencePolicy = Literal["raise", "reset"]


class FilterDivergence(RuntimeError):
    """Raised when a filter produces a non-finite mean or covariance (or a singular innovation covariance)."""


def raise_if_diverged(bad: Tensor, what: str) -> None:
    """Raise :class:`FilterDivergence` naming the batch elements flagged in ``bad``."""
    if bad.any():
        raise FilterDivergence(
            f"{what} produced a non-finite mean/covariance (or a singular innovation covariance) in batch elements "
            f"{element_list(bad)}; check the model's forecast norm, enlarge Q or R, or use on_divergence='reset'"
        )
