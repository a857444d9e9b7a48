"""The paired comparison with the random layouts: each policy's time-averaged MSE against the random layouts'
on the very same episodes (same trajectory, same noise), from a results document alone."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from dks_gym.evaluation.intervals import interval, strata_of


def paired_vs_random(doc: dict[str, Any], *, intervals: bool = False) -> dict[str, dict[str, Any]]:
    """Per policy: its time-averaged MSE against the mean of the random layouts on the same episode.

    For every episode e (trajectory x noise seed), ``q_e = log(MSE_policy(e) / mean_s MSE_random-s(e))``,
    the mean over the run's seeded random layouts of the same episode (same trajectory, same noise); for a
    ``random-s`` record the mean is over the *other* seeds. Returns ``{policy: {log_ratio_mean,
    log_ratio_se, log_ratio_se_trajectories, ratio_mean, wins, n_episodes, n_random}}``: ``log_ratio_se`` =
    std(q)/sqrt(episodes); ``log_ratio_se_trajectories`` the same over the per-trajectory means of q (the
    noise seeds of one trajectory are not independent episodes, so this is the conservative one);
    ``ratio_mean`` = mean of exp(q); ``wins`` = episodes where the policy's MSE is below the random mean.
    ``log_ratio_geometric_mean``/``_se``: the same against the per-episode *geometric* mean of the random
    layouts, i.e. the average paired log ratio against each random layout (the arithmetic mean is pulled up
    by the worst random layouts, so a typical random layout itself scores below 0 against it).
    Negative log ratios beat random. With ``intervals``, also ``log_ratio_ci95``: the 95 % bootstrap interval
    ``[low, high]`` of ``log_ratio_mean``, resampled within trajectories when they repeat (noise seeds;
    :func:`~dks_gym.evaluation.intervals.interval`), null with one episode; an interval below 0 beats random,
    one that includes 0 does not decide. Tables print the stored interval (:func:`add_paired_vs_random`).
    Empty without at least two random layouts. Works on any document
    from :func:`placement_document` (e.g. a committed ``placement.json.gz``), old ones included.
    """
    recs = [r for r in doc["records"] if r["experiment"].startswith("placement/")]
    randoms = {r["policy"]: np.asarray(r["per_trajectory_time_mean_mse"], dtype=float)
               for r in recs if r["policy"].startswith("random-")}
    if len(randoms) < 2:
        return {}
    stack = np.stack(list(randoms.values()))
    total = stack.sum(axis=0)
    out: dict[str, dict[str, Any]] = {}
    for rec in recs:
        a = np.asarray(rec["per_trajectory_time_mean_mse"], dtype=float)
        if a.shape != total.shape:
            continue
        own = randoms.get(rec["policy"])
        ref = (total - own) / (len(randoms) - 1) if own is not None else total / len(randoms)
        q = np.log(a / ref)
        others = stack if own is None else np.stack([v for k, v in randoms.items() if k != rec["policy"]])
        g = np.log(a) - np.log(others).mean(axis=0)  # against the geometric mean = mean paired log ratio per seed
        n = len(q)
        traj = np.asarray(rec.get("trajectories", np.arange(n)))
        per_traj = np.array([q[traj == t].mean() for t in np.unique(traj)])
        out[rec["policy"]] = {
            "log_ratio_mean": float(q.mean()),
            "log_ratio_se": float(q.std(ddof=1) / math.sqrt(n)) if n > 1 else None,
            "log_ratio_se_trajectories": (float(per_traj.std(ddof=1) / math.sqrt(len(per_traj)))
                                          if len(per_traj) > 1 else None),
            "log_ratio_geometric_mean": float(g.mean()),
            "log_ratio_geometric_se": float(g.std(ddof=1) / math.sqrt(n)) if n > 1 else None,
            "ratio_mean": float(np.exp(q).mean()), "wins": int(np.sum(a < ref)), "n_episodes": n,
            "n_trajectories": int(len(per_traj)), "n_random": len(randoms) - (own is not None),
        }
        if intervals:
            bounds = interval(q, strata_of([int(t) for t in traj]))
            out[rec["policy"]]["log_ratio_ci95"] = None if bounds is None else list(bounds)
    return out


def add_paired_vs_random(doc: dict[str, Any]) -> dict[str, Any]:
    """Store :func:`paired_vs_random` (with its intervals) in each record as ``paired_vs_random`` (in place);
    returns ``doc``."""
    paired = paired_vs_random(doc, intervals=True)
    for rec in doc["records"]:
        if rec.get("policy") in paired:
            rec["paired_vs_random"] = paired[rec["policy"]]
    return doc


def add_paired_intervals(doc: dict[str, Any]) -> dict[str, Any]:
    """Give each stored ``paired_vs_random`` block the ``log_ratio_ci95`` it lacks, leaving the rest as it is
    (a migration of committed documents: an interval it holds is kept); in place, returns ``doc``."""
    blocks = [rec["paired_vs_random"] for rec in doc["records"]
              if isinstance(rec.get("paired_vs_random"), dict) and "log_ratio_ci95" not in rec["paired_vs_random"]]
    if blocks:
        paired = paired_vs_random(doc, intervals=True)
        for rec in doc["records"]:
            if rec.get("policy") in paired and isinstance(rec.get("paired_vs_random"), dict):
                rec["paired_vs_random"].setdefault("log_ratio_ci95", paired[rec["policy"]]["log_ratio_ci95"])
    return doc


__all__ = ["add_paired_intervals", "add_paired_vs_random", "paired_vs_random"]
