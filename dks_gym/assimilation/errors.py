"""The errors of a decoded estimate against the true field: Eq. 18's MSE, the relative L2 error and its score.

All three read the same cells and channels: the ``scored`` channels of the benchmark and every cell of the
grid (solid cells included, as Eq. 18 does; no benchmark masks them out of the error), in physical units.

* :func:`field_errors`: Eq. 18, the mean squared error per batch element (the paper's numbers);
* :func:`relative_l2_errors`: ``||x^ - x|| / ||x||``, the norm of the error over the norm of the truth, over
  the scored channels together and over each scored channel alone (SHRED, PDEBench's nRMSE, The Well);
* :func:`ctf_score`: the Common Task Framework's score ``100 (1 - relative L2)``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch


def field_errors(estimate: torch.Tensor, truth: torch.Tensor, scored: tuple[int, ...],
                 std: torch.Tensor | None = None) -> torch.Tensor:
    """Eq. 18: MSE over the scored channels and all cells, per batch element; standardized when ``std`` is given."""
    pick = scored_channels(scored)
    diff = (estimate[:, pick] - truth[:, pick]).flatten(2)
    if std is not None:
        diff = diff.div_(std[pick].to(diff)[None, :, None])  # in place: diff is this call's own
    return diff.pow_(2).mean(dim=(1, 2))


def scored_channels(scored: Sequence[int]) -> slice | list[int]:
    """The index of the ``scored`` channels along a field's channel axis: a slice where they are a run (a
    view, no copy: Burgers scores channel 0 of 1, the cylinder 0-2 of 3), else the list."""
    index = [int(c) for c in scored]
    return slice(index[0], index[-1] + 1) if index and index == list(range(index[0], index[-1] + 1)) else index


def relative_l2_errors(estimate: torch.Tensor, truth: torch.Tensor,
                       scored: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """The relative L2 error of (B, C, *grid) estimates, per batch element: ``(total (B,), per channel
    (B, len(scored)))``, float64.

    ``total[b] = sqrt(sum (x^ - x)^2) / sqrt(sum x^2)``, both sums over the scored channels and every cell
    (the cells and channels of :func:`field_errors`, physical units, so a channel of large values, such as a
    pressure in Pa, weighs most); ``per channel[b, j]`` the same over channel ``scored[j]`` alone. It is
    ``sqrt(MSE / mean x^2)``: 0 for a perfect estimate, 1 for the estimate 0, unbounded above.
    A truth of norm zero (a fluid at rest, as the dambreak's velocity at frame 0) has no relative error:
    NaN there, never a floor that would make one up (records store it as null, tables print ``-``).
    Computed in float64 whatever the estimate's dtype.
    """
    pick = scored_channels(scored)
    x_hat = estimate[:, pick].detach().double().flatten(2)
    x = truth[:, pick].to(x_hat).flatten(2)
    error, norm = (x_hat - x).pow_(2).sum(dim=2), x.pow(2).sum(dim=2)  # (B, n_scored) squared norms per channel

    def ratio(num: torch.Tensor, den: torch.Tensor) -> np.ndarray:
        den = den.cpu().numpy()
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(den > 0, np.sqrt(num.cpu().numpy() / np.where(den > 0, den, 1.0)), np.nan)

    return ratio(error.sum(1), norm.sum(1)), ratio(error, norm)


def ctf_score(relative_l2: np.ndarray | float) -> np.ndarray | float:
    """The Common Task Framework's score ``100 (1 - relative L2)``: 100 for a perfect estimate, 0 for the
    estimate 0, negative for an estimate further from the truth than 0 is (NaN stays NaN)."""
    return 100.0 * (1.0 - relative_l2)


__all__ = ["ctf_score", "field_errors", "relative_l2_errors", "scored_channels"]
