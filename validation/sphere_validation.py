"""Validate the sphere-wake lattice Boltzmann case: drag vs Schiller-Naumann, wake regime, Strouhal number.

Runs the sphere case of :mod:`dks_gym.solvers.sphere_case` (the domain of the benchmark) without
fields, records the force coefficients every few lattice steps and writes a JSON summary:

* mean drag coefficient over the last ``--average`` R/U, against Schiller-Naumann
  Cd = 24/Re (1 + 0.15 Re^0.687), raw and with a simple blockage correction (continuity: the mean
  velocity past the sphere is U / (1 - B), B = pi/64, so Cd_corr = Cd (1 - B)^2);
* wake regime from the lift over the same window: its rms, and the Strouhal number St = f D / U of its
  dominant frequency (lift projected on its principal direction in the y-z plane);
* one JSON per invocation under validation/results/.

Examples (CPU, minutes each)::

    python validation/sphere_validation.py --re 100 200 --resolution 4 --u-lattice 0.05 --time 40 \\
        --out validation/results/sphere_validation_cd_r4.json
    python validation/sphere_validation.py --turek 10 20 --out validation/results/lbm_turek_2d1.json
    python validation/sphere_validation.py --re 350 --resolution 4 --u-lattice 0.05 --time 150 --average 75 \\
        --out validation/results/sphere_validation_re350_r4.json

Reference values: Schiller & Naumann (1933) correlation (about 5 % accurate for Re < 800);
Strouhal number of the sphere wake at Re = 350: about 0.13-0.14 (Johnson & Patel 1999, J. Fluid
Mech. 378, St = 0.137 at Re = 300; Tomboulides & Orszag 2000, J. Fluid Mech. 416, St ~ 0.136 at
Re = 300 and ~0.14 at Re = 350). Steady axisymmetric wake below Re ~ 210, steady planar-symmetric
(non-zero steady lift) for 210 < Re < 270, periodic shedding above Re ~ 270-280 (Johnson & Patel 1999).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np
import torch

from dks_gym.benchmarks import get_benchmark
from dks_gym.benchmarks.sphere import BLOCKAGE
from dks_gym.solvers.sphere_case import simulate


def schiller_naumann(re: float) -> float:
    return 24.0 / re * (1.0 + 0.15 * re**0.687)


def strouhal(t: np.ndarray, lift: np.ndarray) -> tuple[float, float]:
    """(St, rms) of the lift (n, 2) over times t (R/U): dominant frequency of its principal component."""
    centred = lift - lift.mean(0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    signal = centred @ vt[0]
    rms = float(np.sqrt((signal**2).mean()))
    dt = float(t[1] - t[0])
    n = signal.size
    pad = 8 * n
    spec = np.abs(np.fft.rfft(signal * np.hanning(n), pad))
    freq = np.fft.rfftfreq(pad, dt)
    k = int(np.argmax(spec[1:])) + 1
    return 2.0 * float(freq[k]), rms  # St = f D / U = 2 f (time in R/U)


def turek_2d1(d: int, steps: int, device: str = "cpu", compile: bool = True) -> dict:
    """The 2D solver on Schafer & Turek (1996) benchmark 2D-1: cylinder of D nodes at (2D, 2D) in a channel
    4.1 D high and 22 D long, parabolic inflow, Re = U_mean D / nu = 20; reference Cd 5.5795, Cl 0.0106."""
    from dks_gym.solvers import lbm

    h, length = round(4.1 * d), round(22 * d)
    shape = (length + 1, h + 2)
    x = np.arange(shape[0])[:, None]
    y = np.arange(shape[1])[None, :] - 0.5  # walls at y = 0 and y = h
    body = (x - 2 * d) ** 2 + (y - 2 * d) ** 2 < (d / 2) ** 2
    solid = body.copy()
    solid[:, [0, -1]] = True
    u_mean = 0.05
    yy = y[0]
    profile = np.where((yy > 0) & (yy < h), 6 * u_mean * yy * (h - yy) / h**2, 0.0)
    sim = lbm.LBM("D2Q9", shape, [u_mean * d / 20], solid=solid, body=body, outlet=True, smagorinsky=0.0,
                  inlet_velocity=np.stack([profile, 0 * profile]), device=device, compile=compile)
    sim.initialize(np.stack([np.broadcast_to(profile, shape), np.zeros(shape)]))
    t0 = time.perf_counter()
    sim.step(steps)
    cd, cl = (sim.body_force()[0].cpu().numpy() / (0.5 * u_mean**2 * d)).tolist()
    sec = time.perf_counter() - t0
    print(f"Schafer-Turek 2D-1, D = {d}: Cd {cd:.4f} ({100 * (cd / 5.5795 - 1):+.1f}%), Cl {cl:.4f} (ref 0.0106)",
          flush=True)
    return {"D": d, "shape": list(shape), "steps": steps, "Cd": cd, "Cl": cl, "Cd_ref": 5.5795, "Cl_ref": 0.0106,
            "Cd_error": cd / 5.5795 - 1.0, "seconds": sec}


def cylinder_2d(resolution: int, reynolds: float, spin_up: float, record: float, *, u_lattice: float = 0.05,
                smagorinsky: float = 0.15, device: str = "cpu", compile: bool = True) -> dict:
    """The 2D solver (D2Q9) on the cylinder benchmark's own case, to set beside its OpenFOAM data.

    Same geometry, units and faces as :mod:`dks_gym.solvers.cylinder_case`: x in [-8R, 16R], y in [-4R, 4R],
    cylinder of radius R at the origin, uniform inflow U, no-slip walls at y = +-4R (half-way bounce-back
    exactly on them), pressure outlet behind the same absorbing layer as the sphere case (4R beyond x = 16R).
    ``resolution`` nodes per R; impulsive start plus a v bump behind the body; the lift and drag
    (C = F / (1/2 rho U^2 D) per unit depth, as OpenFOAM's forceCoeffs) are sampled every 0.1 R/U over the
    last ``record`` R/U after ``spin_up``; St from the mean period between upward zero crossings of the lift,
    the same estimate as the OpenFOAM mesh study (:func:`dks_gym.solvers.cylinder_case.strouhal`).
    """
    from dks_gym.solvers import cylinder_case as cc
    from dks_gym.solvers import lbm, sphere_case

    r = int(resolution)
    sponge, strength = sphere_case.DEFAULTS["sponge"], sphere_case.DEFAULTS["sponge_strength"]
    x, y, _ = sphere_case.lattice_axes(r, sponge)  # the sphere lattice's x-y plane: walls exactly at y = +-4R
    body = x[:, None] ** 2 + y[None, :] ** 2 < 1.0
    solid = body.copy()
    solid[:, [0, -1]] = True
    shape = solid.shape
    absorber = strength * np.clip((x - sphere_case.EXTENT[0][1]) / sponge, 0.0, 1.0) ** 2
    nu = u_lattice * 2.0 * r / reynolds
    sim = lbm.LBM("D2Q9", shape, [nu], solid=solid, body=body, inlet_velocity=(u_lattice, 0.0), outlet=True,
                  absorber=absorber, smagorinsky=smagorinsky, device=device, compile=compile)
    u0 = np.zeros((2, *shape), np.float32)
    u0[0] = u_lattice
    u0[1] = 0.5 * u_lattice * np.exp(-((x[:, None] - 3.0) ** 2 + y[None, :] ** 2))
    sim.initialize(u0)
    per_sample = round(0.1 * r / u_lattice)  # lattice steps per 0.1 R/U
    dt_sample = per_sample * u_lattice / r
    t0 = time.perf_counter()
    sim.step(round(spin_up / dt_sample) * per_sample)
    samples = []
    for _ in range(round(record / dt_sample)):
        sim.step(per_sample)
        samples.append(sim.body_force()[0].cpu().numpy() / (0.5 * u_lattice**2 * 2 * r))
    if not bool(sim.is_finite().all()):
        raise RuntimeError(f"the D2Q9 cylinder run diverged at Re = {reynolds}, resolution {r}")
    sec = time.perf_counter() - t0
    c = np.array(samples)
    st, cd = cc.strouhal(c[:, 1], dt_sample), float(c[:, 0].mean())
    print(f"D2Q9 cylinder, Re {reynolds:g}, r = {r} ({shape[0]} x {shape[1]} nodes, Cs {smagorinsky}): "
          f"St {st:.4f}, mean Cd {cd:.4f}, Cl amplitude {np.ptp(c[:, 1]) / 2:.3f} ({sec:.0f} s)", flush=True)
    return {"Re": reynolds, "resolution": r, "shape": list(shape), "u_lattice": u_lattice, "smagorinsky": smagorinsky,
            "spin_up": spin_up, "record": record, "St": st, "Cd": cd, "Cl_amplitude": float(np.ptp(c[:, 1]) / 2),
            "seconds": sec, "lattice_updates": float(np.prod(shape)) * sim.time}


def write_rows(out: Path | None, case: str, rows: list[dict]) -> None:
    """The JSON of a 2D check ({"case", "rows"}) at ``out``, if given."""
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps({"case": case, "rows": rows}, indent=1))
        print(f"wrote {out}")


def plot(results: Path, out: Path) -> None:
    """Figure from the JSON files: Cd vs resolution at Re 100 and the lift series at Re 350 and 700."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.6))
    rs, cds = [], []
    for r in (3, 4, 5, 8):
        for f in (results / f"sphere_validation_nowalls_re100_r{r}.json",
                  results / f"sphere_validation_nowalls_r{r}.json"):
            if f.exists():  # rows[0] is Re 100 in both
                rs.append(r)
                cds.append(json.loads(f.read_text())["rows"][0]["Cd"])
                break
    a.plot(rs, cds, "o-", label="LBM, periodic 8R box")
    walls = results / "sphere_validation_walls_r4.json"
    if walls.exists():
        a.plot([4], [json.loads(walls.read_text())["rows"][0]["Cd"]], "s", label="LBM, benchmark walls")
    a.axhline(schiller_naumann(100.0), color="k", ls="--", label="Schiller-Naumann")
    a.axhline(schiller_naumann(100.0) / (1 - BLOCKAGE) ** 2, color="0.5", ls=":",
              label="Schiller-Naumann / (1-B)², continuity blockage")
    a.set(xlabel="nodes per R", ylabel="Cd", title="Re = 100")
    a.legend()
    for re in (350, 700):
        f = results / f"sphere_validation_re{re}_r4.json"
        if f.exists():
            d = json.loads(f.read_text())
            b.plot(d["lift_series"]["time"], np.asarray(d["lift_series"]["cl"])[0, :, 0], label=f"Re {re}, Cl_y")
    b.set(xlabel="t (R/U)", ylabel="lift coefficient", title="benchmark domain, r = 4")
    b.legend()
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    print(f"wrote {out}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--re", type=float, nargs="+", default=[100.0, 200.0])
    ap.add_argument("--resolution", type=int, default=4, help="lattice nodes per sphere radius")
    ap.add_argument("--u-lattice", type=float, default=0.05)
    ap.add_argument("--time", type=float, default=40.0, help="simulated time, R/U")
    ap.add_argument("--average", type=float, default=None, help="averaging window at the end, R/U (default half)")
    ap.add_argument("--smagorinsky", type=float, default=0.15)
    ap.add_argument("--no-walls", action="store_true",
                    help="periodic y faces instead of the no-slip walls (isolates the wall confinement)")
    ap.add_argument("--half-width", type=float, default=4.0,
                    help="half size of the y-z cross-section in R (4 in the benchmark; larger lowers the blockage)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--compile", action=argparse.BooleanOptionalAction, default=True)
    ap.add_argument("--force-every", type=int, default=10, help="force sampling interval, lattice steps")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--turek", type=int, nargs="*", default=None,
                    help="instead: the 2D solver on the Schafer-Turek 2D-1 cylinder at these diameters (nodes)")
    ap.add_argument("--cylinder", type=int, nargs="*", default=None,
                    help="instead: the 2D solver on the cylinder benchmark's case at these resolutions (nodes per R), "
                         "at the first --re, spin-up --time, recording --average R/U (default 50)")
    ap.add_argument("--plot", type=Path, default=None,
                    help="instead: draw the figure from validation/results into PATH")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    if args.plot is not None:
        plot(Path(__file__).parent / "results", args.plot)
        return 0
    if args.turek:
        rows = [turek_2d1(d, 1600 * d, args.device, args.compile) for d in args.turek]
        write_rows(args.out, "Schafer-Turek 2D-1", rows)
        return 0
    if args.cylinder:
        record = args.average if args.average is not None else 50.0
        rows = [cylinder_2d(r, args.re[0], args.time, record, u_lattice=args.u_lattice, smagorinsky=args.smagorinsky,
                            device=args.device, compile=args.compile) for r in args.cylinder]
        write_rows(args.out, "cylinder benchmark, D2Q9", rows)
        return 0
    bench = get_benchmark("sphere")
    settings = {"resolution": args.resolution, "u_lattice": args.u_lattice, "spin_up": args.time, "n_frames": 1,
                "smagorinsky": args.smagorinsky, "walls": not args.no_walls, "half_width": args.half_width}
    t0 = time.perf_counter()
    out = simulate(np.array(args.re), settings, coords=bench.coords(), cell_type=bench.cell_type(),
                   device=args.device, compile=args.compile, fields=False, force_every=args.force_every)
    wall = time.perf_counter() - t0
    t = out["force_time"]
    window = args.average if args.average is not None else args.time / 2
    sel = t >= t[-1] - window
    rows = []
    for i, re in enumerate(args.re):
        c = out["force_coefficients"][i]
        cd = float(c[sel, 0].mean())
        sn = schiller_naumann(re)
        st, rms = strouhal(t[sel], c[sel, 1:])
        blockage = BLOCKAGE * (4.0 / args.half_width) ** 2
        cd_corr = cd * (1.0 - blockage) ** 2
        rows.append({
            "Re": re, "Cd": cd, "Cd_blockage_corrected": cd_corr, "Cd_schiller_naumann": sn,
            "Cd_error": cd / sn - 1.0, "Cd_corrected_error": cd_corr / sn - 1.0,
            "Cd_std_window": float(c[sel, 0].std()), "lift_rms": rms,
            "lift_mean": [float(v) for v in c[sel, 1:].mean(0)], "St": st,
            "Cd_first_half_of_window": float(c[sel, 0][: sel.sum() // 2].mean()),
        })
        print(f"Re {re:6.1f}: Cd {cd:.4f} (corrected {cd_corr:.4f}) vs Schiller-Naumann {sn:.4f} "
              f"-> {100 * (cd / sn - 1):+.1f}% ({100 * (cd_corr / sn - 1):+.1f}%); lift rms {rms:.2e}, "
              f"mean lift {rows[-1]['lift_mean']}, St {st:.3f}", flush=True)
    result = {
        "settings": {**settings, "time": args.time, "average": window, "force_every": args.force_every},
        "lattice_shape": list(out["lattice_shape"]), "nu_lattice": out["nu_lattice"].tolist(),
        "blockage": BLOCKAGE * (4.0 / args.half_width) ** 2, "device": str(args.device), "compile": args.compile,
        "wall_seconds": wall, "mlups": out["lattice_updates"] / wall / 1e6,
        "machine": platform.processor() or platform.machine(), "torch": torch.__version__, "rows": rows,
        "lift_series": {"time": t[sel].tolist(), "cl": out["force_coefficients"][:, sel, 1:].tolist(),
                        "cd": out["force_coefficients"][:, sel, 0].tolist()},
    }
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=1))
        print(f"wrote {args.out}")
    print(f"{wall:.0f} s, {result['mlups']:.2f} MLUPS")
    return 0


if __name__ == "__main__":
    sys.exit(main())
