"""Measurements as the filters take them: ``(B, m)`` readings checked, and the missing ones masked out."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .batch_elements import element_list


def check_mask(mask: Tensor | None, y: Tensor) -> Tensor | None:
    """Validate a ``(B, m)`` boolean mask of the readings present (True) in ``y``; None when all are present.

    A missing reading's value is ignored (NaN is the convention); the update uses the rows that are present.
    """
    if mask is None:
        return None
    mask = torch.as_tensor(mask, device=y.device)
    if mask.dtype != torch.bool or tuple(mask.shape) != tuple(y.shape):
        raise ValueError(f"mask must be a boolean tensor shaped like y {tuple(y.shape)} (True = the reading is "
                         f"present), got {mask.dtype} {tuple(mask.shape)}")
    return None if bool(mask.all()) else mask


def mask_measurement(y: Tensor, mask: Tensor | None, R: Tensor) -> tuple[Tensor, Tensor]:
    """``y`` with the missing readings set to 0 and ``R`` ``(B, m, m)`` with their rows and columns replaced by
    those of the identity: with the observation Jacobian's (or the predicted readings') missing rows zeroed,
    the update is exactly the one with H and R reduced to the rows present (the gain's missing columns are 0)."""
    if mask is None:
        return y, R
    present = mask.to(R.dtype)
    keep = present[:, :, None] * present[:, None, :]
    return torch.where(mask, y, torch.zeros_like(y)), R * keep + torch.diag_embed(1.0 - present)


def check_measurement(y: Tensor, batch: int, m: int | None, like: Tensor, mask: Tensor | None = None) -> Tensor:
    """Validate a measurement ``(B, m)`` (shape, finite where ``mask`` says present, dimension ``m`` if known);
    return it in ``like``'s dtype."""
    y = torch.as_tensor(y)
    if y.ndim != 2 or y.shape[0] != batch:
        raise ValueError(f"measurement y must be (B, m) with B = {batch}, got shape {tuple(y.shape)}")
    if m is not None and y.shape[1] != m:
        raise ValueError(
            f"measurement dimension changed: expected m = {m} values per batch element "
            "(as before / as observe() returns), "
            f"got {y.shape[1]}; a filter's sensor layout is fixed, call reset() (or build a new filter) to change it"
        )
    mask = check_mask(mask, y)  # before it is used: a mask of the wrong shape or dtype gets its own message
    if mask is None and math.isfinite(float(y.sum())):  # every reading finite: one reduction decides it
        return y.to(dtype=like.dtype, device=like.device)
    present = torch.isfinite(y) if mask is None else torch.isfinite(y) | ~mask
    finite = present.all(1)
    if not finite.all():
        raise ValueError(
            f"measurement y contains NaN or inf in batch elements {element_list(~finite)}; "
            "pass mask=... (True where a reading is present) for missing readings, or repair them"
        )
    return y.to(dtype=like.dtype, device=like.device)
