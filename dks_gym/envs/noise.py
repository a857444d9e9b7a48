"""Measurement noise of Eq. 4 (SPEC section 2): one seeded Gaussian field per frame, read at the sensors.

The noise is drawn over the whole grid from a generator keyed by (seed, split, trajectory, frame) and
then sampled at the sensor cells. A sensor at a given cell therefore reads the same noise whatever
the rest of the layout is, so layouts (and models and filters) are compared on identical noise.
"""

from __future__ import annotations

import numpy as np

_SPLIT_KEYS = {"train": 0, "test": 1}


def noise_sigma(observed: np.ndarray, fluid_mask: np.ndarray, noise_level: float) -> float:
    """sigma = noise_level * max |observed channel| over all fluid cells and all frames of a trajectory.

    ``observed`` is (n_t, *grid); ``fluid_mask`` is a boolean grid.
    """
    if noise_level < 0 or not np.isfinite(noise_level):
        raise ValueError(f"noise_level must be a finite number >= 0, got {noise_level}")
    return float(noise_level * np.max(np.abs(observed[:, fluid_mask])))


def standard_noise(seed: int, split: str, trajectory: int, frame: int, n_cells: int) -> np.ndarray:
    """Unit Gaussian noise on every grid cell (flat, float64) for one frame of one trajectory."""
    key = [int(seed) & (2**63 - 1), _SPLIT_KEYS[split], int(trajectory), int(frame)]
    return np.random.default_rng(np.random.SeedSequence(key)).standard_normal(n_cells)


def measurement_noise(
    seed: int, split: str, trajectory: int, frame: int, sensors: np.ndarray, sigma: float, n_cells: int
) -> np.ndarray:
    """The noise added to the readings of ``sensors`` (flat grid indices) at one frame."""
    return sigma * standard_noise(seed, split, trajectory, frame, n_cells)[np.asarray(sensors)]
