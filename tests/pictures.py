"""What a test can say about a written figure without comparing pixels: how much of it is drawn."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image


def ink(path: Path) -> float:
    """The fraction of the PNG's pixels that are not white (0 for a blank page, a few % for a plot)."""
    rgb = np.asarray(Image.open(path).convert("RGB"), dtype=np.int16)
    return float((rgb.min(axis=-1) < 250).mean())
