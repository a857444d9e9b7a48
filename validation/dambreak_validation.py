"""Validate the dambreak generator: water volume conservation and the Martin & Moyce surge front.

1. Volume: for every run of a preset (read from the dataset file's extras, so after
   ``dks-gym data generate dambreak`` this costs nothing; without the file the runs are done, or taken
   from the run cache ``--workdir``), the water volume in the box (integral of
   alpha.water) stays within 0.5 % of the initial column at every frame, and volume inside plus the
   outflow through the open top equals the initial volume to the solver's tolerance.
2. Surge front: with water's real viscosity (nu_w = 1e-6 m^2/s) on the preset's mesh, the front
   position along the floor, Z = z / a against T = t sqrt(2 g / a) with a = 0.1461 m the column width,
   is compared with Martin & Moyce's measurements for a column twice as high as wide (n^2 = 2), the
   points before the obstacle (Z < 2). Criterion: within 10 % after one fitted shift of the experiment's
   time origin (the gate's removal time, which Martin & Moyce's T = 0 does not include; at most T = 0.6),
   reported beside the unshifted errors.

Martin & Moyce (1952), "Part IV. An experimental study of the collapse of liquid columns on a rigid
horizontal plane", Phil. Trans. R. Soc. Lond. A 244(882), 312-324, Fig. 3 (n^2 = 2), as digitized in
PySPH (pypr/pysph, pysph/examples/db_exp_data.py). Only the points with Z < 2 apply here.

Usage::

    python validation/dambreak_validation.py [--preset paper|small] [--data FILE] [--workdir DIR] [--workers N]
        [--plot FILE] [--frames-figure FILE]
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from dks_gym.benchmarks import get_benchmark
from dks_gym.dataset import Dataset
from dks_gym.solvers import dambreak_case as dc
from dks_gym.solvers import openfoam as of

# (T, Z) of Martin & Moyce Fig. 3, n^2 = 2; column width a = 1.125 in and a = 2.25 in.
MARTIN_MOYCE = {
    "a=1.125in": np.array([[0.849, 1.245], [1.212, 1.443], [1.602, 1.884], [2.283, 2.689], [2.950, 3.728]]),
    "a=2.25in": np.array([[0.832, 1.217], [1.219, 1.474], [1.997, 2.292], [2.547, 2.995], [3.345, 4.134]]),
}
OBSTACLE_Z = 2.0  # the obstacle's left face at x = 0.292 m = 2 a
VOLUME_TOLERANCE = 0.005
FRONT_TOLERANCE = 0.10
#: The largest time-origin shift fitted, in T = t sqrt(2g/a) (0.6 is 51 ms for a = 0.1461 m).
MAX_TIME_SHIFT_T = 0.6


def _sweep(preset: str, data_path: Path | None, workdir: Path, workers: int = 1) -> tuple[dict, dict, np.ndarray, Any]:
    """``(params, extras, time, fields(split, index))`` of the preset: read from the dataset file if it exists,
    else from a generation (runs cached in ``workdir``, so a rerun reuses them)."""
    if data_path is not None and Path(data_path).exists():
        ds = Dataset(data_path)
        splits = ("train", "test")
        return {s: ds.params(s) for s in splits}, {s: ds.extras(s) for s in splits}, ds.time, ds.trajectory
    data = dc.generate_dambreak(get_benchmark("dambreak"), preset, workdir=workdir, workers=workers, progress=True)

    def fields(split: str, index: int) -> np.ndarray:  # one use: the trajectories are a stream
        return next(f for s, i, f in data.trajectories if (s, i) == (split, index))

    return data.params, data.extras, np.asarray(data.time), fields


def volume_check(preset: str, workdir: Path, workers: int, data_path: Path | None = None) -> dict:
    """Largest relative change of the water volume and of the volume balance over every run and frame."""
    params, extras, _, _ = _sweep(preset, data_path, workdir, workers)
    worst_change, worst_balance, worst_run = 0.0, 0.0, None
    for split, series in extras.items():
        volume, outflow = series["water_volume"], series["water_outflow"]
        change = np.abs(volume[:, 1:] / volume[:, :1] - 1.0).max(axis=1)
        balance = np.abs((volume[:, 1:] + outflow) / volume[:, :1] - 1.0).max()
        k = int(np.argmax(change))
        if change[k] >= worst_change:
            worst_change, worst_run = float(change[k]), (split, k, float(params[split][k]))
        worst_balance = max(worst_balance, float(balance))
    return {
        "runs": sum(len(p) for p in params.values()),
        "max_volume_change": worst_change,
        "worst_run": worst_run,
        "max_balance_error": worst_balance,
        "passes": bool(worst_change < VOLUME_TOLERANCE),
    }


def surge_front_check(preset: str, workdir: Path, frame_dt: float = 0.0025, n_frames: int = 80) -> dict:
    """Front Z(T) of a real-water run against Martin & Moyce below the obstacle."""
    settings = {**dc.preset_settings(preset), "frame_dt": frame_dt, "n_frames": n_frames}
    workdir = Path(workdir) / "martin_moyce"
    resampler = dc.build_resampler(settings, workdir, get_benchmark("dambreak"))
    paths = of.run_all(
        dc.simulate, [of.Run("train", 0, 1e-6)], name="dambreak-martin-moyce", settings=settings,
        resampler=resampler, workdir=workdir, progress=False,
    )  # fmt: skip
    run = of.load_run(paths[("train", 0)])
    a = dc.WATER_COLUMN[0]
    t = frame_dt * np.arange(0, n_frames + 1)
    z = np.concatenate([[a], run["surge_front"]]) / a
    T = t * math.sqrt(2 * dc.GRAVITY / a)
    rows = []
    for series, points in MARTIN_MOYCE.items():
        for T_exp, Z_exp in points[points[:, 1] < OBSTACLE_Z]:
            Z_sim = float(np.interp(T_exp, T, z))
            rows.append({"series": series, "T": float(T_exp), "Z_exp": float(Z_exp), "Z_sim": Z_sim,
                         "rel_error": (Z_sim - Z_exp) / Z_exp})  # fmt: skip
    worst = max(abs(r["rel_error"]) for r in rows)
    # The criterion: one constant delay of the experiment's time origin, fitted. The simulated gate vanishes
    # at t = 0; the real one was pulled away over a finite time that Martin & Moyce's T = 0 does not include,
    # so the measured column starts to move late by an unknown constant (docs/cfd.md).
    exp = np.array([[r["T"], r["Z_exp"]] for r in rows])
    shifts = np.linspace(0.0, MAX_TIME_SHIFT_T, 601)
    errors = [np.abs(np.interp(exp[:, 0] - d, T, z) / exp[:, 1] - 1.0).max() for d in shifts]
    best = int(np.argmin(errors))
    for r in rows:
        r["Z_sim_shifted"] = float(np.interp(r["T"] - shifts[best], T, z))
        r["rel_error_shifted"] = (r["Z_sim_shifted"] - r["Z_exp"]) / r["Z_exp"]
    return {
        "rows": rows, "max_rel_error_unshifted": worst, "passes_unshifted": bool(worst < FRONT_TOLERANCE),
        "T": T, "Z": z, "time_shift_T": float(shifts[best]),
        "time_shift_s": float(shifts[best] / math.sqrt(2 * dc.GRAVITY / a)),
        "max_rel_error": float(errors[best]), "passes": bool(errors[best] < FRONT_TOLERANCE),
    }  # fmt: skip


def plot(front: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.6))
    ax.plot(front["T"], front["Z"], "-", label="interFoam, nu_w = 1e-6 (this generator)")
    ax.plot(front["T"] + front["time_shift_T"], front["Z"], "--", color="C0", alpha=0.7,
            label=f"the same, delayed by the fitted T = {front['time_shift_T']:.2f}")
    for (series, pts), marker in zip(MARTIN_MOYCE.items(), "os"):
        ax.plot(pts[:, 0], pts[:, 1], marker, mfc="none", label=f"Martin & Moyce 1952, n^2=2, {series}")
    ax.axhline(OBSTACLE_Z, color="k", lw=0.8, ls=":", label="obstacle (Z = 2)")
    ax.set_xlabel("T = t sqrt(2g/a)")
    ax.set_ylabel("Z = z/a")
    ax.set_xlim(0, 3.5)
    ax.set_ylim(1, 4.5)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def frames_figure(preset: str, workdir: Path, path: Path, data_path: Path | None = None) -> None:
    """Rows alpha.water and p of the first test run at t = 0.1, 0.3, 0.6, 1.0 s (from the file or the run cache)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bench = get_benchmark("dambreak")
    params, _, times, trajectory = _sweep(preset, data_path, workdir)
    nu = float(params["test"][0])
    fields = trajectory("test", 0)
    x, y = bench.coords()
    sensors = np.unravel_index(bench.paper_layout(16), bench.grid)
    times = np.asarray(times)
    ks = [int(np.argmin(np.abs(times - t))) for t in (0.1, 0.3, 0.6, 1.0)]
    fig, axes = plt.subplots(2, 4, figsize=(12, 6), sharex=True, sharey=True, layout="constrained")
    for row, name in enumerate(("alpha.water", "p")):
        c = bench.channels.index(name)
        low, high = (0.0, 1.0) if row == 0 else (float(fields[ks, c].min()), float(fields[ks, c].max()))
        for j, k in enumerate(ks):
            ax = axes[row, j]
            im = ax.pcolormesh(x, y, fields[k, c].T, shading="nearest", cmap="Blues" if row == 0 else "viridis",
                               vmin=low, vmax=high)  # fmt: skip
            ax.plot(x[sensors[0]], y[sensors[1]], "r.", ms=4)
            ax.set_aspect("equal")
            ax.set_title(f"{name}, t = {times[k]:.2f} s", fontsize=8)
        fig.colorbar(im, ax=axes[row, :].tolist(), shrink=0.8)
    fig.suptitle(f"dambreak, nu_w = {nu:.3g} m^2/s (64 x 64 grid, paper sensors in red)", fontsize=10)
    fig.savefig(path, dpi=100)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="paper", choices=["paper", "small"])
    parser.add_argument("--data", type=Path, default=None,
                        help="dataset file holding the volumes (default: $DKS_GYM_HOME/data/dambreak-PRESET.h5)")
    parser.add_argument("--workdir", type=Path, default=None,
                        help="run cache used without the file and for the real-water run (default: the file's .work)")
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--plot", type=Path, default=None, help="write the Z(T) figure here")
    parser.add_argument("--skip-volume", action="store_true", help="only the surge-front run")
    parser.add_argument(
        "--frames-figure",
        type=Path,
        default=None,
        help="draw alpha.water and p of the test run with the lowest nu_w at four times, with the paper sensors",
    )
    args = parser.parse_args()
    from dks_gym.home import dataset_path

    if args.data is None:
        args.data = dataset_path("dambreak", args.preset)
    if args.workdir is None:
        args.workdir = args.data.with_name(f"{args.data.stem}.work")

    start = time.perf_counter()
    report: dict = {"preset": args.preset}
    if not args.skip_volume:
        report["volume"] = volume_check(args.preset, args.workdir, args.workers, args.data)
    front = surge_front_check(args.preset, args.workdir)
    report["surge_front"] = {k: v for k, v in front.items() if k not in ("T", "Z")}
    report["wall_s"] = round(time.perf_counter() - start, 1)
    print(json.dumps(report, indent=2))
    if "volume" in report:
        v = report["volume"]
        print(f"\nvolume: max |V/V0 - 1| = {100 * v['max_volume_change']:.3f} % over {v['runs']} runs "
              f"(worst {v['worst_run']}), balance error {v['max_balance_error']:.1e}: "
              f"{'PASS' if v['passes'] else 'FAIL'} (< 0.5 %)")  # fmt: skip
    shift = front["time_shift_T"]
    print(f"\n| series | T | Z Martin & Moyce | Z interFoam | error | Z interFoam at T - {shift:.2f} | error |\n"
          "|---|---|---|---|---|---|---|")
    for r in front["rows"]:
        print(f"| {r['series']} | {r['T']:.3f} | {r['Z_exp']:.3f} | {r['Z_sim']:.3f} | {100 * r['rel_error']:+.1f} % "
              f"| {r['Z_sim_shifted']:.3f} | {100 * r['rel_error_shifted']:+.1f} % |")
    print(
        f"\nsurge front, experiment's time origin delayed by T = {shift:.3f} (t = {1000 * front['time_shift_s']:.1f} "
        f"ms, fitted): max error {100 * front['max_rel_error']:.1f} %: {'PASS' if front['passes'] else 'FAIL'} (< 10 %)"
        f"\nunshifted: max error {100 * front['max_rel_error_unshifted']:.1f} %"
    )
    if args.plot:
        plot(front, args.plot)
        print(f"figure: {args.plot}")
    if args.frames_figure:
        frames_figure(args.preset, args.workdir, args.frames_figure, args.data)
        print(f"figure: {args.frames_figure}")


if __name__ == "__main__":
    main()
