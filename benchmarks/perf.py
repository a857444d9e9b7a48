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
  at the matmul peak; the EKF step also with its diagnostics switched off;
- ``jacobian``: the decoder Jacobian at the sensors, sensor-local against autodiff through the whole decoder;
- ``vector``: the batched vector env (``uncertainty=False``, as for RL) at N envs against N separate
  ``LatentFilter`` envs, per env-step, EKF and EnKF (n = 20);
- ``algebra``: the EKF update with a linear model against filterpy's ``KalmanFilter`` at batch 1 and 256;
- ``training``: one Adam step of each neural model of Burgers (lite and paper presets) and of the cylinder
  (lite), before (the formulation and schedule the shipped lite models were trained with) and
  after (today's), on random windows at each schedule's batch size; the step ratio is the median of the
  per-rep ratios (each rep times the two steps next to each other), the training ratio the step ratio times
  the ratio of the schedules' step counts (validation passes, under 5 % of a run, left out), and the after
  step's FLOPs (``torch.utils.flop_counter``) give its rate against the matmul peak.

    OMP_NUM_THREADS=1 python benchmarks/perf.py                  # benchmarks/results/perf.json
    OMP_NUM_THREADS=1 python benchmarks/perf.py --quick --out /tmp/perf.json   # a smoke run (seconds)
    OMP_NUM_THREADS=1 python benchmarks/perf.py --only training   # rerun one section, keep the others
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path
from typing import Any, Callable

import gymnasium as gym
import numpy as np
import torch

import dks_gym  # noqa: F401  (registers the env ids)
from dks_gym.assimilation import FilterConfig
from dks_gym.atomic import atomic_write_text
from dks_gym.dataset import generate_dataset, load_dataset
from dks_gym.envs.noise import measurement_noise
from dks_gym.filters import EKF, LatentDynamics
from dks_gym.filters.dynamics import GaussianState
from dks_gym.filters.ekf import ekf_forecast, ekf_update
from dks_gym.filters.enkf import enkf_forecast, enkf_update
from dks_gym.filters.jacobians import forecast_with_jacobian, observe_with_jacobian, value_and_jacobian
from dks_gym.models import TrainingSchedule, benchmark_shape, build_model, training_schedule
from dks_gym.models.loss import training_loss
from dks_gym.models.shipped import find_shipped
from dks_gym.models.training import adam
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
            "torch_threads": threads, "loadavg_start": list(os.getloadavg())}


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


def started_vector_env(model: Any, n: int, kind: str, n_members: int = 20) -> LatentFilterVectorEnv:
    config = FilterConfig(kind=kind, Q="paper", P0="paper", n_members=n_members)
    venv = LatentFilterVectorEnv("burgers", n, model=model, config=config, uncertainty=False, preset="small")
    venv.reset(seed=0)
    return venv


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

    single = started_vector_env(model, 1, "enkf", n_members).filter  # what each of B separate envs decodes

    def observe_one_env() -> None:
        with torch.no_grad():
            single.dynamics.observe(single.ensemble.reshape(n_members, -1))

    times = interleaved({"step": step, "forecast": forecast, "observe": observe, "algebra": algebra,
                         "observe_one_env": observe_one_env}, reps, inner)
    floor = [f + o + a for f, o, a in zip(times["forecast"], times["observe"], times["algebra"])]
    return {"batch": batch, "n_members": n_members, "ms": times, "floor_ms": floor,
            "step_over_floor": med(times["step"]) / med(floor),
            # How much one decode of all B * n members saves over B decodes of n: the most batching can give.
            "observe_batching_gain": batch * med(times["observe_one_env"]) / med(times["observe"])}


def jacobian_section(model: Any, batch: int, reps: int, inner: int) -> dict[str, Any]:
    """The decoder Jacobian at 16 sensors: the model's sensor-local one against autodiff through the decoder."""
    venv = started_vector_env(model, batch, "ekf")
    dyn = venv.filter.dynamics
    z = venv.filter.mean.clone()
    local = lambda: observe_with_jacobian(dyn, z)  # noqa: E731
    full = lambda: value_and_jacobian(dyn.observe, z)  # noqa: E731
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
    decoder.convolve = lambda h: decoder.reference_convolve(h) if decoder.training else convolve(h)
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


def training_step(benchmark: str, preset: str, kind: str, batch: int, before: bool) -> Callable[[], None]:
    """One Adam step of a fresh model on a fixed batch of random windows, as ``fit_steps`` takes it; mu from 45
    values, about as many distinct ones per batch as the training split gives."""
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
        loss, _ = training_loss(model, x, mu)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()

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
            before = training_step(benchmark, preset, kind, old.batch_size, before=True)
            after = training_step(benchmark, preset, kind, new.batch_size, before=False)
            with FlopCounterMode(display=False) as counter:
                after()
            flops = int(counter.get_total_flops())
            times = interleaved({"before": before, "after": after, "matmul": matmul}, reps, inner)
            peak = gflops(MATMUL_FLOPS, med(times.pop("matmul")))  # beside the steps, under the same load
            # Each rep's two steps ran next to each other: the median of the per-rep ratios cancels most of a
            # neighbour's load, which moves single timings by 2x on a shared machine.
            step_ratio = med([b / a for b, a in zip(times["before"], times["after"])])
            wall = {"before_s": old.steps * med(times["before"]) / 1e3,
                    "after_s": new.steps * med(times["after"]) / 1e3}  # at the medians of the timings
            rows.append({"benchmark": benchmark, "preset": preset, "model": kind, "ms": times, "step_ratio": step_ratio,
                         "schedule_before": old.record(), "schedule_after": new.record(),
                         "steps_before": old.steps, "steps_after": new.steps, "training_s_estimate": wall,
                         "training_ratio": step_ratio * old.steps / new.steps, "flops_after": flops,
                         "matmul_gflops": peak, "fraction_of_peak_after": gflops(flops, med(times["after"])) / peak})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reps", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--sizes", nargs="+", type=int, default=[1, 16, 64, 256])
    parser.add_argument("--quick", action="store_true", help="tiny sizes, one rep: checks that every section runs")
    parser.add_argument("--only", nargs="+", metavar="SECTION", help="run these sections and replace them in "
                        "--out, keeping its others (their machine and load recorded under machine_SECTION)")
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "perf.json"))
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    reps, inner, batch, sizes, steps = args.reps, 10, 256, args.sizes, 20
    configs, kinds = TRAINING_CONFIGS, ["koopman", "mlp", "xlstm"]
    if args.quick:
        reps, inner, batch, sizes, steps, configs, kinds = 1, 1, 4, [1, 4], 2, TRAINING_CONFIGS[:1], ["koopman"]
    generate_dataset("burgers", "small", progress=False)
    ds = load_dataset("burgers", "small")
    model = build_model("burgers", "koopman", 32, "lite", dataset=ds, seed=0)
    result: dict[str, Any] = {"machine": machine(args.threads)}
    peak = matmul_peak(reps)
    result["machine"]["matmul_gflops"] = peak["gflops"]
    sections = {
        "env": lambda: env_section(reps, 99 if not args.quick else 5),
        "jacobian": lambda: jacobian_section(model, batch, reps, inner),
        "ekf": lambda: ekf_section(model, batch, reps, inner),
        "enkf": lambda: enkf_section(model, batch, 20, reps, inner),
        "algebra": lambda: algebra_section(reps, inner),
        "vector": lambda: vector_section(model, sizes, "ekf", reps, steps)
        + vector_section(model, sizes, "enkf", reps, steps),
        "training": lambda: training_section(configs, kinds, reps, 1 if args.quick else 3),
    }
    unknown = set(args.only or ()) - set(sections)
    if unknown:
        parser.error(f"unknown sections {sorted(unknown)}; choose from {', '.join(sections)}")
    for name, run in sections.items():
        if args.only and name not in args.only:
            continue
        tic = time.perf_counter()
        result[name] = run()
        print(f"{name}: {time.perf_counter() - tic:.1f} s", flush=True)
    result["machine"]["loadavg_end"] = list(os.getloadavg())
    out = Path(args.out)
    if args.only:  # the other sections from the earlier run, this run's machine beside the sections it made
        earlier = json.loads(out.read_text())
        this_run = result.pop("machine")
        result = {**earlier, **result, **{f"machine_{name}": this_run for name in args.only}}
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, json.dumps(result, indent=1) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
