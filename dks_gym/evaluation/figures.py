"""Figures of the paper's Section IV from results records (and, for reconstructions, from run arrays).

* :func:`normalized_bar_chart`: final-time MSE per model divided by the MLP forward-run error of the same
  scenario (so the MLP rollout is 1.0), error bars the sample std across test trajectories divided by the
  same number (Figs. 3, 5, 10, 11, 12, 13); log scale, the value printed on each bar;
* :func:`temporal_error_figure`: MSE against time, one thin line per test trajectory and the mean as a
  thick line, one column per model and one row per estimate (Figs. 7, 9);
* :func:`timing_figure`: wall time per DA step per model and filter (Figs. 4, 6);
* :func:`reconstruction_figure`: truth, estimate and error at the final time for one test trajectory,
  one model per row (Fig. 8 and the 2D/3D reconstructions; 3D shows the middle z slice);
* :func:`spread_figure`: the spread-skill ratio over time per filter and the EnKF's rank histograms of the
  truth, one row per model;
* :func:`uncertainty_figure`: the predictive std of an estimate at chosen time steps: in 1D the estimate,
  the truth and the +-2 std band, in 2D (3D: the middle z slice) the std map beside the absolute-error map.

Every function writes a PNG and returns its path; matplotlib runs headless (Agg).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..atomic import atomic_path
from ..names import MODEL_KINDS

MODEL_ORDER = MODEL_KINDS
MODEL_LABELS = {"koopman": "Koopman", "pdmd": "pDMD", "mlp": "MLP", "xlstm": "xLSTM"}
MODEL_COLORS = {"koopman": "#1f77b4", "pdmd": "#2ca02c", "mlp": "#ff7f0e", "xlstm": "#9467bd"}
FILTER_LABELS = {"forward": "forward run", "ekf": "EKF", "enkf": "EnKF"}


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, path: str | Path, *, dpi: int = 130, tight: bool = True) -> Path:
    """Write ``fig`` as a PNG with a 256-colour palette (a quarter of the size of matplotlib's RGBA, the
    same picture: a plot has few colours) atomically, and close it."""
    import io

    from PIL import Image

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi, **({"bbox_inches": "tight"} if tight else {}))
    _pyplot().close(fig)
    image = Image.open(buffer).convert("RGB").quantize(colors=256, method=Image.Quantize.FASTOCTREE,
                                                       dither=Image.Dither.NONE)
    with atomic_path(path) as tmp:
        image.save(tmp, format="PNG", optimize=True)
    return path


def _ordered(records: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    rank = {m: i for i, m in enumerate(MODEL_ORDER)}
    return sorted(records, key=lambda r: rank.get(r["model"], len(rank)))


def normalized_values(records: Sequence[dict[str, Any]], baseline: dict[str, Any]) -> list[tuple[str, float, float]]:
    """(model, mean / baseline mean, std / baseline mean) for each record, in the paper's model order."""
    base = baseline["final_mse_mean"]
    if base is None or base <= 0:
        raise ValueError(f"the baseline record has no usable final MSE ({base!r}); cannot normalize")
    out = []
    for rec in _ordered(records):
        mean = rec["final_mse_mean"]
        std = rec["final_mse_std"]
        out.append((rec["model"], np.nan if mean is None else mean / base, 0.0 if std is None else std / base))
    return out


def normalized_bar_chart(
    panels: Sequence[tuple[str, Sequence[dict[str, Any]], dict[str, Any]]],
    path: str | Path,
    *,
    title: str | None = None,
    ncols: int | None = None,
) -> Path:
    """One panel per (title, records, baseline record): bars of final MSE / baseline MSE per model.

    Panels fill ``ncols`` columns (default: all in one row).
    """
    if not panels:
        raise ValueError("normalized_bar_chart needs at least one panel")
    plt = _pyplot()
    ncols = len(panels) if ncols is None else max(1, min(ncols, len(panels)))
    nrows = -(-len(panels) // ncols)
    fig, axes = plt.subplots(nrows, ncols, figsize=(3.6 * ncols + 0.6, 3.4 * nrows), squeeze=False, sharey=True)
    flat = axes.ravel()
    for ax in flat[len(panels):]:
        ax.set_axis_off()
    for ax, (panel_title, records, baseline) in zip(flat, panels):
        values = normalized_values(records, baseline)
        x = np.arange(len(values))
        means = np.array([v[1] for v in values])
        stds = np.array([v[2] for v in values])
        # On a log axis a lower bar reaching zero or below cannot be drawn: those bars show the upper half only.
        lower = np.where(means - stds > 0, stds, 0.0)
        ax.bar(x, means, color=[MODEL_COLORS.get(v[0], "grey") for v in values], width=0.65,
               yerr=np.vstack([lower, stds]), capsize=3, error_kw={"elinewidth": 0.8})
        for xi, m, s in zip(x, means, stds):
            if np.isfinite(m):
                ax.annotate(f"{m:.3g}", (xi, m + s), textcoords="offset points", xytext=(0, 2), ha="center",
                            va="bottom", fontsize=7)
        ax.axhline(1.0, color="k", lw=0.6, ls="--")
        ax.set_yscale("log")
        ax.set_xticks(x, [MODEL_LABELS.get(v[0], v[0]) for v in values])
        ax.set_title(panel_title, fontsize=10)
        ax.grid(axis="y", which="major", alpha=0.3)
    for row in axes:
        row[0].set_ylabel("final MSE / MLP forward MSE")
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    return save_figure(fig, path)


def temporal_error_figure(
    rows: Sequence[tuple[str, Sequence[dict[str, Any]]]],
    path: str | Path,
    *,
    time: np.ndarray | None = None,
    title: str | None = None,
) -> Path:
    """Rows of (label, records): per model a panel with one thin line per trajectory and the mean (thick)."""
    plt = _pyplot()
    models = [m for m in MODEL_ORDER if any(r["model"] == m for _, recs in rows for r in recs)]
    fig, axes = plt.subplots(len(rows), len(models), figsize=(3.0 * len(models), 2.4 * len(rows)),
                             squeeze=False, sharex=True, sharey=True)
    for i, (label, records) in enumerate(rows):
        by_model = {r["model"]: r for r in records}
        for j, model in enumerate(models):
            ax = axes[i][j]
            rec = by_model.get(model)
            if rec is None:
                ax.set_axis_off()
                continue
            mean = np.array(rec["per_step_mse_mean"], dtype=float)
            t = np.arange(len(mean)) if time is None else np.asarray(time)[: len(mean)]
            color = MODEL_COLORS.get(model, "grey")
            for curve in rec.get("per_trajectory_step_mse") or []:
                ax.plot(t, np.array(curve, dtype=float), color=color, lw=0.6, alpha=0.35)
            ax.plot(t, mean, color=color, lw=2.0, label="mean")
            ax.set_yscale("log")
            ax.grid(alpha=0.3)
            if i == 0:
                ax.set_title(MODEL_LABELS.get(model, model), fontsize=10)
            if j == 0:
                ax.set_ylabel(f"{label}\nMSE")
            if i == len(rows) - 1:
                ax.set_xlabel("time" if time is not None else "frame")
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    return save_figure(fig, path)


def timing_figure(records: Sequence[dict[str, Any]], path: str | Path, *, title: str | None = None) -> Path:
    """Grouped bars of the mean wall time per DA step (milliseconds), per model and filter."""
    plt = _pyplot()
    filters = [f for f in ("forward", "ekf", "enkf") if any(r["filter"] == f for r in records)]
    models = [m for m in MODEL_ORDER if any(r["model"] == m for r in records)]
    fig, ax = plt.subplots(figsize=(1.6 * len(models) + 2.0, 3.2))
    width = 0.8 / max(len(filters), 1)
    hatches = {"forward": "", "ekf": "//", "enkf": ".."}
    for k, filt in enumerate(filters):
        for j, model in enumerate(models):
            recs = [r for r in records if r["model"] == model and r["filter"] == filt]
            if not recs or recs[0]["da_step_seconds"] is None:
                continue
            ms = 1e3 * recs[0]["da_step_seconds"]
            label = FILTER_LABELS[filt] if j == 0 else None
            ax.bar(j + (k - (len(filters) - 1) / 2) * width, ms, width * 0.95, color=MODEL_COLORS.get(model, "grey"),
                   hatch=hatches[filt], edgecolor="k", linewidth=0.5, label=label)
    ax.set_xticks(np.arange(len(models)), [MODEL_LABELS.get(m, m) for m in models])
    ax.set_yscale("log")
    ax.set_ylabel("wall time per DA step [ms]")
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)


def parameter_figure(curves: dict[tuple[str, str], Sequence[float]], path: str | Path, *,
                     title: str | None = None) -> Path:
    """The median relative error of an estimated parameter over the frames, one panel per filter and one line
    per model (``curves`` by (model, filter))."""
    plt = _pyplot()
    filters = [f for f in ("forward", "ekf", "enkf") if any(key[1] == f for key in curves)] or ["ekf"]
    fig, axes = plt.subplots(1, len(filters), figsize=(4.2 * len(filters), 3.0), sharey=True, squeeze=False)
    for ax, filt in zip(axes[0], filters):
        for model in MODEL_ORDER:
            if (model, filt) in curves:
                curve = np.asarray(curves[model, filt], dtype=float)
                ax.plot(np.arange(len(curve)), curve, color=MODEL_COLORS[model], label=MODEL_LABELS[model])
        ax.set_yscale("log")
        ax.set_title(f"{FILTER_LABELS[filt]}: median relative error of mu", fontsize=9)
        ax.set_xlabel("frame")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    return save_figure(fig, path)


def spread_figure(
    rows: Sequence[tuple[str, dict[str, dict[str, Any] | None]]],
    path: str | Path,
    *,
    time: np.ndarray | None = None,
    title: str | None = None,
) -> Path:
    """Spread diagnostics, one panel row per model: rows of (model, {filter: record or None}).

    Left, the spread-skill ratio ``per_step_spread_skill`` of each filter over frames 1..n_t-1 (log scale, 1
    dashed: calibrated); middle and right, the EnKF's rank histograms of the truth at the sensors and at the
    fixed cells (``rank_histogram_sensors``, ``rank_histogram_cells``) as frequency times n + 1 (1 dashed:
    flat, calibrated). A panel without its field is left blank.
    """
    plt = _pyplot()
    fig, axes = plt.subplots(len(rows), 3, figsize=(11.0, 2.3 * len(rows)), squeeze=False)
    styles = {"ekf": ("-", "EKF"), "enkf": ("--", "EnKF"), "forward": (":", "forward run")}
    for i, (model, by_filter) in enumerate(rows):
        color = MODEL_COLORS.get(model, "grey")
        ax = axes[i][0]
        ratios = {filt: np.array(rec["per_step_spread_skill"], dtype=float)[1:] for filt, rec in by_filter.items()
                  if rec is not None and rec.get("per_step_spread_skill")}
        for filt, ratio in ratios.items():
            t = np.arange(1, len(ratio) + 1) if time is None else np.asarray(time)[1:len(ratio) + 1]
            ax.plot(t, ratio, styles[filt][0], color=color, lw=1.5, label=styles[filt][1])
        if ratios:
            ax.axhline(1.0, color="k", lw=0.8, ls=":")
            ax.set_yscale("log")
            low, high = ax.get_ylim()  # plain numbers at the ticks inside the data's range (over 1 vs under 1)
            ax.set_yticks([v for v in (0.1, 0.25, 0.5, 0.7, 1.0, 1.4, 2.0, 4.0, 10.0) if low <= v <= high])
            ax.yaxis.set_major_formatter("{x:g}")
            ax.yaxis.set_minor_formatter("")
            ax.set_ylabel(f"{MODEL_LABELS.get(model, model)}\nspread / skill")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
            ax.set_xlabel("time" if time is not None else "frame")
        else:
            ax.set_axis_off()
        for j, (name, where) in enumerate((("rank_histogram_sensors", "sensors"), ("rank_histogram_cells",
                                                                                   "fixed cells")), start=1):
            ax, counts = axes[i][j], (by_filter.get("enkf") or {}).get(name)
            if not counts or not sum(counts):
                ax.set_axis_off()
                continue
            freq = np.array(counts, dtype=float) / sum(counts) * len(counts)
            ax.bar(np.arange(len(counts)), freq, width=1.0, color=color, edgecolor="k", linewidth=0.3)
            ax.axhline(1.0, color="k", lw=0.8, ls="--")
            ax.set_title(f"EnKF rank of the truth, {where}", fontsize=9)
            ax.set_xlabel(f"rank among {len(counts) - 1} members")
            ax.set_ylabel("frequency x (n + 1)")
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    return save_figure(fig, path)


def _field_slice(field: np.ndarray) -> np.ndarray:
    """A 1D or 2D view of one channel: the field itself, or the middle z slice of a 3D field."""
    return field if field.ndim <= 2 else field[..., field.shape[-1] // 2]


def reconstruction_figure(
    estimates: dict[str, np.ndarray],
    truth: np.ndarray,
    coords: Sequence[np.ndarray],
    path: str | Path,
    *,
    channel: int = 0,
    channel_name: str = "",
    fluid_mask: np.ndarray | None = None,
    title: str | None = None,
) -> Path:
    """Truth, estimate and error of one channel at one time for each model (``estimates``: model -> (C, *grid))."""
    plt = _pyplot()
    models = [m for m in MODEL_ORDER if m in estimates] + [m for m in estimates if m not in MODEL_ORDER]
    if not models:
        raise ValueError("reconstruction_figure needs at least one estimate")
    true = _field_slice(np.asarray(truth)[channel])
    if np.asarray(truth).ndim == 4 and title:
        title += " (middle z slice)"
    if true.ndim == 1:
        x = np.asarray(coords[0])
        fig, axes = plt.subplots(2, len(models), figsize=(3.2 * len(models), 4.2), squeeze=False, sharex=True,
                                 gridspec_kw={"height_ratios": [2, 1]})
        for j, model in enumerate(models):
            est = _field_slice(np.asarray(estimates[model])[channel])
            ax, ax_err = axes[0][j], axes[1][j]
            ax.plot(x, true, color="k", lw=1.6, label="truth")
            ax.plot(x, est, color=MODEL_COLORS.get(model, "grey"), lw=1.2, ls="--", label="estimate")
            ax.set_title(MODEL_LABELS.get(model, model), fontsize=10)
            ax.grid(alpha=0.3)
            ax_err.plot(x, est - true, color=MODEL_COLORS.get(model, "grey"), lw=1.0)
            ax_err.axhline(0, color="k", lw=0.5)
            ax_err.grid(alpha=0.3)
            ax_err.set_xlabel("x")
            if j == 0:
                ax.set_ylabel(channel_name or "value")
                ax_err.set_ylabel("error")
                ax.legend(fontsize=7)
        err_lim = max(np.max(np.abs(_field_slice(np.asarray(estimates[m])[channel]) - true)) for m in models)
        for ax_err in axes[1]:
            ax_err.set_ylim(-1.05 * err_lim - 1e-12, 1.05 * err_lim + 1e-12)
    else:
        mask = None if fluid_mask is None else _field_slice(np.asarray(fluid_mask))
        aspect = float(np.ptp(coords[1]) / max(np.ptp(coords[0]), 1e-12))
        fig, axes = plt.subplots(len(models), 3, figsize=(11.0, len(models) * (3.3 * aspect + 0.7)), squeeze=False)
        vmin, vmax = float(np.min(true)), float(np.max(true))
        errs = {m: _field_slice(np.asarray(estimates[m])[channel]) - true for m in models}
        emax = max(float(np.max(np.abs(e))) for e in errs.values()) or 1.0
        extent = [coords[0][0], coords[0][-1], coords[1][0], coords[1][-1]]
        for i, model in enumerate(models):
            est = _field_slice(np.asarray(estimates[model])[channel])
            panels = [("truth", true, "viridis", vmin, vmax), ("estimate", est, "viridis", vmin, vmax),
                      ("error", errs[model], "RdBu_r", -emax, emax)]
            for j, (name, data, cmap, lo, hi) in enumerate(panels):
                shown = np.where(mask, data, np.nan) if mask is not None else data
                im = axes[i][j].imshow(shown.T, origin="lower", extent=extent, cmap=cmap, vmin=lo, vmax=hi,
                                       aspect="equal")
                axes[i][j].set_title(f"{MODEL_LABELS.get(model, model)}: {name}", fontsize=9)
                fig.colorbar(im, ax=axes[i][j], fraction=0.046 * aspect, pad=0.02)
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    return save_figure(fig, path)


def uncertainty_figure(
    estimates: np.ndarray,
    stds: np.ndarray,
    truths: np.ndarray,
    coords: Sequence[np.ndarray],
    path: str | Path,
    *,
    steps: Sequence[int] | None = None,
    channel: int = 0,
    channel_name: str = "",
    fluid_mask: np.ndarray | None = None,
    title: str | None = None,
) -> Path:
    """The estimate's predictive std at K chosen time steps of one trajectory.

    ``estimates``, ``stds``, ``truths``: (K, C, *grid), e.g. ``info["estimate"]``, ``info["estimate_std"]``
    and ``env.unwrapped.true_state`` collected at those steps; ``steps`` (K,) labels them (the frame index).
    1D: one panel per step with the truth, the estimate and the band estimate +- 2 std (about 95 %). 2D and
    3D (middle z slice): one row per step, the std map beside the absolute-error map on one colour scale, so
    that an honest std looks like the error it claims to bound.
    """
    plt = _pyplot()
    est, std, true = (np.asarray(a, dtype=np.float64) for a in (estimates, stds, truths))
    if not (est.shape == std.shape == true.shape) or est.ndim < 3 or len(est) == 0:
        raise ValueError(f"estimates, stds and truths must share one (K, C, *grid) shape with K >= 1, got "
                         f"{est.shape}, {std.shape}, {true.shape}")
    if np.any(std < 0) or not np.all(np.isfinite(std)):
        raise ValueError("stds must be finite and non-negative")
    n = len(est)
    steps = list(range(n)) if steps is None else list(steps)
    if len(steps) != n:
        raise ValueError(f"got {len(steps)} step labels for {n} time steps")
    name = channel_name or "value"
    if est.ndim == 3:  # 1D fields
        x = np.asarray(coords[0])
        fig, axes = plt.subplots(1, n, figsize=(3.4 * n + 0.4, 3.0), squeeze=False, sharey=True)
        for ax, k, e, s, t in zip(axes[0], steps, est[:, channel], std[:, channel], true[:, channel]):
            ax.fill_between(x, e - 2 * s, e + 2 * s, color=MODEL_COLORS["koopman"], alpha=0.25, lw=0,
                            label="estimate +- 2 std")
            ax.plot(x, t, color="k", lw=1.4, label="truth")
            ax.plot(x, e, color=MODEL_COLORS["koopman"], lw=1.1, ls="--", label="estimate")
            inside = float(np.mean(np.abs(t - e) <= 2 * s))
            ax.set_title(f"frame {k}: {100 * inside:.0f}% inside", fontsize=9)
            ax.set_xlabel("x")
            ax.grid(alpha=0.3)
        axes[0][0].set_ylabel(name)
        axes[0][0].legend(fontsize=7)
    else:
        mask = None if fluid_mask is None else _field_slice(np.asarray(fluid_mask))
        aspect = float(np.ptp(coords[1]) / max(np.ptp(coords[0]), 1e-12))
        extent = [coords[0][0], coords[0][-1], coords[1][0], coords[1][-1]]
        fig, axes = plt.subplots(n, 2, figsize=(7.6, n * (3.3 * aspect + 0.7)), squeeze=False)
        for i, k in enumerate(steps):
            s = _field_slice(std[i, channel])
            err = np.abs(_field_slice(est[i, channel]) - _field_slice(true[i, channel]))
            hi = max(float(np.max(s)), float(np.max(err))) or 1.0
            for j, (label, data) in enumerate(((f"{name} std", s), (f"|{name} error|", err))):
                shown = np.where(mask, data, np.nan) if mask is not None else data
                im = axes[i][j].imshow(shown.T, origin="lower", extent=extent, cmap="magma", vmin=0.0, vmax=hi,
                                       aspect="equal")
                axes[i][j].set_title(f"frame {k}: {label}", fontsize=9)
                fig.colorbar(im, ax=axes[i][j], fraction=0.046 * aspect, pad=0.02)
        if est.ndim == 5 and title:
            title += " (middle z slice)"
    if title:
        fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    return save_figure(fig, path)


__all__ = [
    "save_figure",
    "FILTER_LABELS",
    "MODEL_COLORS",
    "MODEL_LABELS",
    "MODEL_ORDER",
    "normalized_bar_chart",
    "normalized_values",
    "parameter_figure",
    "reconstruction_figure",
    "spread_figure",
    "temporal_error_figure",
    "timing_figure",
    "uncertainty_figure",
]
