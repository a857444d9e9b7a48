"""Speed of the filtered environments against their floors, as ratios measured side by side in one process.

Burgers (grid 1024), ``small`` data, the ``lite`` Koopman model with r = 32 (untrained weights: the cost of a
step does not depend on them), 16 sensors, the paper's Q and P0, one torch thread unless ``--threads``. Every
pair of timings alternates rep by rep (A, B, A, B, ...) so that a neighbour's load hits both alike; the JSON
keeps every rep's median and the ratio. Sections:

- ``machine``: platform, torch, threads, the load average before and after, and the float32 matmul peak (a
  1024^3 product) at the start; the FLOP floors divide by the same product timed beside the step they judge;
- ``env``: the bare ``SensingEnv`` against its replay floor (frames in memory plus the same seeded noise);
- ``ekf`` / ``enkf``: one filter step at batch B against its floor (the forecast, the observation and, for the
  EKF, its Jacobian at the sensors, and the Kalman algebra, each timed alone) and, for the EKF, against the FLOP
  floor: (m + 1) decoder passes at one element (the issue's count: one decode and one reverse pass per sensor)
  at the matmul peak; the EKF step also with its diagnostics switched off; for the EnKF, the members' readings
  (from their sensors' windows) against decoding every member's whole field;
- ``jacobian``: the decoder Jacobian at the sensors, sensor-local against autodiff through the whole decoder;
- ``vector``: the batched vector env (``uncertainty=False``, as for RL) at N envs against N separate
  ``LatentFilter`` envs, per env-step, EKF and EnKF (n = 20);
- ``uncertainty``: the same for the EKF with the predictive std and its scores (``uncertainty=True``, the
  envs' default) on both sides, and what the std adds to the vector env's step (``std_over_rest``);
- ``algebra``: the EKF update with a linear model against filterpy's ``KalmanFilter`` at batch 1 and 256;
- ``torchkf``: one linear predict and Joseph-form update (r = 32, m = 16, float32) at B = 256 and 1024 against
  torch-kf (a batched PyTorch Kalman filter, the dev extra), and the time of each of our safety checks;
- ``training``: one Adam step of each neural model of Burgers (lite and paper presets) and of the cylinder
  (lite), before (the formulation and schedule the shipped lite models were trained with) and
  after (today's), on random windows at each schedule's batch size; the step ratio is the median of the
  per-rep ratios (each rep times the two steps next to each other), the training ratio the step ratio times
  the ratio of the schedules' step counts (validation passes, under 5 % of a run, left out), and the after
  step's FLOPs (``torch.utils.flop_counter``) give its rate against the matmul peak; beside them the after
  step with its forward pass under CPU bfloat16 autocast (``bf16_autocast_over_after``: how much faster; an
  alternative measured, not how dks-gym trains).

    OMP_NUM_THREADS=1 python benchmarks/perf.py                  # benchmarks/results/perf.json
    OMP_NUM_THREADS=1 python benchmarks/perf.py --quick --out /tmp/perf.json   # a smoke run (seconds)
    OMP_NUM_THREADS=1 python benchmarks/perf.py --sections enkf vector --filters enkf   # refresh those entries
    OMP_NUM_THREADS=1 python benchmarks/perf.py --sections torchkf   # that section alone, the others kept
    OMP_NUM_THREADS=1 python benchmarks/perf.py --sections uncertainty --sizes 16 256   # one section, merged in
    OMP_NUM_THREADS=1 python benchmarks/perf.py --sections training --reps 7   # the training entry, about 2 min

``--sections`` (and ``--filters`` for the vector section) run only some of it and refresh only their entries of an
existing ``--out`` (the vector section's rows by filter and N); the rest of the file is kept, and each refreshed
section's machine and load are recorded under ``refreshed``.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import time
from pathlib import Path
from typing import Any, Callable

import gymnasium as gym
import numpy as np
import torch
from torch import Tensor

import dks_gym  # noqa: F401  (registers the env ids)
from dks_gym.assimilation import FilterConfig
from dks_gym.atomic import atomic_write_text
from dks_gym.dataset import generate_dataset, load_dataset
from dks_gym.envs.noise import measurement_noise
from dks_gym.filters import EKF, LatentDynamics
from dks_gym.filters.dynamics import GaussianState
from dks_gym.filters.batch_elements import nonfinite_elements
from dks_gym.filters.covariance import as_covariance, cholesky_or_nan, symmetrize
from dks_gym.filters.ekf import ekf_forecast, ekf_update
from dks_gym.filters.enkf import enkf_forecast, enkf_update
from dks_gym.filters.jacobians import forecast_with_jacobian, observe_with_jacobian, value_and_jacobian
from dks_gym.filters.measurements import check_measurement
from dks_gym.models import TrainingSchedule, benchmark_shape, build_model, training_schedule
from dks_gym.models.loss import training_loss
from dks_gym.models.shipped import find_shipped
from dks_gym.models.training import adam, adam_step
from dks_gym.wrappers import LatentFilter, LatentFilterVectorEnv


def median_ms(fn: Callable[[], Any], inner: int) -> float:
    """Median wall time of ``fn`` in ms over ``inner`` calls (one call first, untimed, to warm caches)."""
    fn()
    times = []
    for _ in range(inner):
        tic = time.perf_counter()
        fn()
        times.append(time.perf_counter() - tic)
    return 1e3 * float(np.median(times))


def interleaved(fns: dict[str, Callable[[], Any]], reps: int, inner: int) -> dict[str, list[float]]:
    """Each function's median ms, rep by rep in turn: {name: [rep medians]}."""
    out: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(reps):
        for name, fn in fns.items():
            out[name].append(median_ms(fn, inner))
    return out


def med(values: list[float]) -> float:
    return float(np.median(values))


def machine(threads: int) -> dict[str, Any]:
    return {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count(), "python": platform.python_version(), "torch": torch.__version__,
            "torch_threads": threads, "loadavg_start": list(os.getloadavg()),
            # Whether bfloat16 runs natively (the training section's autocast alternative depends on it).
            "cpu_bf16": {"avx512_bf16": torch.cpu._is_avx512_bf16_supported(),
                         "amx_tile": torch.cpu._is_amx_tile_supported()}}


_A, _B = torch.randn(1024, 1024), torch.randn(1024, 1024)
MATMUL_FLOPS = 2 * 1024**3


def matmul() -> None:
    """The peak's yardstick: a 1024^3 float32 matrix product."""
    _A @ _B


def gflops(flops: float, ms: float) -> float:
    return flops / (ms * 1e-3) / 1e9


def matmul_peak(reps: int) -> dict[str, Any]:
    """float32 GFLOP/s of a 1024^3 matrix product (the best rep: the core's reachable peak)."""
    times = [median_ms(matmul, 3) for _ in range(max(reps, 3))]
    return {"gflops": gflops(MATMUL_FLOPS, min(times)), "ms": times}


def env_section(reps: int, steps: int) -> dict[str, Any]:
    """The bare env's steps per second against its replay floor (resets, which read the trajectory, untimed)."""
    env = SensingEnvFactory()
    env.reset(seed=0, options={"trajectory": 0})
    frames = np.asarray(env.dataset.trajectory("test", 0))[:, env.benchmark.observed_index]
    sensors, sigma, n_cells = env.sensors, env.sigma, env.n_cells
    n = min(steps, len(frames) - 1)

    def bare() -> float:
        env.reset(seed=0, options={"trajectory": 0})
        tic = time.perf_counter()
        for _ in range(n):
            env.step(0)
        return time.perf_counter() - tic

    def floor() -> float:
        tic = time.perf_counter()
        for k in range(1, n + 1):
            (frames[k].ravel()[sensors] + measurement_noise(0, "test", 0, k, sensors, sigma, n_cells)).astype(
                np.float32)
        return time.perf_counter() - tic

    rates: dict[str, list[float]] = {"env": [], "floor": []}
    for _ in range(reps):
        for name, fn in (("env", bare), ("floor", floor)):
            rates[name].append(float(np.median([n / fn() for _ in range(5)])))
    return {"steps": n, "env_steps_per_s": rates["env"], "floor_steps_per_s": rates["floor"],
            "env_over_floor_rate": med(rates["env"]) / med(rates["floor"])}


def SensingEnvFactory() -> gym.Env:  # noqa: N802 - reads like the class it builds
    return gym.make("DKS/Burgers-v0", preset="small").unwrapped


def decoder_flops(model: Any) -> int:
    """FLOPs of one decode of one element (torch's flop counter: matmuls and convolutions)."""
    from torch.utils.flop_counter import FlopCounterMode

    z, mu = torch.zeros(1, model.r), torch.full((1,), 0.5)
    with FlopCounterMode(display=False) as counter, torch.no_grad():
        model.decode(z, mu)
    return int(counter.get_total_flops())


def jacobian_flops(model: Any, m: int) -> int:
    """The FLOP floor of one element's EKF step: one decode for h(z) and one reverse pass per sensor for J,
    counted as (m + 1) decodes."""
    return (m + 1) * decoder_flops(model)


def started_vector_env(model: Any, n: int, kind: str, n_members: int = 20,
                       uncertainty: bool = False) -> LatentFilterVectorEnv:
    config = FilterConfig(kind=kind, Q="paper", P0="paper", n_members=n_members)
    venv = LatentFilterVectorEnv("burgers", n, model=model, config=config, uncertainty=uncertainty, preset="small")
    venv.reset(seed=0)
    return venv


def whole_grid_observe(model: Any, venv: LatentFilterVectorEnv) -> Callable[[torch.Tensor], torch.Tensor]:
    """h(z) of the venv's elements through the whole decode, reading the sensors off the field (``k * B`` rows)."""
    mu = torch.tensor([e.mu for e in venv.envs], dtype=torch.float32)
    sensors = torch.as_tensor(np.stack([e.sensors for e in venv.envs]))
    channel = venv.benchmark.observed_index

    def observe(z: torch.Tensor) -> torch.Tensor:
        k = z.shape[0] // len(mu)
        fields = model.decode(z, mu.repeat_interleave(k)).flatten(2)[:, channel]
        return fields.gather(1, sensors.repeat_interleave(k, dim=0))

    return observe


def ekf_section(model: Any, batch: int, reps: int, inner: int) -> dict[str, Any]:
    """One EKF step at ``batch`` against its floor and the FLOP floor; diagnostics on and off."""
    venv = started_vector_env(model, batch, "ekf")
    readings = torch.as_tensor(np.stack([e._observe() for e in venv.envs]))
    filt: EKF = venv.filter
    dyn = filt.dynamics
    z, P = filt.mean.clone(), filt.cov.clone()
    state = GaussianState(z, P)
    _, J = observe_with_jacobian(dyn, z)
    h0 = dyn.observe(z)
    F = dyn.forecast_jacobian
    linear = LatentDynamics(lambda x: x, lambda x: h0, forecast_jacobian=F, observe_jacobian=J)
    sigma2 = torch.tensor([e.sigma for e in venv.envs]) ** 2

    def step(diagnostics: bool) -> Callable[[], Any]:
        def run() -> None:
            filt.record_diagnostics = diagnostics
            filt.state = GaussianState(z, P)
            filt.step(readings)
        return run

    def algebra() -> None:
        new, _ = ekf_forecast(state, linear, 1e-4, check=False)
        ekf_update(new, readings, linear, sigma2, check=False)

    times = interleaved({"step": step(True), "step_no_diagnostics": step(False),
                         "forecast": lambda: forecast_with_jacobian(dyn, z),
                         "observe_and_jacobian": lambda: observe_with_jacobian(dyn, z),
                         "algebra": algebra, "matmul": matmul}, reps, inner)
    filt.record_diagnostics = True
    peak = gflops(MATMUL_FLOPS, med(times["matmul"]))  # measured beside the step, under the same load
    floor = [f + o + a for f, o, a in zip(times["forecast"], times["observe_and_jacobian"], times["algebra"])]
    flop_floor_ms = jacobian_flops(model, readings.shape[1]) * batch / (peak * 1e9) * 1e3
    return {"batch": batch, "ms": times, "floor_ms": floor, "matmul_gflops": peak, "flop_floor_ms": flop_floor_ms,
            "step_over_floor": med(times["step"]) / med(floor),
            "step_over_flop_floor": med(times["step"]) / flop_floor_ms,
            "diagnostics_on_over_off": med(times["step"]) / med(times["step_no_diagnostics"])}


def enkf_section(model: Any, batch: int, n_members: int, reps: int, inner: int) -> dict[str, Any]:
    """One EnKF step at ``batch`` against its floor (forecast, observation of every member, analysis)."""
    venv = started_vector_env(model, batch, "enkf", n_members)
    readings = torch.as_tensor(np.stack([e._observe() for e in venv.envs]))
    filt = venv.filter
    dyn = filt.dynamics
    E = filt.ensemble.clone()
    predicted = dyn.observe(E.reshape(-1, E.shape[-1])).reshape(E.shape[0], E.shape[1], -1)
    linear = LatentDynamics(lambda x: x, lambda x: predicted.reshape(x.shape[0], -1))
    R = torch.tensor([e.sigma for e in venv.envs]) ** 2

    def step() -> None:
        filt.ensemble = E
        filt.step(readings)

    def algebra() -> None:
        forecast = enkf_forecast(E, linear, 1e-4, filt.generator, check=False)
        enkf_update(forecast, readings, linear, R, filt.generator, check=False)

    flat = E.reshape(-1, E.shape[-1])

    def forecast() -> None:
        with torch.no_grad():  # as the filter calls it
            dyn.forecast(flat)

    def observe() -> None:
        with torch.no_grad():
            dyn.observe(flat)

    whole = whole_grid_observe(model, venv)

    def observe_whole_grid() -> None:  # every member's whole field decoded, the sensors read off it
        with torch.no_grad():
            whole(flat)

    single = started_vector_env(model, 1, "enkf", n_members).filter  # what each of B separate envs decodes

    def observe_one_env() -> None:
        with torch.no_grad():
            single.dynamics.observe(single.ensemble.reshape(n_members, -1))

    with torch.no_grad():
        error = float((dyn.observe(flat) - whole(flat)).abs().max() / whole(flat).abs().max())
    times = interleaved({"step": step, "forecast": forecast, "observe": observe, "algebra": algebra,
                         "observe_one_env": observe_one_env, "observe_whole_grid": observe_whole_grid}, reps, inner)
    floor = [f + o + a for f, o, a in zip(times["forecast"], times["observe"], times["algebra"])]
    return {"batch": batch, "n_members": n_members, "ms": times, "floor_ms": floor,
            "step_over_floor": med(times["step"]) / med(floor),
            # The members' readings from their sensors' windows against decoding every member's whole field.
            "observe_speedup_over_whole_grid": med(times["observe_whole_grid"]) / med(times["observe"]),
            "observe_max_relative_difference": error,
            # How much one decode of all B * n members saves over B decodes of n: the most batching can give.
            "observe_batching_gain": batch * med(times["observe_one_env"]) / med(times["observe"])}


def jacobian_section(model: Any, batch: int, reps: int, inner: int) -> dict[str, Any]:
    """The decoder Jacobian at 16 sensors: the model's sensor-local one against autodiff through the decoder."""
    venv = started_vector_env(model, batch, "ekf")
    dyn = venv.filter.dynamics
    z = venv.filter.mean.clone()
    local = lambda: observe_with_jacobian(dyn, z)  # noqa: E731
    full = lambda: value_and_jacobian(whole_grid_observe(model, venv), z)  # noqa: E731
    error = float((local()[1] - full()[1]).abs().max() / full()[1].abs().max())
    times = interleaved({"sensor_local": local, "autodiff_full_decoder": full}, reps, inner)
    return {"batch": batch, "ms": times, "speedup": med(times["autodiff_full_decoder"]) / med(times["sensor_local"]),
            "max_relative_difference": error}


def vector_section(model: Any, sizes: list[int], kind: str, reps: int, steps: int) -> list[dict[str, Any]]:
    """Per env-step ms of the vector env at each N against one ``LatentFilter`` (N separate envs cost N times it)."""
    config = FilterConfig(kind=kind, Q="paper", P0="paper")
    single = LatentFilter(gym.make("DKS/Burgers-v0", preset="small"), model=model, config=config, uncertainty=False)
    single.reset(seed=0)
    last = single.unwrapped.dataset.n_frames - 1  # steps per episode: resets are not env-steps, so stay inside one
    rows = []
    state = {"single": 0}
    for n in sizes:
        venv = started_vector_env(model, n, kind)
        actions = np.zeros(n, dtype=np.int64)
        state["vector"] = 0

        def run_single() -> None:
            if state["single"] >= last:
                single.reset(seed=0)
                state["single"] = 0
            single.step(0)
            state["single"] += 1

        def run_vector() -> None:
            if state["vector"] >= last - 1:  # the vector env restarts the batch inside its last step
                venv.reset(seed=0)
                state["vector"] = 0
            venv.step(actions)
            state["vector"] += 1

        times = interleaved({"separate": run_single, "vector": run_vector, "matmul": matmul}, reps, steps)
        per_env = [t / n for t in times["vector"]]
        row = {"filter": kind, "num_envs": n, "separate_ms_per_env_step": times["separate"],
               "vector_ms_per_env_step": per_env, "speedup": med(times["separate"]) / med(per_env)}
        if kind == "ekf":  # the Jacobian's FLOPs per env-step at the matmul rate measured beside it
            peak = gflops(MATMUL_FLOPS, med(times["matmul"]))
            row["flop_floor_ms_per_env_step"] = jacobian_flops(model, venv.envs[0].n_sensors) / (peak * 1e9) * 1e3
            row["over_flop_floor"] = med(per_env) / row["flop_floor_ms_per_env_step"]
        rows.append(row)
        venv.close()
    return rows


def episode_stepper(env: Any, actions: Any) -> Callable[[], None]:
    """One env step per call, restarting the episode before its last step (resets are not env-steps; the
    vector env restarts the batch inside its last step)."""
    last = (env.envs[0] if hasattr(env, "envs") else env.unwrapped).dataset.n_frames - 2
    state = {"k": 0}

    def run() -> None:
        if state["k"] >= last:
            env.reset(seed=0)
            state["k"] = 0
        env.step(actions)
        state["k"] += 1

    env.reset(seed=0)
    return run


def uncertainty_section(model: Any, sizes: list[int], reps: int, steps: int) -> list[dict[str, Any]]:
    """The EKF with the predictive std (``uncertainty=True``, the envs' default) and without, per env-step: N
    separate ``LatentFilter`` envs (one, N times) and the vector env, all four interleaved rep by rep. The
    speedup compares like with like (the std on both sides); ``std_over_rest`` is what the std and its scores
    add to the vector env's step over the step without them."""
    config = FilterConfig(kind="ekf", Q="paper", P0="paper")
    singles = {unc: LatentFilter(gym.make("DKS/Burgers-v0", preset="small"), model=model, config=config,
                                 uncertainty=unc) for unc in (True, False)}
    rows = []
    for n in sizes:
        actions = np.zeros(n, dtype=np.int64)
        venvs = {unc: started_vector_env(model, n, "ekf", uncertainty=unc) for unc in (True, False)}
        fns = {f"{kind}_{'on' if unc else 'off'}": episode_stepper(env, 0 if kind == "separate" else actions)
               for kind, envs in (("separate", singles), ("vector", venvs)) for unc, env in envs.items()}
        times = interleaved(fns, reps, steps)
        per_env = {name: [t / n for t in ts] if name.startswith("vector") else ts for name, ts in times.items()}
        rows.append({"filter": "ekf", "num_envs": n, "ms_per_env_step": per_env,
                     "speedup_on": med(per_env["separate_on"]) / med(per_env["vector_on"]),
                     "speedup_off": med(per_env["separate_off"]) / med(per_env["vector_off"]),
                     "std_over_rest": med(per_env["vector_on"]) / med(per_env["vector_off"]) - 1.0})
        for env in venvs.values():
            env.close()
    return rows


def algebra_section(reps: int, inner: int) -> list[dict[str, Any]]:
    """The EKF update of a linear-Gaussian model (r = 32, m = 16): ours batched against filterpy in a loop."""
    from filterpy.kalman import KalmanFilter

    rng = np.random.default_rng(0)
    r, m = 32, 16
    F = np.linalg.qr(rng.standard_normal((r, r)))[0] * 0.99
    H = rng.standard_normal((m, r))
    rows = []
    for batch in (1, 256):
        y = rng.standard_normal((batch, m))
        kfs = []
        for _ in range(batch):
            kf = KalmanFilter(dim_x=r, dim_z=m)
            kf.F, kf.H, kf.Q, kf.R, kf.P = F, H, 1e-4 * np.eye(r), 0.04 * np.eye(m), np.eye(r)
            kfs.append(kf)
        dyn = LatentDynamics(lambda x: x @ torch.as_tensor(F, dtype=torch.float32).T,
                             lambda x: x @ torch.as_tensor(H, dtype=torch.float32).T,
                             forecast_jacobian=torch.as_tensor(F, dtype=torch.float32),
                             observe_jacobian=torch.as_tensor(H, dtype=torch.float32))
        state = GaussianState(torch.zeros(batch, r), torch.eye(r).expand(batch, r, r).clone())
        yt = torch.as_tensor(y, dtype=torch.float32)

        def ours() -> None:
            new, _ = ekf_forecast(state, dyn, 1e-4, check=False)
            ekf_update(new, yt, dyn, 0.04, check=False)

        def filterpy() -> None:
            for kf, yi in zip(kfs, y):
                kf.x, kf.P = np.zeros((r, 1)), np.eye(r)
                kf.predict()
                kf.update(yi)

        times = interleaved({"ours": ours, "filterpy": filterpy}, reps, inner)
        rows.append({"batch": batch, "ms": times, "filterpy_over_ours": med(times["filterpy"]) / med(times["ours"])})
    return rows


def check_pieces(state: GaussianState, dyn: LatentDynamics, y: Tensor, Q: float, R: float) -> dict[str, Callable]:
    """Our safety checks and chosen forms alone, on one step's own tensors: the three symmetrizations (P_f, S,
    P_a), the two divergence checks, the measurement check, the Joseph form and its cheaper alternative
    ``P_f - K J P_f``, the gain from the Cholesky factor with its failure flags and torch-kf's LU inverse; and
    the forms these replaced: the gain by ``cholesky_solve``, the divergence checks by ``isfinite`` on every
    entry."""
    from dks_gym.filters.ekf import joseph_covariance, kalman_gain  # ImportError in a tree from before them

    batch, m = state.mean.shape[0], y.shape[1]
    forecast, _ = ekf_forecast(state, dyn, Q)
    z_f, P_f = forecast.mean, forecast.cov
    _, J = observe_with_jacobian(dyn, z_f)
    R_mat = as_covariance(R, batch, m, like=z_f, name="R")
    K, _ = kalman_gain(P_f, J, R_mat)
    PJt = P_f @ J.mT
    S = torch.baddbmm(R_mat, J, PJt)  # before its symmetrization
    analysis, _ = ekf_update(forecast, y, dyn, R)

    def symmetrizations() -> None:
        symmetrize(P_f), symmetrize(S), symmetrize(analysis.cov)

    def gain_lu_inverse() -> Tensor:  # torch-kf's gain: S inverted by LU, no symmetrization, no failure flag
        PJt = P_f @ J.mT
        return PJt @ torch.linalg.inv(torch.baddbmm(R_mat, J, PJt))

    def gain_cholesky_solve() -> Tensor:  # the gain before: a Cholesky solve for the r right-hand sides
        PJt = P_f @ J.mT
        return torch.cholesky_solve(PJt.mT, cholesky_or_nan(symmetrize(torch.baddbmm(R_mat, J, PJt)))[0]).mT

    def isfinite_every_entry() -> None:  # the divergence checks before
        for t in (z_f, P_f, analysis.mean, analysis.cov):
            ~torch.isfinite(t).flatten(1).all(1)

    return {
        "symmetrizations": symmetrizations,
        "divergence_checks": lambda: (nonfinite_elements(z_f, P_f), nonfinite_elements(analysis.mean, analysis.cov)),
        "measurement_check": lambda: check_measurement(y, batch, m, like=z_f),
        "joseph_covariance": lambda: joseph_covariance(P_f, K, J, R_mat, diagonal_R=True),
        "simple_covariance": lambda: torch.baddbmm(P_f, K, PJt.mT, alpha=-1.0),
        "gain_cholesky_flagged": lambda: kalman_gain(P_f, J, R_mat),
        "gain_lu_inverse": gain_lu_inverse,
        "gain_cholesky_solve": gain_cholesky_solve,
        "divergence_checks_isfinite_every_entry": isfinite_every_entry,
    }


def check_costs(times: dict[str, list[float]]) -> dict[str, float]:
    """Each check's ms (median): a piece's time, or a chosen form's time over the cheaper form's."""
    if "symmetrizations" not in times:
        return {}
    return {"symmetrizations": med(times["symmetrizations"]), "divergence_checks": med(times["divergence_checks"]),
            "measurement_check": med(times["measurement_check"]),
            "joseph_over_simple_form": med(times["joseph_covariance"]) - med(times["simple_covariance"]),
            "cholesky_gain_over_lu_inverse": med(times["gain_cholesky_flagged"]) - med(times["gain_lu_inverse"])}


def page_faults_per_call(fn: Callable[[], Any], calls: int = 20) -> float:
    """Minor page faults per call of ``fn``: memory the allocator gave back to the OS and maps again."""
    import resource

    fn()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(calls):
        fn()
    return (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / calls


def torchkf_section(batches: list[int], reps: int, inner: int) -> dict[str, Any]:
    """A linear predict and Joseph-form update (r = 32, m = 16, float32, constant F and H, Q = 1e-4 I, R = 0.04 I):
    ours (``ekf_forecast`` + ``ekf_update``, every check on, and with the divergence checks off) against torch-kf's
    ``KalmanFilter(joseph_update=True)``, and beside them :func:`check_pieces`. Run against a tree from before
    ``kalman_gain`` and ``joseph_covariance`` existed, it times the steps alone."""
    try:
        import torch_kf
    except ImportError:
        return {"skipped": "torch-kf is not installed; it is in the dev extra: pip install -e '.[dev]'"}
    from importlib.metadata import version

    rng = np.random.default_rng(0)
    r, m, Q, R = 32, 16, 1e-4, 0.04
    F = torch.as_tensor(np.linalg.qr(rng.standard_normal((r, r)))[0] * 0.99, dtype=torch.float32)
    H = torch.as_tensor(rng.standard_normal((m, r)), dtype=torch.float32)
    dyn = LatentDynamics(lambda x: x @ F.T, lambda x: x @ H.T, forecast_jacobian=F, observe_jacobian=H)
    kf = torch_kf.KalmanFilter(F, H, Q * torch.eye(r), R * torch.eye(m), joseph_update=True)
    rows = []
    loadavg_start = list(os.getloadavg())
    for batch in batches:
        A = torch.as_tensor(rng.standard_normal((batch, r, r)), dtype=torch.float32)
        z = torch.as_tensor(rng.standard_normal((batch, r)), dtype=torch.float32)
        y = torch.as_tensor(rng.standard_normal((batch, m)), dtype=torch.float32)
        state = GaussianState(z, A @ A.mT / r + 0.1 * torch.eye(r))
        theirs_state = torch_kf.GaussianState(z[..., None], state.cov)

        def ours(check: bool = True) -> GaussianState:
            forecast, _ = ekf_forecast(state, dyn, Q, check=check)
            return ekf_update(forecast, y, dyn, R, check=check)[0]

        def theirs() -> Any:
            return kf.update(kf.predict(theirs_state), y[..., None])

        try:
            pieces = check_pieces(state, dyn, y, Q, R)
        except ImportError:
            pieces = {}
        times = interleaved({"ours": ours, "ours_without_divergence_checks": lambda: ours(False), "torchkf": theirs,
                             **pieces}, reps, inner)
        faults = {"ours": page_faults_per_call(ours), "torchkf": page_faults_per_call(theirs)}
        analysis, ref = ours(), theirs()
        torchkf_ms = med(times["torchkf"])
        costs = check_costs(times)
        rows.append({
            "batch": batch, "ms": times,
            "ours_over_torchkf": med(times["ours"]) / torchkf_ms,
            "ours_over_torchkf_per_rep": [a / b for a, b in zip(times["ours"], times["torchkf"])],
            "unchecked_over_torchkf": med(times["ours_without_divergence_checks"]) / torchkf_ms,
            "minor_page_faults_per_call": faults,
            "check_ms": costs, "check_fraction_of_torchkf": {k: v / torchkf_ms for k, v in costs.items()},
            "max_relative_difference": {
                "mean": float((analysis.mean - ref.mean[..., 0]).abs().max() / ref.mean.abs().max()),
                "cov": float((analysis.cov - ref.covariance).abs().max() / ref.covariance.abs().max())},
        })
    malloc = {k: os.environ.get(k) for k in ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")}
    return {"torch_kf": version("torch-kf"), "torch_threads": torch.get_num_threads(), "glibc_malloc_env": malloc,
            "rows": rows,
            "loadavg_start": loadavg_start, "loadavg_end": list(os.getloadavg())}

# (benchmark, preset) of the training section, each with the three neural kinds.
TRAINING_CONFIGS = (("burgers", "lite"), ("cylinder", "lite"), ("burgers", "paper"))


def before_formulation(model: Any) -> None:
    """Switch ``model`` to the training formulation the shipped lite models were trained with: the encoder's
    convolutions as torch's layers run them (not in channels-last layout), torch's ConvTranspose on the whole
    batch in the decoder in training mode (out of it, the plain-convolution formulation, as then) and, for the
    Koopman map, float64 ``matrix_exp`` (the map kept out of training mode, the only thing its mode switches).
    Their optimizer was Adam's plain loop."""
    encoder, decoder = model.encoder.backbone, model.decoder
    encoder.forward = lambda x: encoder.fc(encoder.conv(x).flatten(1))
    convolve = decoder.convolve
    decoder.convolve = lambda h, *rest: decoder.reference_convolve(h) if decoder.training else convolve(h, *rest)
    if model.kind == "koopman":
        model.latent_map.train = lambda mode=True: torch.nn.Module.train(model.latent_map, False)


def schedules(benchmark: str, preset: str, kind: str) -> tuple[Any, Any]:
    """The resolved schedule a model was trained with before (a lite model: the shipped one's) and now."""
    now = training_schedule(benchmark, preset)
    shipped = find_shipped(benchmark, kind) if preset == "lite" else None
    if shipped is None:
        return now, now
    meta = shipped.metadata
    n_traj, n_t = meta["data"]["train_shape"][:2]
    windows = (n_traj - len(meta["validation_trajectories"])) * (n_t - meta["T"])
    return TrainingSchedule(**meta["schedule"]), now.resolve(windows)


def training_step(benchmark: str, preset: str, kind: str, schedule: TrainingSchedule,
                  before: bool, bf16: bool = False) -> Callable[[], None]:
    """One Adam step of a fresh model on a fixed batch of random windows at ``schedule``'s batch size (its
    gradients clipped as it says), as ``fit_steps`` takes it; mu from 45 values, about as many distinct
    ones per batch as the training split gives. ``bf16``: the forward pass under CPU bfloat16 autocast (timed
    as an alternative; dks-gym trains in float32)."""
    batch = schedule.batch_size
    shape = benchmark_shape(benchmark)
    gen = torch.Generator().manual_seed(0)
    cell_type = torch.randint(0, 3, shape.grid, generator=gen).numpy() if shape.has_cell_type else None
    model = build_model(benchmark, kind, 32, preset, seed=0, cell_type=cell_type)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-4) if before else adam(model, 1e-4)
    if before:
        before_formulation(model)
    low, high = shape.param_range
    x = torch.randn(batch, 2, shape.n_fields, *shape.grid, generator=gen)
    mu = (low + (high - low) * torch.rand(45, generator=gen, dtype=torch.float64))[torch.randint(45, (batch,),
                                                                                                  generator=gen)]

    def step() -> None:
        model.train()
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            loss, _ = training_loss(model, x, mu)
        adam_step(model, optimizer, loss, schedule.clip_norm)  # before: the shipped file's schedule, unclipped

    return step


def training_section(configs: tuple[tuple[str, str], ...], kinds: list[str], reps: int,
                     inner: int) -> list[dict[str, Any]]:
    """Per model: one Adam step before and after (interleaved), and the run's wall time estimated from them and
    the schedules' step counts; the after step's FLOP rate against the matmul peak."""
    from torch.utils.flop_counter import FlopCounterMode

    rows = []
    for benchmark, preset in configs:
        for kind in kinds:
            old, new = schedules(benchmark, preset, kind)
            before = training_step(benchmark, preset, kind, old, before=True)
            after = training_step(benchmark, preset, kind, new, before=False)
            after_bf16 = training_step(benchmark, preset, kind, new, before=False, bf16=True)
            with FlopCounterMode(display=False) as counter:
                after()
            flops = int(counter.get_total_flops())
            times = interleaved({"before": before, "after": after, "after_bf16": after_bf16, "matmul": matmul},
                                reps, inner)
            peak = gflops(MATMUL_FLOPS, med(times.pop("matmul")))  # beside the steps, under the same load
            # Each rep's two steps ran next to each other: the median of the per-rep ratios cancels most of a
            # neighbour's load, which moves single timings by 2x on a shared machine.
            step_ratio = med([b / a for b, a in zip(times["before"], times["after"])])
            wall = {"before_s": old.steps * med(times["before"]) / 1e3,
                    "after_s": new.steps * med(times["after"]) / 1e3}  # at the medians of the timings
            bf16_ratio = med([a / b for a, b in zip(times["after"], times["after_bf16"])])
            rows.append({"benchmark": benchmark, "preset": preset, "model": kind, "ms": times, "step_ratio": step_ratio,
                         "bf16_autocast_over_after": bf16_ratio,
                         "schedule_before": old.record(), "schedule_after": new.record(),
                         "steps_before": old.steps, "steps_after": new.steps, "training_s_estimate": wall,
                         "training_ratio": step_ratio * old.steps / new.steps, "flops_after": flops,
                         "matmul_gflops": peak, "fraction_of_peak_after": gflops(flops, med(times["after"])) / peak})
    return rows


SECTIONS = ("env", "jacobian", "ekf", "enkf", "algebra", "torchkf", "vector", "uncertainty", "training")


def refreshed(previous: dict[str, Any], run: dict[str, Any], names: list[str]) -> dict[str, Any]:
    """``previous`` results with the sections ``names`` of a partial ``run`` in place of theirs (the vector
    section's rows matched by filter and N) and the run's machine and load under ``refreshed``."""
    out = dict(previous)
    for name in names:
        if name == "vector":
            fresh = {(row["filter"], row["num_envs"]) for row in run[name]}
            kept = [row for row in previous.get(name, []) if (row["filter"], row["num_envs"]) not in fresh]
            out[name] = sorted(kept + run[name], key=lambda row: (row["filter"] != "ekf", row["num_envs"]))
        else:
            out[name] = run[name]
    out["refreshed"] = {**previous.get("refreshed", {}), **{name: run["machine"] for name in names}}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reps", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--sizes", nargs="+", type=int, default=[1, 16, 64, 256])
    parser.add_argument("--quick", action="store_true", help="tiny sizes, one rep: checks that every section runs")
    parser.add_argument("--sections", nargs="+", choices=SECTIONS, default=list(SECTIONS),
                        help="run only these sections and refresh only their entries of --out")
    parser.add_argument("--filters", nargs="+", choices=("ekf", "enkf"), default=["ekf", "enkf"],
                        help="the vector section's filters")
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "perf.json"))
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    reps, inner, batch, sizes, steps = args.reps, 10, 256, args.sizes, 20
    configs, kinds, kf_batches = TRAINING_CONFIGS, ["koopman", "mlp", "xlstm"], [256, 1024]
    if args.quick:
        reps, inner, batch, sizes, steps, kf_batches = 1, 1, 4, [1, 4], 2, [4, 16]
        configs, kinds = TRAINING_CONFIGS[:1], ["koopman"]

    @functools.cache
    def data() -> tuple[Any, Any]:
        """The small Burgers data and the untrained lite Koopman model (built once, for the sections using them)."""
        generate_dataset("burgers", "small", progress=False)
        ds = load_dataset("burgers", "small")
        return ds, build_model("burgers", "koopman", 32, "lite", dataset=ds, seed=0)

    sections = {
        "env": lambda: env_section(reps, 99 if not args.quick else 5),
        "jacobian": lambda: jacobian_section(data()[1], batch, reps, inner),
        "ekf": lambda: ekf_section(data()[1], batch, reps, inner),
        "enkf": lambda: enkf_section(data()[1], batch, 20, reps, inner),
        "algebra": lambda: algebra_section(reps, inner),
        # Small and quick: five times the reps of a third the calls, each pair close in time, for ratios near 1.
        "torchkf": lambda: torchkf_section(kf_batches, 5 * reps, max(inner // 3, 1)),
        "vector": lambda: [row for kind in args.filters
                           for row in vector_section(data()[1], sizes, kind, reps, steps)],
        "uncertainty": lambda: uncertainty_section(data()[1], sizes, reps, steps),
        "training": lambda: training_section(configs, kinds, reps, 1 if args.quick else 3),
    }
    result: dict[str, Any] = {"machine": machine(args.threads)}
    result["machine"]["matmul_gflops"] = matmul_peak(reps)["gflops"]
    for name in args.sections:
        tic = time.perf_counter()
        result[name] = sections[name]()
        print(f"{name}: {time.perf_counter() - tic:.1f} s", flush=True)
    result["machine"]["loadavg_end"] = list(os.getloadavg())
    out = Path(args.out)
    if (len(args.sections) < len(SECTIONS) or len(args.filters) < 2) and out.exists():
        result = refreshed(json.loads(out.read_text()), result, args.sections)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, json.dumps(result, indent=1) + "\n")
    print(f"wrote {out}")

if __name__ == "__main__":
    main()
