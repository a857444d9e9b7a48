"""Aggregates over test episodes with their uncertainty: the mean, the interquartile mean and a 95 % bootstrap
interval, stratified by trajectory when one trajectory is run with several noise seeds.

The resampling is :func:`scipy.stats.bootstrap`'s; this module only arranges the data for it.

* **Stratification.** scipy's bootstrap has no strata argument, but it resamples each of several samples
  independently (``paired=False``), within itself. So each stratum (a test trajectory; its replicates the noise
  seeds it was run with) is passed as one sample, and the statistic is taken over the concatenation of the
  resampled strata: every resample keeps each trajectory's number of episodes, and only the spread of the
  replicates inside a trajectory enters the interval, not the spread between trajectories. A stratum with a
  single value has nothing to resample (scipy refuses a sample of one); it enters every resample as it is.
  Without strata the episodes are one sample, resampled as a whole. Like every bootstrap, the interval is
  narrow by about sqrt((n - 1) / n) for n values per sample, which matters within small strata: with three
  noise seeds per trajectory a nominal 95 % interval covers about 88 % (simulated); read it as a lower bound on the
  uncertainty there.
* **Method.** The percentile interval (``method="percentile"``), as rliable uses for its stratified bootstrap:
  BCa's acceleration needs a jackknife of every sample, which fails for strata of one or two values and for
  constant strata (a NaN interval), and its gain on a few-dozen episodes is small beside the reproducibility
  of a method that cannot fail.
* **Determinism.** ``random_state=np.random.default_rng(seed)``: the same values and seed give the same interval
  with one scipy version; another version may draw differently, so tables print the intervals a results file
  stores and never recompute them.
* **Missing values.** Non-finite values (a diverged episode, stored as ``null``) are dropped before the
  interval is formed, so it describes the finite episodes; the record's mean is ``null`` in that case, which
  says so. Fewer than two finite values (or, with strata, no stratum of two) give ``None``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from scipy import stats

#: The statistics :func:`interval` bounds.
STATISTICS = ("mean", "iqm")
#: Bootstrap resamples by default (the Monte Carlo error of a 95 % percentile bound is then well below the
#: three significant digits the tables print for typical episode counts).
N_RESAMPLES = 9999


def iqm(values: Sequence[float] | np.ndarray) -> float:
    """The interquartile mean: the mean of the middle half of the values (``trim_mean(values, 0.25)``);
    robust to a few diverged or outlying episodes."""
    return float(stats.trim_mean(np.asarray(values, dtype=np.float64), 0.25))


def _statistic(name: str) -> Callable[..., np.ndarray]:
    if name == "mean":
        return lambda x, axis=-1: np.mean(x, axis=axis)
    if name == "iqm":
        return lambda x, axis=-1: stats.trim_mean(x, 0.25, axis=axis)
    raise ValueError(f"statistic must be one of {', '.join(STATISTICS)}, got {name!r}")


def _clean(values: Any, strata: Any) -> tuple[np.ndarray, np.ndarray | None]:
    """The finite values (float) and their strata, non-finite entries (and ``None``) dropped."""
    x = np.array([np.nan if v is None else v for v in np.ravel(np.asarray(values, dtype=object))], dtype=np.float64)
    keep = np.isfinite(x)
    if strata is None:
        return x[keep], None
    s = np.asarray(strata)
    if s.shape != (x.size,):
        raise ValueError(f"strata must give one label per value ({x.size}), got shape {s.shape}")
    return x[keep], s[keep]


def interval(values: Sequence[float | None] | np.ndarray, strata: Sequence[Any] | np.ndarray | None = None, *,
             statistic: str = "mean", confidence: float = 0.95, n_resamples: int = N_RESAMPLES,
             seed: int = 0) -> tuple[float, float] | None:
    """The ``confidence`` percentile bootstrap interval ``(low, high)`` of the mean or the interquartile mean of
    ``values``, resampled within each stratum when ``strata`` (one label per value) are given; ``None`` when
    there is nothing to resample (see the module's notes on stratification and missing values)."""
    stat = _statistic(statistic)
    x, s = _clean(values, strata)
    if s is None:
        samples, fixed = ([x] if x.size >= 2 else []), np.empty(0)
    else:
        groups = [x[s == label] for label in dict.fromkeys(s.tolist())]
        samples = [g for g in groups if g.size >= 2]
        fixed = np.concatenate([g for g in groups if g.size < 2] + [np.empty(0)])
    if not samples:
        return None

    def pooled(*resampled: np.ndarray, axis: int = -1) -> np.ndarray:
        shape = resampled[0].shape[:-1] + (fixed.size,)
        return stat(np.concatenate(list(resampled) + [np.broadcast_to(fixed, shape)], axis=-1), axis=-1)

    res = stats.bootstrap(tuple(samples), pooled, paired=False, vectorized=True, confidence_level=confidence,
                          n_resamples=n_resamples, method="percentile", random_state=np.random.default_rng(seed))
    low, high = float(res.confidence_interval.low), float(res.confidence_interval.high)
    return (low, high) if np.isfinite(low) and np.isfinite(high) else None


def strata_of(trajectories: Sequence[int] | None) -> list[int] | None:
    """The strata a record's episodes resample in: its trajectories when one of them repeats (several noise
    seeds, or repeats, per trajectory), otherwise ``None`` (the episodes are independent draws)."""
    if trajectories is None or len(set(trajectories)) == len(trajectories):
        return None
    return list(trajectories)


#: The aggregates a record's intervals summarize: (field prefix, the per-episode field they are computed from).
INTERVAL_SOURCES = (("final_mse", "per_trajectory_final_mse"), ("final_rel_l2", "per_trajectory_final_rel_l2"),
                    ("time_mean_mse", "per_trajectory_time_mean_mse"))


def interval_fields(record: dict[str, Any]) -> dict[str, Any]:
    """A record's ``{prefix}_iqm`` and ``{prefix}_ci95`` (the 95 % interval of the mean, ``[low, high]``)
    for each per-episode field of :data:`INTERVAL_SOURCES` it holds, from the stored values, stratified by
    trajectory when its trajectories repeat (:func:`strata_of`); ``None`` where undefined."""
    out: dict[str, Any] = {}
    strata = strata_of(record.get("trajectories"))
    for prefix, source in INTERVAL_SOURCES:
        if record.get(source) is None:
            continue
        finite = [v for v in record[source] if v is not None and np.isfinite(v)]
        bounds = interval(record[source], strata)
        out[f"{prefix}_iqm"] = iqm(finite) if finite else None
        out[f"{prefix}_ci95"] = None if bounds is None else list(bounds)
    return out


__all__ = ["INTERVAL_SOURCES", "N_RESAMPLES", "STATISTICS", "interval", "interval_fields", "iqm",
           "strata_of"]
