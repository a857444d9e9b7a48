"""The batch elements a check flags: which ones hold non-finite values, and how a message names them."""

from __future__ import annotations

import torch
from torch import Tensor


def element_list(mask: Tensor, limit: int = 20) -> str:
    """The flagged indices of a boolean ``mask`` as ``"[0, 3, ...]"``, at most ``limit`` of them."""
    idx = torch.nonzero(mask.reshape(-1)).reshape(-1).tolist()
    text = ", ".join(str(i) for i in idx[:limit])
    return f"[{text}{', ...' if len(idx) > limit else ''}]"


def nonfinite_elements(*tensors: Tensor) -> Tensor:
    """Boolean ``(B,)``: batch elements where any of the given tensors (leading dim ``B``) holds NaN or inf."""
    bad = torch.zeros(tensors[0].shape[0], dtype=torch.bool, device=tensors[0].device)
    for t in tensors:
        bad |= ~torch.isfinite(t).flatten(1).all(1)
    return bad
