"""``dks-gym demo``: the paper's main comparison on Burgers, from nothing, in a few minutes on a laptop CPU.

Generates the Burgers ``paper`` dataset if it is missing (seconds), trains the four ``lite`` models if
their checkpoints are missing (minutes; reused afterwards), runs the forward run, the EKF and the EnKF
(n = 20) of every model over the 10 test trajectories (20% noise, 16 sensors, approximate initial
condition, r = 32, the default calibrated Q and P0), prints the table of final-time errors and writes one figure (final MSE of each model
and filter divided by the MLP forward-run error, as in the paper's bar charts) and the results file.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..benchmarks import get_benchmark
from .figures import MODEL_LABELS, MODEL_ORDER, normalized_bar_chart
from .results import make_record, new_results, save_results

DEMO_BENCHMARK = "burgers"
DEMO_FILTERS = ("forward", "ekf", "enkf")
#: Measured: `dks-gym train burgers --model all --preset lite` on one CPU core (docs/training.md).
DEMO_TRAIN_MINUTES_PER_MODEL = "6-8"


def _fmt(mean: float | None, std: float | None) -> str:
    if mean is None:
        return "diverged"
    return f"{mean:.2e} ± {std:.1e}" if std is not None else f"{mean:.2e}"


def demo_table(records: list[dict[str, Any]]) -> str:
    """The demo's plain-text table: final MSE per model and filter, max ||F_k||, time per EKF step."""
    head = f"{'model':<9}{'forward run':>22}{'EKF':>22}{'EnKF (n=20)':>22}{'max|F| EKF':>12}{'EKF ms/step':>13}"
    lines = [head, "-" * len(head)]
    for model in MODEL_ORDER:
        recs = {r["filter"]: r for r in records if r["model"] == model}
        if not recs:
            continue
        cells = [_fmt(recs[f]["final_mse_mean"], recs[f]["final_mse_std"]) if f in recs else "-" for f in DEMO_FILTERS]
        ekf = recs.get("ekf")
        norms = [v for v in (ekf or {}).get("max_forecast_norm") or [] if v is not None]
        norm = f"{max(norms):.3f}" if norms else "-"
        ms = f"{1e3 * ekf['da_step_seconds']:.1f}" if ekf and ekf["da_step_seconds"] is not None else "-"
        lines.append(f"{MODEL_LABELS[model]:<9}{cells[0]:>22}{cells[1]:>22}{cells[2]:>22}{norm:>12}{ms:>13}")
    return "\n".join(lines)


def first_run_message() -> str:
    """What the demo is about to do, in plain words: what it must generate and train first, and how long."""
    from ..home import data_home, dataset_path
    from ..models.checkpoint import calibration_names, checkpoint_path

    bench = get_benchmark(DEMO_BENCHMARK)
    todo = []
    if not dataset_path(DEMO_BENCHMARK, "paper").exists():
        todo.append(f"generating the Burgers data ({bench.generation_costs['paper'].time})")
    untrained = [MODEL_LABELS[kind] for kind in MODEL_ORDER
                 if not checkpoint_path(DEMO_BENCHMARK, kind, "lite", 32, 1, data_preset="paper").exists()]
    if untrained:
        todo.append(f"training the {'four' if len(untrained) == 4 else ', '.join(untrained)} lite "
                    f"model{'s' if len(untrained) > 1 else ''} to convergence (about {DEMO_TRAIN_MINUTES_PER_MODEL} "
                    "min for each neural one on one CPU core, seconds for pDMD)")
    run = "then running the forward run, the EKF and the EnKF of each model on the 10 test trajectories"
    paths = [checkpoint_path(DEMO_BENCHMARK, kind, "lite", 32, 1, data_preset="paper") for kind in MODEL_ORDER]
    untuned = len(untrained) if untrained else sum("Q_scale" not in calibration_names(p) for p in paths)
    if untuned:
        run += " (first tuning each filter's process noise once, about 1 min per model)"
    if not todo:
        return f"dks-gym demo: data and models found in {data_home()}; {run} (about {1.5 + untuned:g} min)."
    return (f"dks-gym demo, first run: {' and '.join(todo)}, {run}. Later runs reuse the data and the models "
            f"kept in {data_home()}.")


def run_demo(
    out: str | Path | None = None,
    *,
    device: str = "cpu",
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Run the demo (see the module docstring); return the results document written to ``out/results.json``
    (``out`` defaults to ``$DKS_GYM_HOME/demo``)."""
    import torch
    from tqdm.auto import tqdm

    from ..version import __version__
    from ..dataset import DatasetMissing, generate_dataset, load_dataset
    from ..models import load_model
    from ..models.checkpoint import dataset_identity
    from ..assimilation import AssimilationConfig, run_assimilation
    from ..home import data_home

    start = time.perf_counter()
    out = data_home() / "demo" if out is None else Path(out)
    log(first_run_message())
    try:
        ds = load_dataset(DEMO_BENCHMARK, "paper")
    except DatasetMissing:
        ds = load_dataset(DEMO_BENCHMARK, "paper", generate_dataset(DEMO_BENCHMARK, "paper", progress=progress))
    models = {}
    for kind in MODEL_ORDER:
        models[kind] = load_model(DEMO_BENCHMARK, kind, r=32, preset="lite", dataset=ds, device=device,
                                  train_if_missing=True, progress=progress)
    trained = time.perf_counter()

    records = []
    base = AssimilationConfig()  # the defaults a user meets: calibrated Q and P0
    jobs = [(kind, filt) for filt in DEMO_FILTERS for kind in MODEL_ORDER]
    bar = tqdm(jobs, desc="assimilating (model x filter)", unit="run", disable=not progress, dynamic_ncols=True)
    for kind, filt in bar:
        bar.set_postfix_str(f"{kind} {filt}", refresh=False)
        result = run_assimilation(models[kind], ds, base.replace(kind=filt), progress=progress,
                                  description=f"{kind} {filt}")
        records.append(make_record(result, experiment="demo", keep_curves=False))
    bar.close()

    config = {"experiments": ["demo"], "n_sensors": base.n_sensors, "P0": base.filter.P0, "Q": base.filter.Q,
              "noise_seed": base.noise_seed, "filter_seed": base.filter.seed,
              "split": "test", "n_test": ds.n_trajectories("test"), "n_frames": ds.n_frames, "dt": ds.dt,
              "t0": float(ds.time[0]), "param_name": ds.param_name, "observed_channel": ds.observed_channel,
              "scored_channels": list(ds.scored_channels), "device": device, "dtype": "float32",
              "data_preset": ds.preset, "dks_gym_version": __version__, "torch_version": torch.__version__,
              "wall_time_s": time.perf_counter() - start, "setup_time_s": trained - start}
    doc = new_results(DEMO_BENCHMARK, "lite", dataset_identity(ds), config, records)
    save_results(doc, out / "results.json")

    baseline = next(r for r in records if r["model"] == "mlp" and r["filter"] == "forward")
    panels = [(f"({'abc'[i]}) {label}", [r for r in records if r["filter"] == filt], baseline)
              for i, (filt, label) in enumerate((("forward", "forward run"), ("ekf", "EKF"), ("enkf", "EnKF n=20")))]
    figure = normalized_bar_chart(panels, out / "demo.png",
                                  title="Burgers, lite models: final-time MSE / MLP forward-run MSE "
                                        "(r=32, 16 sensors, 20% noise, approximate IC)")
    log("")
    log(f"Burgers test split ({ds.n_trajectories('test')} trajectories), final-time MSE (mean ± std over "
        "trajectories), lite models, r=32, 16 sensors, 20% noise, approximate initial condition, calibrated "
        "Q and P0 (the paper's Q = 1e-4 I: `dks-gym reproduce burgers`)")
    log(demo_table(records))
    log("")
    log(f"figure: {figure}\nresults: {out / 'results.json'}\n"
        f"total {time.perf_counter() - start:.0f} s (data and models {trained - start:.0f} s). "
        "For every experiment of the paper: `dks-gym reproduce burgers`.")
    return doc


__all__ = ["DEMO_BENCHMARK", "DEMO_FILTERS", "demo_table", "run_demo"]
