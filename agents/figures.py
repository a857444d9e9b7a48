"""The placement figures: each policy's layout over the observed field (``placement_layouts.png``) and the
error-vs-budget curves with paired confidence bands (``budgets.png``)."""

from __future__ import annotations

import math
from pathlib import Path
from collections.abc import Sequence
from typing import Any

import numpy as np

from dks_gym.evaluation.figures import save_figure

from .policies import PlacementTask
from .records import PolicyResult
from .tables import budget_rows


def layout_figure(task: PlacementTask, results: Sequence[PolicyResult], path: str | Path,
                  trajectory: int | None = None) -> Path:
    """Each policy's layout over the observed field of one test trajectory (default: median parameter) at the
    final frame. 1D: the field on top and one strip of sensor positions per policy; 2D/3D: one panel per
    policy (3D: the mid-plane z slice, off-plane sensors as +). Adaptive policies show the cells read at
    the final step."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    from dks_gym.envs.render import draw_field

    ds, bench = task.dataset, task.benchmark
    split = task.config.split
    index = results[0].result.trajectories
    params = ds.params(split)[index]
    if trajectory is None:
        pos = int(np.argsort(params)[len(params) // 2])
    else:
        pos = int(np.flatnonzero(index == trajectory)[0])
    traj = int(index[pos])
    frame = ds.n_frames - 1
    field_ = ds.frame(split, traj, frame)[bench.observed_index]
    title = f"{bench.name}: {bench.observed_channel} at t={ds.time[frame]:.3g}, {ds.param_name}={params[pos]:.4g}"

    def cells_of(pr: PolicyResult) -> np.ndarray:
        return pr.layouts[pos, -1] if pr.policy.adaptive else pr.layouts[pos]

    if bench.ndim == 1:
        x = ds.coords[0]
        fig = Figure(figsize=(8, 2.2 + 0.28 * len(results)), dpi=120)
        top, strip = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [2.2, 0.28 * len(results) + 0.3]})
        top.plot(x, field_, lw=1.2, color="0.2")
        top.set_ylabel(bench.observed_channel)
        top.set_title(title, fontsize=9)
        for i, pr in enumerate(results):
            cells = cells_of(pr)
            strip.plot(x[cells], np.full(len(cells), i), "|" if not pr.policy.adaptive else "x", ms=9, mew=1.6,
                       color=f"C{i % 10}")
        strip.set_yticks(range(len(results)), [pr.name + (" (step)" if pr.policy.adaptive else "") for pr in results],
                         fontsize=7)
        strip.set_ylim(len(results) - 0.5, -0.5)
        strip.set_xlabel("x")
        strip.grid(axis="x", alpha=0.3)
    else:
        ncols = min(4, len(results))
        nrows = math.ceil(len(results) / ncols)
        fig = Figure(figsize=(4.2 * ncols, 3.2 * nrows), dpi=100)
        axes = np.atleast_1d(fig.subplots(nrows, ncols, squeeze=False)).ravel()
        vmax = float(np.abs(field_).max())
        for ax, pr in zip(axes, results):
            draw_field(ax, bench, ds.coords, field_, cells_of(pr), bench.fluid_mask(ds.cell_type),
                       pr.name + (" (last step)" if pr.policy.adaptive else ""), vmin=-vmax, vmax=vmax)
        for ax in axes[len(results):]:
            ax.set_visible(False)
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path, dpi=fig.dpi, tight=False)


def budget_figure(docs: dict[int, dict[str, Any]], path: str | Path) -> Path:
    """Error vs budget per policy: the paired log ratio to random with a band of ± 2 standard errors."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 4))
    ax_mse, ax_ratio = fig.subplots(1, 2)
    colors = matplotlib.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, (name, per_m) in enumerate(budget_rows(docs).items()):
        color = colors[i % len(colors)]  # one colour per policy in both panels
        ms = sorted(per_m)
        ax_mse.plot(ms, [per_m[m]["time_mean_mse_mean"] for m in ms], "o-", label=name, color=color)
        paired = [(m, per_m[m].get("paired_vs_random")) for m in ms]
        paired = [(m, p) for m, p in paired if p and p.get("log_ratio_se_trajectories") is not None]
        if paired and name != "random":
            x = np.array([m for m, _ in paired])
            mean = np.array([p["log_ratio_mean"] for _, p in paired])
            se = np.array([p["log_ratio_se_trajectories"] for _, p in paired])
            ax_ratio.plot(x, mean, "o-", label=name, color=color)
            ax_ratio.fill_between(x, mean - 2 * se, mean + 2 * se, alpha=0.15, color=color)
    for ax in (ax_mse, ax_ratio):
        ax.set_xscale("log", base=2)
        ax.set_xlabel("sensors m")
    ax_mse.set_yscale("log")
    ax_mse.set_ylabel("time-averaged MSE")
    ax_ratio.axhline(0.0, color="k", lw=0.8)
    ax_ratio.set_ylabel("log(MSE / random), paired, ± 2 se")
    ax_mse.legend(fontsize=7)
    fig.tight_layout()
    return save_figure(fig, path, dpi=110, tight=False)


__all__ = ["budget_figure", "layout_figure"]
