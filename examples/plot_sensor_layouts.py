"""Draw the paper's sensor layouts of the four benchmarks (paper Fig. 2): Burgers, and the cell types of the CFD ones.

    python examples/plot_sensor_layouts.py            # writes docs/figures/sensor_layouts.png
    python examples/plot_sensor_layouts.py --m 8 --out layouts8.png

Top: Burgers, the initial condition u0 = sin x + 0.5 cos 2x on the periodic grid with its sensors.
Below, one column per CFD benchmark: the cylinder, the dambreak, and the sphere's z = +dz/2 slice (the
sphere's sensors are projected along z; each marker there stands for a +-z pair). The middle row shows
the whole domain, the bottom row the region around the body or obstacle (the box drawn on top) enlarged.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import ListedColormap  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402

from dks_gym.benchmarks import get_benchmark  # noqa: E402

# One colour per cell-type name, shared by all panels.
COLOURS = {
    "interior": "#f4f4f4",
    "wall": "#5a5a5a",
    "body": "#1a1a1a",
    "obstacle": "#1a1a1a",
    "inlet": "#4c8fd6",
    "outlet": "#e39b3b",
    "atmosphere": "#9fd3e8",
}
MARKERS = {  # sensor group -> (marker, colour)
    "surface": ("o", "#d62728"),
    "wake": ("^", "#9c27b0"),
    "bottom": ("o", "#d62728"),
    "obstacle": ("^", "#9c27b0"),
}
ZOOM = {"cylinder": (-2.0, 6.0, -2.0, 2.0), "dambreak": (0.24, 0.37, 0.0, 0.065), "sphere": (-2.0, 6.0, -2.0, 2.0)}
TITLES = {
    "cylinder": "cylinder, {m} sensors",
    "dambreak": "dambreak, {m} sensors",
    "sphere": "sphere, slice z = +dz/2, {m} sensors (projected along z: one marker per +-z pair)",
}


def draw_cell_types(ax, bench, plane: np.ndarray) -> None:
    """The cell-type codes of a 2D plane as a categorical image in physical coordinates."""
    names = sorted(bench.cell_type_codes, key=bench.cell_type_codes.get)
    cmap = ListedColormap([COLOURS[n] for n in names])
    x, y = bench.coords()[:2]
    dx, dy = x[1] - x[0], y[1] - y[0]
    extent = (x[0] - dx / 2, x[-1] + dx / 2, y[0] - dy / 2, y[-1] + dy / 2)
    ax.imshow(plane.T, origin="lower", extent=extent, cmap=cmap, vmin=-0.5, vmax=len(names) - 0.5,
              interpolation="nearest")
    ax.set_aspect("equal")


def draw_sensors(ax, bench, groups: dict[str, np.ndarray], size: float) -> None:
    x, y = bench.coords()[:2]
    for name, flat in groups.items():
        if len(flat) == 0:
            continue
        idx = np.unravel_index(flat, bench.grid)
        marker, colour = MARKERS[name]
        ax.scatter(x[idx[0]], y[idx[1]], s=size, marker=marker, facecolor=colour, edgecolor="k", linewidth=0.6,
                   zorder=3, label=f"{name} ({len(flat)})")


def annotate_depth(ax, bench, flat: np.ndarray) -> None:
    """Write |z| next to each projected 3D sensor in the upper half (the lower half mirrors it)."""
    x, y, z = bench.coords()
    i, j, k = np.unravel_index(flat, bench.grid)
    for (ii, jj), depth in sorted({(a, b): abs(z[c]) for a, b, c in zip(i, j, k) if y[b] > 0}.items()):
        ax.annotate(f"|z|={depth:.2f}", (x[ii], y[jj]), xytext=(5, 4), textcoords="offset points", fontsize=7,
                    bbox=dict(boxstyle="round,pad=0.15", facecolor="white", edgecolor="none", alpha=0.85))


def column(top, bottom, name: str, m: int) -> None:
    """The whole domain on ``top``, the region around the body or obstacle enlarged on ``bottom``."""
    bench = get_benchmark(name)
    ct = bench.cell_type()
    plane = ct[:, :, bench.grid[2] // 2] if bench.ndim == 3 else ct
    groups = bench.layout_groups(m)
    unit = "m" if name == "dambreak" else "R"
    for ax, size in ((top, 16), (bottom, 36)):
        draw_cell_types(ax, bench, plane)
        draw_sensors(ax, bench, groups, size=size)
        ax.set_xlabel(f"x [{unit}]")
        ax.set_ylabel(f"y [{unit}]")
        ax.tick_params(labelsize=8)
    if bench.ndim == 3:
        annotate_depth(bottom, bench, np.concatenate(list(groups.values())))
    x0, x1, y0, y1 = ZOOM[name]
    bottom.set_xlim(x0, x1)
    bottom.set_ylim(y0, y1)
    top.indicate_inset((x0, y0, x1 - x0, y1 - y0), edgecolor="0.2", linewidth=1.0)
    top.set_title(TITLES[name].format(m=m), fontsize=10)
    bottom.set_title("enlarged", fontsize=9)
    handles = [Patch(facecolor=COLOURS[n], edgecolor="0.5", label=f"{v} {n}")
               for n, v in sorted(bench.cell_type_codes.items(), key=lambda kv: kv[1])]
    handles += top.get_legend_handles_labels()[0]
    bottom.legend(handles=handles, fontsize=7, loc="center left", bbox_to_anchor=(1.02, 0.5), framealpha=0.9)


def burgers_panel(ax, m: int) -> None:
    """Burgers: u0 on the 1024-point periodic grid, the sensors marked on it."""
    from dks_gym.benchmarks.burgers import initial_condition

    bench = get_benchmark("burgers")
    (x,) = bench.coords()
    u0 = initial_condition(x)
    sensors = bench.paper_layout(m)
    ax.plot(x, u0, color="0.3", lw=1.2, label="u0 = sin x + 0.5 cos 2x")
    ax.scatter(x[sensors], u0[sensors], s=36, marker="o", facecolor="#d62728", edgecolor="k", linewidth=0.6,
               zorder=3, label=f"sensors ({m}, equidistant)")
    ax.set(xlim=(0, 2 * np.pi), xlabel="x", ylabel="u")
    ax.set_title(f"burgers, {m} sensors (indices {sensors[0]} + {sensors[1] - sensors[0]} k)", fontsize=10)
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))
    ax.tick_params(labelsize=8)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--m", type=int, default=16, help="number of sensors (default 16, the paper's)")
    default_out = Path(__file__).resolve().parents[1] / "docs" / "figures" / "sensor_layouts.png"
    parser.add_argument("--out", type=Path, default=default_out, help="output image")
    args = parser.parse_args()

    fig, axes = plt.subplot_mosaic([["burgers"] * 3, ["t0", "t1", "t2"], ["b0", "b1", "b2"]], figsize=(18, 8.6),
                                   gridspec_kw={"width_ratios": [3, 1.6, 3], "height_ratios": [0.7, 1, 1]},
                                   layout="constrained")
    burgers_panel(axes["burgers"], args.m)
    for j, name in enumerate(("cylinder", "dambreak", "sphere")):
        column(axes[f"t{j}"], axes[f"b{j}"], name, args.m)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=150)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
