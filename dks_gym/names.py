"""The names every layer shares, defined once and importable without torch (the CLI's choices use them)."""

from __future__ import annotations

MODEL_KINDS = ("koopman", "pdmd", "mlp", "xlstm")  # the latent models, in the paper's order
FILTERS = ("forward", "ekf", "enkf")  # "forward" is the forward run: the filter loop with the update off
ESTIMATORS = ("shred",)  # reconstructors without a latent model or a filter (their records' filter is "none")

__all__ = ["ESTIMATORS", "FILTERS", "MODEL_KINDS"]
