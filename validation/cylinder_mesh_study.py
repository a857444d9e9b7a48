"""Mesh study of the cylinder generator: Strouhal number and mean drag on a mesh and on one twice as fine.

For each Reynolds number (default 200 and 990) the case runs on the preset's mesh (refine 1.15 for
`paper`) and on the mesh with every cell count doubled and the wall cell halved (twice the preset's
refine: four times the cells, half the time step). ``--refine`` takes absolute factors on the base
mesh (n_quarter 24, wall cell 0.02 for `paper`), so ``--refine 1 2`` reruns the earlier pair. St comes from the
mean period between upward zero crossings of the lift over the recording window
(:func:`dks_gym.solvers.cylinder_case.strouhal`), the drag is averaged over the same window.
Criterion: both change by less than 3 % from the coarsest to every finer mesh given.

For reference the table lists Roshko's relation for an unconfined cylinder, St = 0.212 - 4.5 / Re
(Roshko 1954, NACA Report 1191, fitted for 50 < Re < 150 and often used up to Re ~ 300): the channel
walls at y = +-4R block D / H = 25 % of it, which accelerates the flow past the body and raises St.

``--spin-up-check`` also runs the given Reynolds numbers on the preset mesh and prints the lift
amplitude over the last spin-up windows and the recording window, to show whether the fixed spin-up
is long enough for the shedding to have saturated.

Usage::

    python validation/cylinder_mesh_study.py [--re 200 990] [--refine 1.15 2.3] [--workers 2] [--workdir DIR]
        [--spin-up 150] [--frames 100] [--spin-up-check 59.5 80 120]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from dks_gym.benchmarks import get_benchmark
from dks_gym.solvers import cylinder_case as cc
from dks_gym.solvers import openfoam as of

TOLERANCE = 0.03


def roshko(reynolds: float) -> float:
    """Roshko's unconfined-cylinder Strouhal number St = 0.212 - 4.5 / Re."""
    return 0.212 - 4.5 / reynolds


def run_cases(cases: list[tuple[float, float]], base: dict, workdir: Path, workers: int) -> dict:
    """Run every (Re, refine) case (cached under workdir/refine-R) and return the cache contents."""
    out = {}
    by_refine: dict[float, list[float]] = {}
    for re, refine in cases:
        by_refine.setdefault(refine, []).append(re)
    bench = get_benchmark("cylinder")
    for refine, res in sorted(by_refine.items()):
        settings = {**base, "refine": float(refine)}
        wd = workdir / f"refine-{refine:g}"
        resampler = cc.build_resampler(settings, wd, bench)
        runs = [of.Run("train", i, float(re)) for i, re in enumerate(res)]
        paths = of.run_all(
            cc.simulate, runs, name=f"cylinder-refine{refine:g}", settings=settings, resampler=resampler,
            workdir=wd, workers=workers, progress=True,
        )  # fmt: skip
        for r in runs:
            out[(r.param, refine)] = {**of.load_run(paths[(r.split, r.index)]), "cells": resampler.n_cells}
    return out


def frames_figure(fields: np.ndarray, reynolds: float, settings: dict, path: Path) -> None:
    """Rows u, v, p; columns four frames spread over the recording; black dots: the paper's 16 sensors."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bench = get_benchmark("cylinder")
    x, y = bench.coords()
    sensors = np.unravel_index(bench.paper_layout(16), bench.grid)
    ks = np.linspace(0, fields.shape[0] - 1, 4).round().astype(int)
    fig, axes = plt.subplots(3, 4, figsize=(13, 4.6), sharex=True, sharey=True, layout="constrained")
    for c, name in enumerate(bench.channels):
        lim = np.abs(fields[:, c]).max()
        for j, k in enumerate(ks):
            ax = axes[c, j]
            im = ax.pcolormesh(x, y, fields[k, c].T, shading="nearest", cmap="RdBu_r", vmin=-lim, vmax=lim)
            ax.plot(x[sensors[0]], y[sensors[1]], "k.", ms=3)
            ax.set_aspect("equal")
            ax.set_title(f"{name}, t - t0 = {settings['frame_dt'] * k:g} R/U", fontsize=8)
        fig.colorbar(im, ax=axes[c, :].tolist(), shrink=0.8)
    fig.suptitle(f"cylinder, Re = {reynolds:g} (64 x 64 grid, paper sensors)", fontsize=10)
    fig.savefig(path, dpi=100)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--re", type=float, nargs="+", default=[200.0, 990.0])
    parser.add_argument("--refine", type=float, nargs="+", default=None,
                        help="absolute refine factors (default: the preset's and twice it)")
    parser.add_argument("--preset", default="paper", choices=["paper", "small"])
    parser.add_argument("--spin-up", type=float, default=None, help="override the preset's minimum spin-up (R/U)")
    parser.add_argument("--spin-up-max", type=float, default=None, help="override the preset's maximum spin-up (R/U)")
    parser.add_argument("--frames", type=int, default=None, help="override the preset's frame count")
    parser.add_argument("--wall-cell", type=float, default=None,
                        help="override the preset's first radial cell at the cylinder (R; refine divides it)")
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--workdir", type=Path, default=Path("cylinder-mesh-study.work"))
    parser.add_argument("--spin-up-check", type=float, nargs="*", default=[])
    parser.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    parser.add_argument(
        "--frames-figure",
        type=Path,
        default=None,
        help="draw u, v, p of the first Re on the coarsest mesh at four times, with the paper sensors",
    )
    args = parser.parse_args()

    base = cc.preset_settings(args.preset)
    preset_refine = float(base["refine"])
    if args.refine is None:
        args.refine = [preset_refine, 2.0 * preset_refine]
    if args.spin_up is not None:
        base["spin_up"] = args.spin_up
    if args.spin_up_max is not None:
        base["spin_up_max"] = args.spin_up_max
    if args.wall_cell is not None:
        base["wall_cell"] = args.wall_cell
    cc.check_settings(base)
    if args.frames is not None:
        base["n_frames"] = args.frames
    start = time.perf_counter()
    cases = [(re, rf) for re in args.re for rf in args.refine] + [(re, preset_refine) for re in args.spin_up_check]
    results = run_cases(cases, base, args.workdir, args.workers)

    rows = []
    for re in args.re:
        for rf in args.refine:
            r = results[(re, rf)]
            rows.append({
                "Re": re, "refine": rf, "cells": r["cells"],
                "St": cc.strouhal(r["lift"], base["force_dt"]), "St_roshko": roshko(re),
                "Cd_mean": float(np.mean(r["drag"])), "Cl_amplitude": float(0.5 * np.ptp(r["lift"])),
                "wall_s": float(r["wall_s"]),
            })  # fmt: skip
    print(
        "\n| Re | refine | cells | St | St Roshko | St / Roshko - 1 | mean Cd | Cl amplitude | change St | change Cd "
        "| run time |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    verdict = True
    for row in rows:
        coarse = next(r for r in rows if r["Re"] == row["Re"] and r["refine"] == min(args.refine))
        d_st = row["St"] / coarse["St"] - 1.0
        d_cd = row["Cd_mean"] / coarse["Cd_mean"] - 1.0
        row["change_St"], row["change_Cd"] = d_st, d_cd
        if row is not coarse:
            verdict &= bool(abs(d_st) < TOLERANCE and abs(d_cd) < TOLERANCE)
        print(
            f"| {row['Re']:g} | {row['refine']:g} | {row['cells']} | {row['St']:.4f} | {row['St_roshko']:.4f} | "
            f"{100 * (row['St'] / row['St_roshko'] - 1):+.1f} % | {row['Cd_mean']:.4f} | {row['Cl_amplitude']:.4f} | "
            f"{100 * d_st:+.2f} % | {100 * d_cd:+.2f} % | {row['wall_s']:.0f} s |"
        )
    print(f"\nmesh criterion (|change| < 3 % for St and mean Cd): {'PASS' if verdict else 'FAIL'}")

    spin = []
    if args.spin_up_check:
        print("\nLift amplitude (half peak-to-peak) over the spin-up, in windows of 10 R/U, and over the recording:")
        for re in args.spin_up_check:
            r = results[(re, preset_refine)]
            ls = r["lift_spin_up"]
            per = round(10.0 / base["force_dt"])
            windows = [0.5 * float(np.ptp(ls[i : i + per])) for i in range(0, len(ls) - per + 1, per)]
            rec = 0.5 * float(np.ptp(r["lift"]))
            spin.append({"Re": re, "spin_up_windows": windows, "recording": rec,
                         "t_start": float(r.get("t_start", np.nan)),
                         "St": cc.strouhal(r["lift"], base["force_dt"])})  # fmt: skip
            print(
                f"  Re {re:g}: spin-up {spin[-1]['t_start']:g} R/U, last windows "
                f"{', '.join(f'{w:.4f}' for w in windows[-4:])}; recording {rec:.4f}; St {spin[-1]['St']:.4f}"
            )
    if args.frames_figure:
        frames_figure(results[(args.re[0], min(args.refine))]["fields"], args.re[0], base, args.frames_figure)
        print(f"figure: {args.frames_figure}")
    total = time.perf_counter() - start
    print(f"\nwall time {total:.0f} s")
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "spin_up": spin, "settings": base, "pass": verdict}, indent=2))


if __name__ == "__main__":
    main()
