"""Spread diagnostics of a filter's predictive uncertainty (DAPPER's): the spread-skill ratio and rank histograms.

* **Spread-skill ratio** (every filter): the spread ``sqrt(mean over the scored cells of the predicted
  variance std^2)`` (the RMSE the predictive std promises) over the skill, the RMSE of the estimate over the
  same cells (Eq. 18's cells, physical units). Per frame, over B trajectories, :func:`spread_skill` divides
  the root of the mean predicted MSE by the root of the mean MSE, ``sqrt(mean_b s_b^2 / mean_b e_b^2)``: 1
  when calibrated, below 1 overconfident (the std too small), above 1 underconfident. The ratio of one
  trajectory at one frame (``spread_skill`` in the wrappers' infos) is biased high: ``E[1 / RMSE] >
  1 / sqrt(E[MSE])``, by 25 % when the error has 4 degrees of freedom (a linear decoder of a 4-dimensional
  latent state), so the squares are averaged over trajectories first.
* **Rank histograms** (EnKF): at each checked cell and frame the rank of the noise-free truth among the n
  decoded members, the number of members below it (:func:`truth_ranks`; a tie with members is broken at
  random, uniformly over the ranks it spans, by a seeded generator), counted into n + 1 bins
  (:func:`rank_histogram`). Flat when the truth is statistically one more member (calibrated); U-shaped when
  the ensemble is too narrow (the truth often outside it); dome-shaped when too wide; sloped when biased.
  The members are the filter's ensemble decoded, without the decoder's reconstruction-error variance (which
  the predictive std adds): a U there may be decoder error the ensemble does not carry.
  The checked cells are the sensors read at each frame (the observed channel) and the fixed cells of
  :func:`rank_cells`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

#: How many fixed cells :func:`rank_cells` checks by default.
RANK_CELLS = 8


def spread_skill(predicted_mse: np.ndarray, mse: np.ndarray, axis: int | None = 0) -> np.ndarray | float:
    """The spread-skill ratio ``sqrt(mean predicted_mse / mean mse)`` with the means along ``axis`` (default
    0: over trajectories of ``(B, n_t)`` arrays, one ratio per frame). ``predicted_mse`` is the mean over
    the scored cells of the predicted variance, ``mse`` Eq. 18 over the same cells, per trajectory and frame.
    NaN where the mean MSE is 0 (no error: no skill to compare with)."""
    spread = np.mean(np.asarray(predicted_mse, dtype=np.float64), axis=axis)
    skill = np.mean(np.asarray(mse, dtype=np.float64), axis=axis)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(skill > 0, np.sqrt(spread / np.where(skill > 0, skill, 1.0)), np.nan)


def truth_ranks(members: np.ndarray, truth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The rank of ``truth`` (..., k) among ``members`` (..., n, k) at each of the k cells: the number of
    members strictly below it, plus, where members equal it, a uniform draw from 0 to their number (ties
    broken at random). Integers in [0, n], shape (..., k). One uniform number is drawn per rank, tie or not,
    so the draws (and the ranks) depend only on the generator's seed and the shapes."""
    members, truth = np.asarray(members), np.asarray(truth)
    if members.shape[:-2] + members.shape[-1:] != truth.shape:
        raise ValueError(f"members (..., n, k) {members.shape} and truth (..., k) {truth.shape} do not match")
    below = (members < truth[..., None, :]).sum(axis=-2)
    ties = (members == truth[..., None, :]).sum(axis=-2)
    return below + np.floor(rng.random(truth.shape) * (ties + 1)).astype(np.int64)


def rank_histogram(ranks: np.ndarray, n_members: int) -> np.ndarray:
    """How many of ``ranks`` (any shape, integers in [0, n_members]) fall in each of the n_members + 1 bins."""
    ranks = np.asarray(ranks).ravel()
    if ranks.size and (ranks.min() < 0 or ranks.max() > n_members):
        raise ValueError(f"ranks must lie in [0, {n_members}] for {n_members} members")
    return np.bincount(ranks, minlength=n_members + 1).astype(np.int64)


def rank_cells(benchmark: Any, fluid_mask: np.ndarray, count: int = RANK_CELLS) -> np.ndarray:
    """The ``count`` fixed cells whose rank histogram the EnKF records, flat indices into a decoded field
    ``(C, *grid)`` (``channel * n_cells + cell``): the fluid cells of the benchmark's scored channels,
    channel by channel in C order, less the cells of its paper sensor layout (``paper_layout()``, 16
    sensors), taken at ``count`` equidistant positions, the centres of ``count`` equal parts of that list.
    Burgers: cells 64, 192, ..., 960 of 1024 (the sensors sit at 32 + 64 j)."""
    if count < 1:
        raise ValueError(f"count must be a positive number of cells, got {count}")
    n_cells = int(np.prod(fluid_mask.shape))
    free = np.flatnonzero(fluid_mask.ravel())
    free = free[~np.isin(free, benchmark.paper_layout())]
    pool = np.concatenate([c * n_cells + free for c in benchmark.scored_indices])
    if len(pool) < count:
        raise ValueError(f"only {len(pool)} fluid cells are free of sensors; ask for at most that many")
    return pool[((np.arange(count) + 0.5) * len(pool) / count).astype(np.int64)]


__all__ = ["RANK_CELLS", "rank_cells", "rank_histogram", "spread_skill", "truth_ranks"]
