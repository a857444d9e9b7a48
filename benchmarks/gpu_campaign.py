"""The CUDA paths measured in one run: tests, vector env, lattice Boltzmann, sphere validation and generation, training.

    python benchmarks/gpu_campaign.py --out DIR                  # on a CUDA machine: about 8 min (--budget 480)
    python benchmarks/gpu_campaign.py --quick --out /tmp/gpuc    # a smoke run with tiny sizes (the CPU is enough)
    python benchmarks/gpu_campaign.py --strouhal DIR/sphere_validation.json   # the shedding, from the stored series

Steps, in priority order, each in a child process of its own (a crash or a hang in one leaves the others, and
each starts with a fresh CUDA context and torch.compile cache) and under a time cap: its share of ``--budget``
plus whatever the earlier steps left unused. A step rewrites ``DIR/<step>.json`` after every measurement, so a
step stopped at its cap keeps what it measured; within a step, a measurement whose predicted time no longer
fits is skipped and listed. ``DIR/summary.json`` (the machine, and per step its status, time and headline) is
rewritten after every step.

1. ``tests``: the tests that skip without CUDA (``-k cuda`` in tests/test_models.py and tests/test_filters.py:
   the sensor-local Jacobian and the inference decoder, the EKF and EnKF, each on CUDA against the CPU) and
   ``test_cli_train`` (which trains on CUDA when it is there), with pytest's output tail.
2. ``vector``: ``LatentFilterVectorEnv`` on Burgers ``paper`` data with the shipped lite Koopman model
   (r = 32, 16 sensors, the paper's Q and P0), EKF and EnKF (20 members), uncertainty off and on: env-steps
   per second at N = 256, 1024 and 4096 on CUDA, and at N = 256 on the CPU with all cores and with one thread.
   The N SensingEnvs are built once per N and reused by every filter (building one opens and validates the
   dataset file). The mean MSE after each step is kept, so CUDA and CPU runs can be set side by side.
3. ``lbm``: the D3Q19 solver on CUDA: a small sphere case (fields resampled to 64^3, drag) on the CPU and on
   CUDA, then the throughput of ``benchmarks/lbm_throughput.py``'s case on the paper lattice (225 x 66 x 64) at
   batch 1, 32 and 8, eager and compiled: MLUPS, compile time, peak memory per case
   (``torch.cuda.max_memory_allocated``) against ``lbm.bytes_per_case``, and the compiled populations against
   the eager ones after the same steps.
4. ``sphere_validation``: ``validation/sphere_validation.py``'s measurement on CUDA at r = 8 (then r = 12):
   mean Cd at Re 100 and 200 in the periodic 8R box against Schiller-Naumann (raw and continuity-corrected),
   the same run as the CPU's ``validation/results/sphere_validation_nowalls_r8.json``; Re 350 over 150 R/U
   (periodic box, then the benchmark's walls): lift rms, its spectrum's peak and the Strouhal number from the
   spectrum and from zero crossings (literature: 0.137 at Re 300, Johnson & Patel 1999, J. Fluid Mech. 378;
   about 0.14 at Re 350, Tomboulides & Orszag 2000, J. Fluid Mech. 416).
5. ``sphere_generation``: the ``paper`` preset's generator (``sphere_case.run_batches``: the preset's lattice,
   spin-up and 100 frames resampled to 64^3, compiled on CUDA) for a few Reynolds numbers of its sweep spread
   over the range, timed, and the 101-run sweep's time extrapolated.
6. ``training``: the ``paper`` preset's Burgers Koopman model (batch 256, lr 1e-4) on CUDA: a 200-step run to
   time a step, then a fresh run of as many steps as the cap leaves (at most 20,000: the paper's "1000
   training steps" read as epochs), with its one-step error against persistence and its forward and EKF
   (paper Q and P0) final MSE on the test split beside the paper's.

The Burgers ``paper`` data are generated first into ``--home`` (DKS_GYM_HOME; default a temporary folder).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import re
import signal
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path
from typing import Any, Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
STEPS = ("tests", "vector", "lbm", "sphere_validation", "sphere_generation", "training")
# Share of the budget per step (steps 1-3 about half); time a step leaves unused goes to the next ones.
SHARES = {"tests": 0.10, "vector": 0.25, "lbm": 0.18, "sphere_validation": 0.20, "sphere_generation": 0.13,
          "training": 0.14}
GRACE = 15.0  # seconds a child may overrun its cap (writing its JSON) before it is killed
PAPER_LATTICE = (225, 66, 64)  # the sphere's paper preset: r = 8 with the 4R absorbing layer


# Shared pieces -------------------------------------------------------------------------------------------
def load_script(relative: str) -> Any:
    """A script of this repository (benchmarks/, validation/) imported as a module."""
    path = ROOT / relative
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def jsonable(value: Any) -> Any:
    """numpy scalars and arrays, tuples and paths as JSON values."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serializable: {type(value).__name__}")


def write_json(path: Path, doc: dict[str, Any]) -> None:
    """Write ``doc`` to ``path`` through a temporary file, so a reader never sees half a file."""
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(doc, indent=1, default=jsonable) + "\n")
    os.replace(tmp, path)


class Record:
    """A step's JSON document, rewritten after every change."""

    def __init__(self, out: Path, step: str, deadline: float, quick: bool) -> None:
        self.path = out / f"{step}.json"
        self.deadline = deadline
        self.quick = quick
        self.doc: dict[str, Any] = {"step": step, "status": "running", "quick": quick, "headline": {},
                                    "rows": [], "skipped": []}
        self.write()

    def left(self) -> float:
        """Seconds left before the step's deadline."""
        return self.deadline - time.time()

    def add(self, row: dict[str, Any]) -> None:
        self.doc["rows"].append(row)
        self.write()

    def skip(self, what: str, why: str) -> None:
        print(f"  skipped {what}: {why}", flush=True)
        self.doc["skipped"].append({"what": what, "why": why})
        self.write()

    def fits(self, what: str, predicted: float, margin: float = 5.0) -> bool:
        """Whether ``predicted`` seconds fit before the deadline; else the measurement is listed as skipped."""
        if predicted + margin <= self.left():
            return True
        self.skip(what, f"predicted {predicted:.0f} s, {self.left():.0f} s left in the step's cap")
        return False

    def write(self) -> None:
        write_json(self.path, self.doc)


def device_name() -> str:
    """'cuda' when a GPU is there, else 'cpu' (the quick run's fallback)."""
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


def synchronize() -> None:
    import torch

    if torch.cuda.is_available():
        torch.cuda.synchronize()


# 1. tests ------------------------------------------------------------------------------------------------
TEST_FILES = ("tests/test_models.py", "tests/test_filters.py", "tests/test_training.py")


def step_tests(rec: Record) -> None:
    """The tests that skip without CUDA, one process, their outcome counts and output tail."""
    cmd = [sys.executable, "-m", "pytest", "-q", "-rA", "-n", "0", "-p", "no:cacheprovider", "--timeout", "300",
           *TEST_FILES, "-k", "cuda or test_cli_train"]
    rec.doc["command"] = "python -m pytest -q -rA -n 0 " + " ".join(TEST_FILES) + ' -k "cuda or test_cli_train"'
    start = time.perf_counter()
    try:
        proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=max(10.0, rec.left() - 5))
        output, rc = proc.stdout + proc.stderr, proc.returncode
    except subprocess.TimeoutExpired as exc:  # what pytest printed before its time ran out
        output, rc = (exc.stdout or b"").decode(errors="replace"), "timeout"
    counts = {word: int(n) for n, word in re.findall(r"(\d+) (passed|failed|skipped|deselected|errors?)", output)}
    outcomes = re.findall(r"^(PASSED|FAILED|SKIPPED|ERROR) (\S+)", output, flags=re.M)
    rec.doc.update(rc=rc, seconds=time.perf_counter() - start, counts=counts, outcomes=outcomes,
                   tail=output[-8000:])
    rec.doc["headline"] = {"rc": rc, **counts}
    print(output[-3000:], flush=True)
    if rc != 0:
        raise RuntimeError(f"pytest exited with {rc}")


# 2. vector env -------------------------------------------------------------------------------------------
def build_vector_env(model: Any, n: int) -> Any:
    from dks_gym.wrappers import LatentFilterVectorEnv

    return LatentFilterVectorEnv("burgers", n, model=model, filter="ekf", uncertainty=False)


def use_filter(venv: Any, model: Any, kind: str, uncertainty: bool) -> None:
    """Put a fresh assimilation core (``kind``, the paper's Q and P0, ``uncertainty``) of ``model`` on the vector
    env's SensingEnvs, as the constructor would have built it, so that one set of N envs serves every filter."""
    from dks_gym.assimilation import FilterConfig
    from dks_gym.wrappers.building import build_assimilation

    config = FilterConfig(kind=kind, Q="paper", P0="paper")
    venv.assimilation = build_assimilation(venv.envs[0], model, None, config, reward="mse", uncertainty=uncertainty)
    venv.model, venv.config = venv.assimilation.model, venv.assimilation.config


def time_vector_env(venv: Any, warm: int, steps: int) -> dict[str, Any]:
    """Reset (seed 0), ``warm`` untimed steps, ``steps`` timed ones inside one episode; env-steps per second and
    the mean MSE over the envs after every step."""
    n = venv.num_envs
    actions = np.zeros(n, dtype=np.int64)
    t0 = time.perf_counter()
    venv.reset(seed=0)
    reset_s = time.perf_counter() - t0
    mse = []
    for _ in range(warm):
        mse.append(float(venv.step(actions)[4]["mse"].mean()))
    synchronize()
    t0 = time.perf_counter()
    for _ in range(steps):
        mse.append(float(venv.step(actions)[4]["mse"].mean()))
    synchronize()
    sec = time.perf_counter() - t0
    return {"reset_s": reset_s, "timed_steps": steps, "seconds": sec, "ms_per_step": 1e3 * sec / steps,
            "env_steps_per_s": n * steps / sec, "mse_per_step": mse}


def vector_config(rec: Record, venv: Any, model: Any, row: dict[str, Any], warm: int, steps: int) -> dict[str, Any]:
    """One timed configuration of the vector env; an exception is recorded in the row (the next ones still run)."""
    try:
        use_filter(venv, model, row["filter"], row["uncertainty"])
        row.update(time_vector_env(venv, warm, steps))
    except Exception as exc:  # noqa: BLE001 - a failing configuration is a result
        row["error"] = f"{type(exc).__name__}: {exc}"
        row["traceback"] = traceback.format_exc()[-3000:]
    rec.add(row)
    return row


def shipped_koopman(rec: Record, ds: Any, device: str) -> Any:
    """The shipped lite Koopman model (r = 32) on ``device``, looked up for ``ds`` as a user would; if the data
    generated here do not match its fingerprint, the shipped file is loaded directly (recorded): the cost of a
    step does not depend on the weights."""
    from dks_gym.models import load_model
    from dks_gym.models.checkpoint import model_from_checkpoint
    from dks_gym.models.shipped import WEIGHTS_DIR

    try:
        model = load_model("burgers", "koopman", r=32, preset="lite", dataset=ds, device=device)
        rec.doc["model"] = Path(str(getattr(model, "checkpoint_path", ""))).name
    except Exception as exc:  # noqa: BLE001 - recorded; the timing does not need the fingerprint
        model = model_from_checkpoint(WEIGHTS_DIR / "burgers-koopman-lite-r32-T1.safetensors", device)
        rec.doc["model"] = f"burgers-koopman-lite-r32-T1.safetensors, loaded directly ({type(exc).__name__}: {exc})"
    return model


def step_vector(rec: Record) -> None:
    """Env-steps per second of the vector env, EKF and EnKF, uncertainty off and on, CUDA against the CPU."""
    import torch

    import dks_gym
    from dks_gym.dataset import load_dataset

    dev = device_name()
    ds = load_dataset("burgers", "paper")
    models = {d: shipped_koopman(rec, ds, d) for d in {dev, "cpu"}}
    cores = os.cpu_count() or 1
    small, *larger = [4, 8] if rec.quick else [256, 1024, 4096]
    # (N, device, torch threads) in priority order: CUDA and all CPU cores at the smallest N, the larger N on CUDA,
    # then one CPU thread at the smallest N.
    plan = [(small, dev, 1), (small, "cpu", cores)] + [(n, dev, 1) for n in larger] + [(small, "cpu", 1)]
    envs: dict[int, Any] = {}
    per_env_build = 0.01
    # Seconds per env-step by (device, filter, uncertainty), the slowest seen: the next configuration's time is
    # predicted linearly in N (an upper bound on CUDA, where a larger batch costs less per env).
    per_env: dict[tuple[str, str, bool], float] = {}
    for n, d, threads in plan:
        if n not in envs:
            if not rec.fits(f"building N = {n}", per_env_build * n):
                continue
            t0 = time.perf_counter()
            envs[n] = build_vector_env(models[d], n)
            per_env_build = (time.perf_counter() - t0) / n
            rec.doc.setdefault("build_seconds", {})[str(n)] = per_env_build * n
            print(f"vector env N = {n}: built in {per_env_build * n:.1f} s", flush=True)
        dks_gym.set_threads(threads)
        warm, steps = (1, 2) if rec.quick else (2, 8) if d == "cuda" else (1, 4)
        for kind in ("ekf", "enkf"):
            for uncertainty in (False, True):
                what = f"{kind} N={n} {d} threads={threads} uncertainty={uncertainty}"
                if not rec.fits(what, per_env.get((d, kind, uncertainty), 0.0) * n * (warm + steps + 1)):
                    continue
                row = vector_config(rec, envs[n], models[d], {
                    "filter": kind, "num_envs": n, "device": d, "threads": threads if d == "cpu" else None,
                    "uncertainty": uncertainty}, warm, steps)
                if "error" in row:
                    print(f"  {what}: FAILED {row['error']}", flush=True)
                    continue
                key = (d, kind, uncertainty)
                per_env[key] = max(per_env.get(key, 0.0), row["ms_per_step"] / 1e3 / n)
                print(f"  {what}: {row['env_steps_per_s']:,.0f} env-steps/s ({row['ms_per_step']:.1f} ms/step)",
                      flush=True)
    dks_gym.set_threads(None)
    rec.doc.update(torch=torch.__version__, cpu_cores=cores)
    rec.doc["headline"] = {f"{r['filter']} N={r['num_envs']} {r['device']}"
                           f"{'' if r['threads'] is None else ' x' + str(r['threads'])}"
                           f"{' +unc' if r['uncertainty'] else ''}": round(r["env_steps_per_s"]) if "error" not in r
                           else "failed" for r in rec.doc["rows"]}
    if any("error" in r for r in rec.doc["rows"]):
        raise RuntimeError("some configurations failed (see their rows)")


# 3. lattice Boltzmann ------------------------------------------------------------------------------------
def small_sphere(device: str, compile: bool) -> dict[str, np.ndarray]:
    """The sphere case at r = 2 (two Reynolds numbers, 2 R/U spin-up, 2 frames) with fields."""
    from dks_gym.benchmarks import get_benchmark
    from dks_gym.solvers import sphere_case

    bench = get_benchmark("sphere")
    return sphere_case.simulate([80.0, 900.0], {"resolution": 2, "u_lattice": 0.1, "spin_up": 2.0, "n_frames": 2},
                                coords=bench.coords(), cell_type=bench.cell_type(), device=device, compile=compile)


def lbm_device_check(rec: Record, dev: str) -> None:
    """The small sphere case on the CPU and on ``dev`` (eager): fields and drag side by side."""
    cpu = small_sphere("cpu", False)
    other = small_sphere(dev, False)
    scale = float(np.abs(cpu["fields"]).max())
    rec.doc["device_check"] = {
        "case": "sphere r = 2, Re 80 and 900, 2 R/U + 1 frame, fields on 64^3, eager",
        "max_field_difference_relative": float(np.abs(other["fields"] - cpu["fields"]).max() / scale),
        "drag_cpu": cpu["drag"][:, -1], "drag_device": other["drag"][:, -1]}
    rec.write()
    print(f"LBM {dev} vs cpu: {rec.doc['device_check']}", flush=True)


def run_lbm(shape: tuple[int, ...], batch: int, dev: str, compile: bool, steps: int) -> tuple[dict[str, Any], Any]:
    """One throughput measurement of lbm_throughput's case: warm-up 3 steps (compiling), ``steps`` timed; the
    peak memory above what was allocated before; returns the row and the final populations (on the device)."""
    import torch

    from dks_gym.solvers import lbm

    case = load_script("benchmarks/lbm_throughput.py")._case(shape)
    cuda = dev == "cuda"
    if cuda:
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats()
    base = torch.cuda.memory_allocated() if cuda else 0
    sim = lbm.LBM("D3Q19", shape, np.linspace(1e-3, 1e-2, batch), device=dev, compile=compile, **case)
    t0 = time.perf_counter()
    sim.step(3)
    synchronize()
    warm = time.perf_counter() - t0
    t0 = time.perf_counter()
    sim.step(steps)
    synchronize()
    sec = time.perf_counter() - t0
    n = int(np.prod(shape))
    row = {"shape": list(shape), "batch": batch, "compile": compile, "steps": steps, "seconds": sec,
           "warmup_seconds": warm, "mlups": lbm.mlups(batch, n, steps, sec), "finite": bool(sim.is_finite().all()),
           "bytes_per_case_estimate": lbm.bytes_per_case("D3Q19", shape, compiled=compile)}
    if cuda:
        row["peak_bytes"] = torch.cuda.max_memory_allocated() - base
        row["peak_bytes_per_case"] = row["peak_bytes"] / batch
    return row, sim.f


def step_lbm(rec: Record) -> None:
    """The device check, then eager and compiled throughput on the paper lattice at batch 1, 32, 8."""
    import torch

    from dks_gym.solvers import lbm

    dev = device_name()
    lbm_device_check(rec, dev)
    shape = (57, 18, 16) if rec.quick else PAPER_LATTICE
    batches = [1, 2] if rec.quick else [1, 32, 8]
    steps = 3 if rec.quick else 100
    modes = [False] if rec.quick and dev == "cpu" else [False, True]  # compiling on a CPU takes 30 s a shape
    seconds_per_update: dict[bool, float] = {}
    compile_s = 60.0  # a guess until the first compilation is timed
    for batch in batches:
        finals = {}
        for compile in modes:
            guess = (compile_s if compile else 1.0) + seconds_per_update.get(compile, 0.0) * batch * np.prod(shape) \
                * (steps + 3)
            if not rec.fits(f"batch {batch} compile {compile}", guess):
                continue
            try:
                row, finals[compile] = run_lbm(shape, batch, dev, compile, steps)
            except Exception as exc:  # noqa: BLE001 - a failing mode is a result; the other one still runs
                rec.add({"shape": list(shape), "batch": batch, "compile": compile,
                         "error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()[-3000:]})
                print(f"  batch {batch} compile {compile}: FAILED {exc}", flush=True)
                continue
            seconds_per_update[compile] = row["seconds"] / (batch * np.prod(shape) * steps)
            if compile:
                compile_s = row["warmup_seconds"]
            if len(finals) == 2:  # the same steps from the same state: compiled against eager
                e = finals[False]
                row["compiled_vs_eager_max_relative"] = float((finals[True] - e).abs().max() / e.abs().max())
            rec.add(row)
            print(f"  D3Q19 {'x'.join(map(str, shape))} batch {batch} compile {compile}: {row['mlups']:,.0f} MLUPS"
                  f" (warm-up {row['warmup_seconds']:.1f} s, peak {row.get('peak_bytes_per_case', 0) / 2**30:.2f}"
                  f" GiB per case)", flush=True)
        del finals
    if dev == "cuda":
        per_case = lbm.bytes_per_case("D3Q19", PAPER_LATTICE, compiled=True)
        rec.doc["cuda"] = {"name": torch.cuda.get_device_name(0), "mem_get_info": torch.cuda.mem_get_info(),
                           "max_batch_paper_compiled": lbm.max_batch(per_case, "cuda")}
    rec.doc["headline"] = {f"b{r['batch']}{' compiled' if r['compile'] else ''}":
                           round(r["mlups"]) if "error" not in r else "failed" for r in rec.doc["rows"]}
    if any("error" in r for r in rec.doc["rows"]):
        raise RuntimeError("some measurements failed (see their rows)")


# 4. sphere validation ------------------------------------------------------------------------------------
def force_analysis(t: np.ndarray, c: np.ndarray, window: float, re: float, half_width: float) -> dict[str, Any]:
    """The validation script's numbers for one case's force coefficients ``c`` (n, 3) over the last ``window``
    R/U, plus the Strouhal number from zero crossings and the spectrum's peak-to-median ratio."""
    from dks_gym.benchmarks.sphere import BLOCKAGE
    from dks_gym.solvers.cylinder_case import strouhal as zero_crossing_strouhal

    val = load_script("validation/sphere_validation.py")
    sel = t >= t[-1] - window
    cd = float(c[sel, 0].mean())
    sn = val.schiller_naumann(re)
    cd_corr = cd * (1.0 - BLOCKAGE * (4.0 / half_width) ** 2) ** 2
    lift = c[sel, 1:] - c[sel, 1:].mean(0)
    st, rms = val.strouhal(t[sel], c[sel, 1:])
    principal = lift @ np.linalg.svd(lift, full_matrices=False)[2][0]
    spectrum = np.abs(np.fft.rfft(principal * np.hanning(principal.size)))[1:]
    dt = float(t[1] - t[0])
    return {"Re": re, "Cd": cd, "Cd_blockage_corrected": cd_corr, "Cd_schiller_naumann": sn,
            "Cd_error": cd / sn - 1.0, "Cd_corrected_error": cd_corr / sn - 1.0,
            "Cd_std_window": float(c[sel, 0].std()),
            "lift_rms": rms, "lift_mean_y": float(c[sel, 1].mean()), "lift_mean_z": float(c[sel, 2].mean()),
            "St_spectrum": st, "St_zero_crossings": zero_crossing_strouhal(principal, dt),
            "spectrum_peak_over_median": float(spectrum.max() / np.median(spectrum)),
            "shedding": shedding(t[sel], c[sel, 1:])}


def shedding(t: np.ndarray, lift: np.ndarray, smooth: float = 2.5) -> dict[str, Any]:
    """Strouhal number of a lift series (n, 2: y and z) from the mean period between upward crossings of its
    principal component, linearly detrended (the mean lift drifts while the wake settles) and smoothed by a moving
    mean over ``smooth`` R/U (which removes the lattice's acoustic ripple, St 3-4, that plain crossings count);
    the periods and their coefficient of variation (small for periodic shedding). NaN with fewer than 2 periods."""
    dt = float(t[1] - t[0])
    k = max(1, round(smooth / dt))
    if t.size < k + 3:  # too short a window to say anything
        return {"St": float("nan"), "periods": [], "period_cv": float("nan")}
    centred = lift - lift.mean(0)
    signal = np.convolve(centred @ np.linalg.svd(centred, full_matrices=False)[2][0], np.ones(k) / k, mode="valid")
    ts = t[: signal.size] + (k - 1) * dt / 2
    signal = signal - np.polyval(np.polyfit(ts, signal, 1), ts)
    up = np.flatnonzero((signal[:-1] < 0) & (signal[1:] >= 0))
    periods = np.diff(ts[up] + signal[up] / (signal[up] - signal[up + 1]) * dt)
    if periods.size < 2:
        return {"St": float("nan"), "periods": periods.tolist(), "period_cv": float("nan")}
    return {"St": 2.0 / float(periods.mean()), "periods": periods.tolist(),
            "period_cv": float(periods.std() / periods.mean())}


def reanalyse(path: Path) -> None:
    """Print :func:`shedding` of every case of a sphere_validation.json over its averaging window, from the series
    stored there (every 0.5 R/U)."""
    doc = json.loads(path.read_text())
    print("run | Re | St (smoothed crossings) | periods (R/U) | period CV")
    for row in doc["rows"]:
        t = np.asarray(row["series"]["time"])
        sel = t >= t[-1] - row["average"]
        for case, coef in zip(row["cases"], np.asarray(row["series"]["coefficients"])):
            res = shedding(t[sel], coef[sel, 1:])
            print(f"{row['name']} | {case['Re']:g} | {res['St']:.3f} | {', '.join(f'{p:.1f}' for p in res['periods'])}"
                  f" | {res['period_cv']:.2f}")


def validation_runs(quick: bool) -> list[dict[str, Any]]:
    """The runs in priority order: (name, Re list, settings, simulated time, averaging window)."""
    if quick:
        base = {"resolution": 2, "u_lattice": 0.1, "walls": False}
        return [{"name": "cd_r2", "re": [100.0, 200.0], "settings": base, "time": 2.0, "average": 1.0},
                {"name": "re350_r2", "re": [350.0], "settings": base, "time": 3.0, "average": 2.0}]
    box = {"resolution": 8, "u_lattice": 0.05, "walls": False}
    return [{"name": "cd_r8", "re": [100.0, 200.0], "settings": box, "time": 30.0, "average": 10.0},
            {"name": "re350_r8", "re": [350.0], "settings": box, "time": 150.0, "average": 75.0},
            {"name": "re350_r8_walls", "re": [350.0], "settings": {**box, "walls": True}, "time": 150.0,
             "average": 75.0},
            {"name": "cd_r12", "re": [100.0, 200.0], "settings": {**box, "resolution": 12}, "time": 30.0,
             "average": 10.0}]


def lbm_rates(out: Path) -> dict[str, Any]:
    """From step 3's lbm.json: seconds per lattice update by batch, eager and compiled, and the longest
    compilation; empty when it is missing."""
    path = out / "lbm.json"
    rows = [r for r in json.loads(path.read_text())["rows"] if "error" not in r] if path.exists() else []
    rates: dict[str, Any] = {}
    for compile, key in ((False, "eager"), (True, "compiled")):
        by_batch = {r["batch"]: 1.0 / (r["mlups"] * 1e6) for r in rows if r["compile"] == compile}
        if by_batch:
            rates[key] = by_batch
    compiled = [r["warmup_seconds"] for r in rows if r["compile"]]
    rates["compile_s"] = max(compiled) if compiled else None
    return rates


def rate_for(rates: dict[str, Any], key: str, batch: int) -> float | None:
    """Seconds per lattice update of ``key`` ("eager", "compiled") at the largest measured batch not above
    ``batch`` (the smallest measured one if all are above); None if it was not measured."""
    by_batch = rates.get(key)
    if not by_batch:
        return None
    below = [b for b in by_batch if int(b) <= batch]
    return by_batch[max(below, key=int)] if below else by_batch[min(by_batch, key=int)]


def choose_mode(rates: dict[str, Any], updates: float, batch: int) -> tuple[bool, float | None]:
    """(compile, predicted seconds) for a run of ``updates`` lattice updates over ``batch`` cases: compiled when
    its compilation plus its run is predicted shorter than the eager run."""
    eager, compiled = rate_for(rates, "eager", batch), rate_for(rates, "compiled", batch)
    eager_s = eager * updates if eager else None
    compiled_s = rates["compile_s"] + compiled * updates if compiled else None
    if compiled_s is not None and (eager_s is None or compiled_s < eager_s):
        return True, compiled_s
    return False, eager_s


def step_sphere_validation(rec: Record, out: Path) -> None:
    """Drag at Re 100 and 200 and the Re 350 wake at r = 8 (then r = 12) on the device, forces every 10 lattice
    steps (the validation script's default); eager or compiled, whichever step 3's rates predict shorter."""
    from dks_gym.benchmarks import get_benchmark
    from dks_gym.solvers import sphere_case

    dev = device_name()
    bench = get_benchmark("sphere")
    rates = lbm_rates(out)
    rec.doc["rates_from_lbm"] = rates
    correction = 1.5  # measured / predicted, updated after every run (force sampling, lattice differences)
    for run in validation_runs(rec.quick):
        settings = {**run["settings"], "spin_up": run["time"], "n_frames": 1, "smagorinsky": 0.15}
        described = sphere_case.describe(settings)
        updates = len(run["re"]) * float(np.prod(described["shape"])) * described["steps"]["total"]
        compile, predicted = choose_mode(rates, updates, len(run["re"]))
        if predicted is not None and not rec.fits(run["name"], correction * predicted):
            continue
        t0 = time.perf_counter()
        out_run = sphere_case.simulate(np.array(run["re"]), settings, coords=bench.coords(),
                                       cell_type=bench.cell_type(), device=dev, compile=compile, fields=False,
                                       force_every=10)
        wall = time.perf_counter() - t0
        if predicted:
            correction = max(1.0, wall / predicted)
        t, coef = out_run["force_time"], out_run["force_coefficients"]
        cases = [force_analysis(t, coef[i], run["average"], re, 4.0) for i, re in enumerate(run["re"])]
        every = max(1, int(round(0.5 / float(t[1] - t[0]))))  # the series every 0.5 R/U, for a figure
        rec.add({**run, "device": dev, "compile": compile, "lattice": described["shape"],
                 "steps": described["steps"]["total"], "seconds": wall, "predicted_seconds": predicted,
                 "mlups": updates / wall / 1e6, "cases": cases,
                 "series": {"time": t[::every], "coefficients": coef[:, ::every]}})
        for case in cases:
            print(f"  {run['name']} Re {case['Re']:g}: Cd {case['Cd']:.3f} (corrected {case['Cd_corrected_error']:+.1%}"
                  f" vs Schiller-Naumann), lift rms {case['lift_rms']:.2e}, St {case['St_spectrum']:.3f} /"
                  f" {case['St_zero_crossings']:.3f}, peak/median {case['spectrum_peak_over_median']:.0f}"
                  f" ({wall:.0f} s, compile {compile})", flush=True)
    rec.doc["headline"] = {f"{r['name']} Re {c['Re']:g}": {k: round(c[k], 4) for k in
                                                         ("Cd", "Cd_corrected_error", "lift_rms", "St_spectrum",
                                                          "St_zero_crossings")}
                           for r in rec.doc["rows"] for c in r["cases"]}


# 5. sphere generation ------------------------------------------------------------------------------------
def generation_plan(rec: Record, rates: dict[str, Any], settings: dict[str, Any], per_case: float
                    ) -> tuple[int, dict[str, Any]]:
    """How many cases (8, 4, 2 or 1) fit 80 % of the step's time at the compiled rate of step 3, and the settings
    to run: the preset's, or with spin-up and frames cut in proportion when even one case does not fit."""
    key = "compiled" if rates.get("compiled") else "eager"
    if not rates.get(key):  # no rate measured: two cases, the preset's settings
        return 2, settings
    room = 0.8 * rec.left() - (rates["compile_s"] if key == "compiled" else 0.0)
    for k in (8, 4, 2, 1):
        if k * per_case * rate_for(rates, key, k) < room:
            return k, settings
    scale = max(0.05, room / (per_case * rate_for(rates, key, 1)))
    spin_up = max(5.0, round(2 * settings["spin_up"] * scale) / 2)  # a multiple of 0.5 R/U: whole lattice steps
    return 1, {**settings, "spin_up": spin_up, "n_frames": max(10, round(settings["n_frames"] * scale))}


def step_sphere_generation(rec: Record, out: Path) -> None:
    """A few Reynolds numbers of the paper sweep through the generator's batches (compiled on CUDA), timed;
    the 101-run sweep extrapolated from them and from the compiled throughput of step 3."""
    from dks_gym.benchmarks import get_benchmark
    from dks_gym.benchmarks.base import interleaved_sweep
    from dks_gym.solvers import lbm, sphere_case

    dev = device_name()
    bench = get_benchmark("sphere")
    preset = "small" if rec.quick else "paper"
    settings = sphere_case.generator_settings(preset, {}, bench.dt)
    n_train, n_test = sphere_case.PRESET_COUNTS[preset]
    sweep = np.sort(np.concatenate(interleaved_sweep(*bench.param_range, n_train, n_test, np.random.default_rng(0))))
    described = sphere_case.describe(settings)
    per_case = float(np.prod(described["shape"])) * described["steps"]["total"]  # lattice updates of one run
    rates = lbm_rates(out)
    k, run_settings = generation_plan(rec, rates, settings, per_case)
    k = min(k, sweep.size)
    shortened = run_settings != settings
    run_updates = float(np.prod(described["shape"])) * sphere_case.describe(run_settings)["steps"]["total"]
    chosen = sweep[np.linspace(0, sweep.size - 1, k).round().astype(int)]  # spread over the range, both ends in
    rec.doc.update(preset=preset, settings=settings, run_settings=run_settings, shortened=shortened,
                   lattice=described, sweep_size=int(sweep.size), chosen_re=chosen, rates_from_lbm=rates)
    rec.write()
    # The generator's default (compiled on CUDA), unless step 3 measured no compiled rate (it failed there).
    compile = None if rates.get("compiled") or not rates.get("eager") else False
    rec.doc["compile"] = "default" if compile is None else compile
    info: dict[str, Any] = {}
    t0 = time.perf_counter()
    cases = []
    for part, res in sphere_case.run_batches(chosen, run_settings, coords=bench.coords(), cell_type=bench.cell_type(),
                                             device=dev, compile=compile, fields=True, info=info):
        for j, i in enumerate(range(part.start, part.stop)):
            cases.append({"Re": chosen[i], "fields_finite": bool(np.isfinite(res["fields"][j]).all()),
                          "drag_mean": float(res["drag"][j].mean()), "lift_rms": float(res["lift"][j].std())})
    wall = time.perf_counter() - t0
    compiled = dev == "cuda" and compile is None  # the default compiles on CUDA only
    setup = (rates.get("compile_s") or 0.0) if compiled else 0.0
    per_update = max(wall - setup, 0.1 * wall) / (k * run_updates)  # without the compilation
    frames_bytes = int(settings["n_frames"]) * 4 * 64**3 * 4  # one trajectory's frames on the host
    full = {"cases": int(sweep.size), "lattice_updates": sweep.size * per_case, "compile_seconds_assumed": setup,
            "seconds_at_this_run_rate": setup + sweep.size * per_case * per_update,
            "seconds_at_compiled_rate_batch_32": setup + sweep.size * per_case * rate_for(rates, "compiled", 32)
            if rates.get("compiled") else None,
            "max_batch_device": lbm.max_batch(info["bytes_per_case"], dev),
            "max_batch_host_frames": lbm.max_batch(frames_bytes, "cpu", fraction=0.5)}
    rec.doc.update(seconds=wall, mlups_excluding_compile=1e-6 / per_update, batch_size=info["batch_size"],
                   cases=cases, full_sweep=full)
    rec.doc["headline"] = {"cases": int(chosen.size), "shortened": shortened, "seconds": round(wall, 1),
                           "all_finite": all(c["fields_finite"] for c in cases),
                           "full_sweep_minutes": round(full["seconds_at_this_run_rate"] / 60, 1)}
    rec.write()
    print(f"  sphere {preset}: {chosen.size} cases{' (shortened)' if shortened else ''} in {wall:.0f} s "
          f"({1e-6 / per_update:,.0f} MLUPS without compiling); the {sweep.size}-run sweep about "
          f"{full['seconds_at_this_run_rate'] / 60:.1f} min", flush=True)


# 6. training ---------------------------------------------------------------------------------------------
def evaluate_trained(model: Any, ds: Any) -> dict[str, Any]:
    """One-step error against persistence (train and test), forward and EKF (paper Q and P0) final MSE on the
    test split; a part that fails is recorded as its error and the others still run."""
    import torch

    from dks_gym.assimilation import AssimilationConfig, run_assimilation
    from dks_gym.evaluation.paper import PAPER_FINAL_MSE
    from dks_gym.models import one_step_error

    model = model.eval()
    out: dict[str, Any] = {}

    def attempt(name: str, fn: Callable[[], Any]) -> None:
        try:
            out[name] = fn()
        except Exception as exc:  # noqa: BLE001
            out[name] = {"error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc()[-3000:]}

    for split in ("train", "test"):
        with torch.no_grad():
            attempt(f"one_step_{split}", lambda split=split: one_step_error(model, ds, split, max_pairs=2048))
    for kind in ("forward", "ekf"):
        config = AssimilationConfig().replace(kind=kind, Q="paper", P0="paper")
        attempt(f"{kind}_final_mse", lambda config=config: run_assimilation(model, ds, config,
                                                                            uncertainty=False).final_mse_mean)
        out[f"{kind}_paper"] = PAPER_FINAL_MSE["burgers"][("koopman", kind)]
    return out


def train_timed(rec: Record, ds: Any, dev: str, path: Path, steps: int, batch: int, label: str) -> Any:
    """A fresh paper-preset Burgers Koopman run of ``steps`` Adam steps at ``path``; adds its row (wall time, the
    median time of a step, each step synchronized and the first 10 left out, and the time outside the steps:
    data, set-up, calibration, checkpoint), also when it fails; returns the model."""
    from dks_gym.models import train_model, training_schedule

    stamps: list[float] = []

    def on_step(done: int, terms: Any) -> None:
        synchronize()
        stamps.append(time.perf_counter())

    row: dict[str, Any] = {"run": label, "steps": steps, "batch_size": batch, "device": dev}
    t0 = time.perf_counter()
    try:
        result = train_model("burgers", "koopman", r=32, preset="paper", dataset=ds, seed=0, device=dev, path=path,
                             resume=False, progress=False, on_step=on_step,
                             schedule=training_schedule("burgers", "paper", steps=steps, batch_size=batch))
        row["mean_loss_last_100"] = float(result.losses[-100:, 0].mean())
        return result.model
    except Exception as exc:
        row["error"] = f"{type(exc).__name__}: {exc} (after {len(stamps)} steps)"
        raise
    finally:
        wall = time.perf_counter() - t0
        gaps = np.diff(stamps)[10:] if len(stamps) > 12 else np.diff([t0, *stamps])
        row.update(seconds=wall, steps_done=len(stamps),
                   seconds_per_step=float(np.median(gaps)) if len(gaps) else None)
        if row["seconds_per_step"] is not None:
            row["seconds_outside_steps"] = wall - row["seconds_per_step"] * len(stamps)
        rec.add(row)


def step_training(rec: Record, home: Path) -> None:
    """The paper preset's Burgers Koopman model on the device: a short run to time a step, then a fresh run of
    the most steps the cap leaves (at most 20,000: a checkpoint cannot be resumed with another step count); then
    the errors of what it reached."""
    from dks_gym.dataset import load_dataset

    dev = device_name()
    ds = load_dataset("burgers", "paper")
    batch = 16 if rec.quick else 256
    reserve = 10.0 if rec.quick else 15.0  # the evaluation after training (6 s on an H200)
    train_timed(rec, ds, dev, home / "campaign" / "timing.safetensors", 20 if rec.quick else 200, batch, "timing")
    timing = rec.doc["rows"][-1]
    print(f"  training (timing run): {timing['steps']} steps, {timing['seconds_per_step'] * 1e3:.2f} ms/step, "
          f"{timing['seconds_outside_steps']:.1f} s outside the steps", flush=True)
    affordable = (rec.left() - reserve - 1.5 * timing["seconds_outside_steps"]) / timing["seconds_per_step"]
    steps = int(min(20000, 0.85 * affordable) // 100 * 100) if not rec.quick else 30
    if steps < (10 if rec.quick else 1000):
        rec.skip("the main run", f"{steps} steps would fit, fewer than the paper's 1000")
        return
    model = train_timed(rec, ds, dev, home / "campaign" / "burgers-koopman-paper-r32.safetensors", steps, batch,
                        "main")
    main = rec.doc["rows"][-1]
    print(f"  training: {steps} steps in {main['seconds']:.0f} s ({main['seconds_per_step'] * 1e3:.2f} ms/step)",
          flush=True)
    errors = evaluate_trained(model, ds)
    rec.doc["errors"] = errors
    test = errors["one_step_test"]
    rec.doc["headline"] = {"steps": steps, "ms_per_step": round(1e3 * main["seconds_per_step"], 2),
                           "forward_final_mse": errors["forward_final_mse"], "ekf_final_mse": errors["ekf_final_mse"],
                           "one_step_over_persistence_test": test["model_mse"] / test["persistence_mse"]
                           if "model_mse" in test else test}
    rec.write()
    print(f"  training errors: {errors}", flush=True)
    if any(isinstance(v, dict) and "error" in v for v in errors.values()):
        raise RuntimeError("some evaluations failed (see errors)")


# Driver --------------------------------------------------------------------------------------------------
def run_step(name: str, out: Path, deadline: float, quick: bool, home: Path) -> int:
    """Child mode: run one step, its JSON marked ok or failed (with the traceback)."""
    rec = Record(out, name, deadline, quick)
    start = time.perf_counter()
    steps: dict[str, Callable[[], None]] = {
        "tests": lambda: step_tests(rec), "vector": lambda: step_vector(rec), "lbm": lambda: step_lbm(rec),
        "sphere_validation": lambda: step_sphere_validation(rec, out),
        "sphere_generation": lambda: step_sphere_generation(rec, out), "training": lambda: step_training(rec, home)}
    try:
        steps[name]()
        rec.doc["status"] = "ok"
        code = 0
    except Exception as exc:  # noqa: BLE001 - a failed step is a result: recorded, and the next steps run
        rec.doc.update(status="failed", error=f"{type(exc).__name__}: {exc}", traceback=traceback.format_exc()[-6000:])
        print(traceback.format_exc(), flush=True)
        code = 1
    rec.doc["step_seconds"] = time.perf_counter() - start
    rec.write()
    return code


def machine() -> dict[str, Any]:
    """The host and the GPU, read without creating a CUDA context in this process."""
    import torch

    info: dict[str, Any] = {"python": platform.python_version(), "torch": torch.__version__,
                            "torch_cuda": torch.version.cuda, "cpu_cores": os.cpu_count(),
                            "platform": platform.platform()}
    try:
        info["nvidia_smi"] = subprocess.run(
            ["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"],
            capture_output=True, text=True, timeout=30).stdout.strip()
    except (OSError, subprocess.TimeoutExpired) as exc:
        info["nvidia_smi"] = f"unavailable: {exc}"
    return info


def prepare_data(summary: dict[str, Any]) -> None:
    """The Burgers paper data (the shipped models' data, about 5 s) in the data home."""
    from dks_gym.dataset import generate_dataset

    t0 = time.perf_counter()
    generate_dataset("burgers", "paper", progress=False)
    summary["data_seconds"] = time.perf_counter() - t0


def drive(args: argparse.Namespace) -> int:
    """Parent mode: the steps one after another, each a child process under its cap; summary.json after each."""
    out = args.out
    summary: dict[str, Any] = {"command": "python benchmarks/gpu_campaign.py" + (" --quick" if args.quick else ""),
                               "budget_s": args.budget, "machine": machine(), "steps": {}}
    write_json(out / "summary.json", summary)
    prepare_data(summary)
    start = time.time()  # the budget is the steps'
    names = [s for s in STEPS if s in args.steps]
    total = sum(SHARES[s] for s in names)
    for i, name in enumerate(names):
        used = time.time() - start
        planned = args.budget * sum(SHARES[s] for s in names[: i + 1]) / total  # this step's end, if on time
        cap = args.budget - used if i == len(names) - 1 else planned - used
        if cap < 5:
            summary["steps"][name] = {"status": "not run", "why": f"{cap:.0f} s left for it"}
            write_json(out / "summary.json", summary)
            continue
        print(f"== {name}: cap {cap:.0f} s ({used:.0f} s used of {args.budget:.0f})", flush=True)
        cmd = [sys.executable, str(Path(__file__).resolve()), "--step", name, "--out", str(out),
               "--deadline", str(time.time() + cap), "--home", str(args.home)] + (["--quick"] if args.quick else [])
        t0 = time.time()
        child = subprocess.Popen(cmd, start_new_session=True)
        try:
            rc: int | str = child.wait(timeout=cap + GRACE)
        except subprocess.TimeoutExpired:
            os.killpg(child.pid, signal.SIGKILL)
            child.wait()
            rc = "killed at its cap"
        for tmp in out.glob(".*.tmp"):  # a write cut off by the kill: only the step's last whole JSON counts
            tmp.unlink()
        doc_path = out / f"{name}.json"
        doc = json.loads(doc_path.read_text()) if doc_path.exists() else {}
        summary["steps"][name] = {"status": doc.get("status", "no output") if rc != "killed at its cap" else rc,
                                  "rc": rc, "seconds": time.time() - t0, "cap_s": cap,
                                  "skipped": doc.get("skipped", []), "error": doc.get("error"),
                                  "headline": doc.get("headline", {})}
        write_json(out / "summary.json", summary)
        print(f"== {name}: {summary['steps'][name]['status']} in {time.time() - t0:.0f} s", flush=True)
    summary["seconds"] = time.time() - start
    write_json(out / "summary.json", summary)
    return 0 if all(s.get("status") == "ok" for s in summary["steps"].values()) else 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path(os.environ.get("OUT", "gpu-campaign")),
                        help="folder for the JSON files (default $OUT, else ./gpu-campaign)")
    parser.add_argument("--budget", type=float, default=480.0, help="seconds for all steps together")
    parser.add_argument("--quick", action="store_true", help="tiny sizes: a smoke run, on the CPU too")
    parser.add_argument("--steps", nargs="+", choices=STEPS, default=list(STEPS), help="a subset, in this order")
    parser.add_argument("--home", type=Path, default=None, help="the data home (default: a temporary folder)")
    parser.add_argument("--strouhal", type=Path, default=None,
                        help="instead: the shedding analysis of the series stored in a sphere_validation.json")
    parser.add_argument("--step", choices=STEPS, help=argparse.SUPPRESS)  # child mode
    parser.add_argument("--deadline", type=float, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.strouhal is not None:
        reanalyse(args.strouhal)
        return 0
    args.out.mkdir(parents=True, exist_ok=True)
    if args.home is None:
        args.home = Path(tempfile.mkdtemp(prefix="dks-gpu-campaign-"))
    os.environ["DKS_GYM_HOME"] = str(args.home)
    os.environ["PYTHONUNBUFFERED"] = "1"
    if args.step:
        return run_step(args.step, args.out, args.deadline, args.quick, args.home)
    return drive(args)


if __name__ == "__main__":
    sys.exit(main())
