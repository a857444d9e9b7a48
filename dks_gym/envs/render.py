"""Draw a field with its sensors as an RGB array: a line in 1D, an image in 2D, the mid-plane slice in 3D."""

from __future__ import annotations

import numpy as np

from ..benchmarks import Benchmark


def _figure(ncols: int = 1):
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    # A bare Figure (no pyplot) keeps rendering thread-safe and leaves no global state behind.
    fig = Figure(figsize=(4.2 * ncols, 3.4), dpi=80)
    return fig, fig.subplots(1, ncols, squeeze=False)[0]


def _to_rgb(fig) -> np.ndarray:
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def draw_field(ax, bench: Benchmark, coords, field: np.ndarray, sensors=None, fluid_mask=None, title: str = "",
               cmap: str = "RdBu_r", vmin=None, vmax=None) -> None:
    """Draw one scalar field (grid-shaped) on ``ax`` with the sensors marked."""
    sensors = np.asarray([] if sensors is None else sensors, dtype=np.int64)
    if bench.ndim == 1:
        ax.plot(coords[0], field, lw=1.2)
        ax.plot(coords[0][sensors], field[sensors], "kx", ms=6)
        ax.set_xlabel("x")
        if vmin is not None:
            ax.set_ylim(vmin, vmax)
    else:
        if bench.ndim == 3:
            kz = bench.grid[2] // 2
            plane = field[:, :, kz]
            mask = None if fluid_mask is None else fluid_mask[:, :, kz]
            ijk = np.unravel_index(sensors, bench.grid)
            in_plane = ijk[2] == kz
            pts = (ijk[0], ijk[1])
        else:
            plane, mask = field, fluid_mask
            pts = np.unravel_index(sensors, bench.grid)
            in_plane = np.ones(len(sensors), dtype=bool)
        img = np.ma.masked_where(~mask, plane) if mask is not None else plane
        x, y = coords[0], coords[1]
        half_x, half_y = (x[1] - x[0]) / 2, (y[1] - y[0]) / 2
        extent = (x[0] - half_x, x[-1] + half_x, y[0] - half_y, y[-1] + half_y)
        from matplotlib import colormaps

        im = ax.imshow(img.T, origin="lower", extent=extent, cmap=colormaps[cmap].with_extremes(bad="0.6"),
                       aspect="auto", vmin=vmin, vmax=vmax)
        ax.figure.colorbar(im, ax=ax, shrink=0.8)
        px, py = x[pts[0]], y[pts[1]]
        ax.plot(px[in_plane], py[in_plane], "kx", ms=6, mew=1.5)
        ax.plot(px[~in_plane], py[~in_plane], "k+", ms=5, alpha=0.6)
        ax.set_xlabel("x")
        ax.set_ylabel("y")
    ax.set_title(title, fontsize=8)


def render_field(bench: Benchmark, coords, field: np.ndarray, sensors, fluid_mask=None, title: str = "") -> np.ndarray:
    """One field with its sensors as an (H, W, 3) uint8 image (3D: mid-plane z slice, off-plane sensors as +)."""
    fig, axes = _figure()
    draw_field(axes[0], bench, coords, field, sensors, fluid_mask, title)
    fig.tight_layout()
    return _to_rgb(fig)


def render_panels(bench: Benchmark, coords, panels: list[tuple[str, np.ndarray]], sensors,
                  fluid_mask=None) -> np.ndarray:
    """Several fields side by side (e.g. truth, estimate, error) as one (H, W, 3) uint8 image."""
    fig, axes = _figure(len(panels))
    for ax, (title, field) in zip(axes, panels):
        draw_field(ax, bench, coords, field, sensors, fluid_mask, title)
    fig.tight_layout()
    return _to_rgb(fig)
