"""The batch elements a check flags: which ones hold non-finite values, and how a message names them."""

from __future__ import annotations

import math

import torch
from torch import Tensor


def element_list(mask: Tensor, limit: int = 20) -> str:
    """The flagged indices of a boolean ``mask`` as ``"[0, 3, ...]"``, at most ``limit`` of them."""
    idx = torch.nonzero(mask.reshape(-1)).reshape(-1).tolist()
    text = ", ".join(str(i) for i in idx[:limit])
    return f"[{text}{', ...' if len(idx) > limit else ''}]"


def nonfinite_elements(*tensors: Tensor) -> Tensor:
    """Boolean ``(B,)``: batch elements where any of the given tensors (leading dim ``B``) holds NaN or inf.

    A NaN or inf makes the sum of everything non-finite, so a finite total clears every element with one
    reduction per tensor (``isfinite`` over every entry costs 20x more at ``(256, 32, 32)``); only when the
    total is not finite (a divergence, or finite entries whose sum overflows) is each element decided entry by
    entry.
    """
    total = sum(t.sum() for t in tensors)
    if math.isfinite(float(total)):
        return torch.zeros(tensors[0].shape[0], dtype=torch.bool, device=tensors[0].device)
    bad = torch.zeros(tensors[0].shape[0], dtype=torch.bool, device=tensors[0].device)
    for t in tensors:
        bad |= ~torch.isfinite(t).flatten(1).all(1)
    return bad
