"""The loss-curve figure written beside every trained checkpoint: train and validation, each term of Eq. 10."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..atomic import atomic_path

TERMS = ("total", "reconstruction", "prediction", "latent")


def write_loss_curves(train: np.ndarray, validation: np.ndarray | None, path: Path | str, title: str) -> Path:
    """Plot the per-step training losses ``train`` (n, 4) (a running mean over 1 % of the steps, so the curve
    reads through the batch noise) and the validation losses ``validation`` (m, 5: step and the four terms),
    one panel per term of :data:`TERMS`, log scale; write the PNG atomically to ``path``."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    train = np.asarray(train, dtype=np.float64)
    steps = np.arange(1, len(train) + 1)
    width = max(1, len(train) // 100)
    kernel = np.ones(width) / width
    fig = Figure(figsize=(10, 2.8), dpi=100)
    axes = fig.subplots(1, len(TERMS))
    for j, (ax, term) in enumerate(zip(axes, TERMS)):
        if len(train):
            smooth = np.convolve(train[:, j], kernel, mode="valid")
            ax.semilogy(steps[width - 1:], smooth, lw=1, label="train (running mean)")
        if validation is not None and len(validation):
            ax.semilogy(validation[:, 0], validation[:, j + 1], "o-", ms=2, lw=1, label="validation")
            best = int(np.argmin(validation[:, 1]))
            ax.axvline(validation[best, 0], color="0.6", ls=":", lw=1)
        ax.set_title(term, fontsize=9)
        ax.set_xlabel("step", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(f"{title}: loss (normalized units); dotted line: best validation", fontsize=9)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, format="png")
    return path
