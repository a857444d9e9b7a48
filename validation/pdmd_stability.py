"""pDMD forward runs under other thread counts, BLAS code paths and dtypes: before and after issue 16.

Fits pDMD (r = 32 unless the data has fewer frames) on one dataset (default: the Burgers ``paper`` preset)
and runs the forward run of every test and train trajectory: A~(mu) applied n_t - 1 times to the encoded
first frame (the exact initial condition), decoded, compared with the last frame. It does so under

* torch threads 1 and 2 x BLAS threads 1 and 2 (``threadpoolctl``) x forward-run inputs (the first frame,
  hence the latent state) in float32 and float64: 8 configurations in this process;
* with ``--emulate``, in child processes whose OpenBLAS and MKL take the code paths of other CPUs
  (``OPENBLAS_CORETYPE``, ``MKL_CBWR``), as another machine would (1 thread, both dtypes each);

once with ``dks_gym/models/pdmd.py`` as of ``--before-ref`` (default b012fbc, the last commit before the
fix) and once with the working tree's (``after``). Per configuration and trajectory it records the final
MSE (physical units) and the relative L2 error of the final frame; per split the largest ||A~(mu)||_2 and
|eig A~(mu)| over the split's parameters. The summary gives per version the worst relative spread of one
trajectory's final MSE across all configurations, the diverging trajectories (relative error > 1) and the
extremes. The JSON holds file names and the dataset fingerprint, no paths.

    OMP_NUM_THREADS=1 python validation/pdmd_stability.py --emulate --out validation/results/pdmd_stability.json
    OMP_NUM_THREADS=1 python validation/pdmd_stability.py --benchmark cylinder --preset small \\
        --out validation/results/pdmd_stability_cylinder_small.json
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import torch
from threadpoolctl import threadpool_limits

ROOT = Path(__file__).resolve().parents[1]
BEFORE_REF = "b012fbc"
#: Environment settings that make OpenBLAS (numpy, scipy, PyDMD) and MKL (torch) run other CPUs' kernels.
EMULATED_CPUS = {
    "openblas-prescott": {"OPENBLAS_CORETYPE": "Prescott"},
    "openblas-skylakex+mkl-avx2": {"OPENBLAS_CORETYPE": "SkylakeX", "MKL_CBWR": "AVX2"},
    "openblas-sandybridge+mkl-compatible": {"OPENBLAS_CORETYPE": "Sandybridge", "MKL_CBWR": "COMPATIBLE"},
}
DTYPES = {"float32": torch.float32, "float64": torch.float64}


def pdmd_module(version: str, before_ref: str) -> ModuleType:
    """``dks_gym.models.pdmd`` (after) or the file as of ``before_ref``, imported beside it (before)."""
    if version == "after":
        from dks_gym.models import pdmd

        return pdmd
    source = subprocess.run(["git", "show", f"{before_ref}:dks_gym/models/pdmd.py"], cwd=ROOT, check=True,
                            capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp(prefix="pdmd_before_")) / "pdmd_before.py"
    path.write_text(source)
    import dks_gym.models  # noqa: F401  (the package its relative imports resolve in)

    spec = importlib.util.spec_from_file_location("dks_gym.models._pdmd_before", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def operator_stats(model: Any, mu: np.ndarray) -> dict[str, float]:
    a = model.online_operator(mu)
    return {"max_norm": float(torch.linalg.matrix_norm(a, ord=2).max()),
            "max_abs_eig": float(torch.linalg.eigvals(a).abs().max())}


def forward_runs(model: Any, ds: Any, split: str, dtype: torch.dtype) -> dict[str, list[float]]:
    """Final MSE and relative L2 error of the forward run of every trajectory of ``split``."""
    fields = ds.fields(split)
    mu = torch.as_tensor(ds.params(split))
    first = torch.as_tensor(np.asarray(fields[:, 0]), dtype=dtype)
    last = torch.as_tensor(np.asarray(fields[:, -1]), dtype=torch.float64)
    with torch.no_grad():
        z = model.rollout(model.encode(first, mu), mu, fields.shape[1] - 1)[:, -1]
        err = (model.decode(z, mu).double() - last).flatten(1)
    return {"final_mse": (err**2).mean(1).tolist(),
            "final_rel_l2": (err.norm(dim=1) / last.flatten(1).norm(dim=1)).tolist()}


def run_config(module: ModuleType, ds: Any, r: int, torch_threads: int, blas_threads: int,
               dtypes: list[str], settings: dict[str, float | None]) -> list[dict[str, Any]]:
    """Fit under the given thread counts, then forward runs in each dtype: one row per dtype."""
    from dks_gym.models.presets import benchmark_shape

    torch.set_num_threads(torch_threads)
    rows = []
    with threadpool_limits(blas_threads):
        start = time.perf_counter()
        model = module.PDMD(benchmark_shape(ds.benchmark.name), r, dt=ds.dt, stats_mean=ds.stats_mean,
                            stats_std=ds.stats_std, **settings).fit_dataset(ds, seed=0)
        fit_s = time.perf_counter() - start
        ops = {split: operator_stats(model, ds.params(split)) for split in ("test", "train")}
        for name in dtypes:
            row = {"torch_threads": torch_threads, "blas_threads": blas_threads, "dtype": name,
                   "fit_s": round(fit_s, 2)}
            for split in ("test", "train"):
                row[split] = {**forward_runs(model, ds, split, DTYPES[name]), **ops[split]}
            rows.append(row)
    return rows


def summarize(rows: list[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for split in ("test", "train"):
        mse = np.array([row[split]["final_mse"] for row in rows])  # (configs, trajectories)
        rel = np.array([row[split]["final_rel_l2"] for row in rows])
        spread = (mse.max(0) - mse.min(0)) / mse.min(0)
        out[split] = {
            "max_final_mse": float(mse.max()),
            "mean_final_mse_range": [float(mse.mean(1).min()), float(mse.mean(1).max())],
            "max_final_rel_l2": float(rel.max()),
            "diverged_trajectories": int((rel > 1).any(0).sum()),
            "diverged_in_some_config": int((rel > 1).any(1).sum()),
            "worst_relative_spread_of_final_mse": float(spread.max()),
            "max_norm_range": [min(r[split]["max_norm"] for r in rows), max(r[split]["max_norm"] for r in rows)],
            "max_abs_eig_range": [min(r[split]["max_abs_eig"] for r in rows),
                                  max(r[split]["max_abs_eig"] for r in rows)],
        }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    parser.add_argument("--benchmark", default="burgers")
    parser.add_argument("--preset", default="paper", help="dataset preset (generated if missing)")
    parser.add_argument("--r", type=int, default=32, help="latent dimension, at most n_t - 1 (default 32)")
    parser.add_argument("--versions", nargs="+", default=["before", "after"], choices=["before", "after"])
    parser.add_argument("--before-ref", default=BEFORE_REF, help="git revision of the 'before' pdmd.py")
    parser.add_argument("--emulate", action="store_true", help="also run in children emulating other CPUs")
    parser.add_argument("--out", type=Path, default=Path("pdmd_stability.json"))
    parser.add_argument("--setting", action="append", default=[], metavar="NAME=VALUE",
                        help="a regularization setting of the 'after' PDMD (dmd_tikhonov, rbf_smoothing, "
                             "operator_tikhonov, pinv_rtol; 'none' for None); repeatable")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)  # VERSION: one config, JSON on stdout
    args = parser.parse_args()
    settings = {}
    for item in args.setting:
        name, _, value = item.partition("=")
        settings[name] = None if value.lower() == "none" else float(value)

    from dks_gym.dataset import generate_dataset, load_dataset
    from dks_gym.models.checkpoint import dataset_identity

    generate_dataset(args.benchmark, args.preset, progress=False)
    ds = load_dataset(args.benchmark, preset=args.preset)
    r = min(args.r, ds.fields("train").shape[1] - 1)
    if args.child:
        rows = run_config(pdmd_module(args.child, args.before_ref), ds, r, 1, 1, list(DTYPES),
                          settings if args.child == "after" else {})
        print(json.dumps(rows))
        return

    versions: dict[str, Any] = {}
    for version in args.versions:
        module = pdmd_module(version, args.before_ref)
        rows = []
        for torch_threads in (1, 2):
            for blas_threads in (1, 2):
                rows += run_config(module, ds, r, torch_threads, blas_threads, list(DTYPES),
                                   settings if version == "after" else {})
                print(f"{version}: torch {torch_threads} BLAS {blas_threads} done", flush=True)
        for row in rows:
            row["cpu"] = "native"
        if args.emulate:
            for name, env in EMULATED_CPUS.items():
                cmd = [sys.executable, str(Path(__file__).resolve()), "--benchmark", args.benchmark, "--preset",
                       args.preset, "--r", str(r), "--before-ref", args.before_ref, "--child", version,
                       *(f"--setting={item}" for item in args.setting)]
                done = subprocess.run(cmd, env={**os.environ, **env}, check=True, capture_output=True, text=True)
                for row in json.loads(done.stdout.strip().splitlines()[-1]):
                    rows.append({**row, "cpu": name})
                print(f"{version}: emulated {name} done", flush=True)
        versions[version] = {"summary": summarize(rows), "configs": rows}

    import scipy
    from importlib.metadata import version as package_version

    identity = dataset_identity(ds)
    payload = {
        "command": "python validation/pdmd_stability.py " + " ".join(sys.argv[1:]),
        "benchmark": args.benchmark,
        "dataset": {**identity, "path": Path(identity["path"]).name},
        "r": r,
        "before_ref": args.before_ref,
        "after_settings": settings,
        "emulated_cpus": EMULATED_CPUS if args.emulate else {},
        "params": {split: ds.params(split).tolist() for split in ("test", "train")},
        "environment": {"python": platform.python_version(), "machine": platform.machine(),
                        "torch": torch.__version__, "numpy": np.__version__, "scipy": scipy.__version__,
                        "pydmd": package_version("pydmd")},
        "versions": versions,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(payload, indent=1) + "\n")
    for version, v in versions.items():
        for split, s in v["summary"].items():
            print(f"{version:6s} {split:5s} max final MSE {s['max_final_mse']:.3g}, max rel L2 "
                  f"{s['max_final_rel_l2']:.3g}, diverged {s['diverged_trajectories']}, worst MSE spread "
                  f"{s['worst_relative_spread_of_final_mse']:.2g}, max||A~|| {s['max_norm_range'][0]:.4g}.."
                  f"{s['max_norm_range'][1]:.4g}, max|eig| {s['max_abs_eig_range'][0]:.4g}.."
                  f"{s['max_abs_eig_range'][1]:.4g}")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
