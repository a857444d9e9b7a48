"""``dks-gym demo``: the paper's main comparison on Burgers, from nothing, in about a minute on a laptop CPU.

Generates the Burgers ``paper`` dataset if it is missing (seconds), takes the four ``lite`` models (the
user's own trained ones in the data home when present, else the ones shipped with dks-gym; ``train=True``
trains and tunes them into the data home first, minutes per model), runs the forward run, the EKF and the
EnKF (n = 20) of every model over the 10 test trajectories (20% noise, 16 sensors, approximate initial
condition, r = 32, the default calibrated Q and P0), prints the table of final-time errors and writes one
figure (final MSE of each model and filter divided by the MLP forward-run error, as in the paper's bar
charts) and the results file.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..benchmarks import get_benchmark
from ..assimilation import AssimilationConfig
from ..dataset import Dataset
from ..models import LatentModel
from .conformance import stamp_protocol
from .expected import run_filters
from .figures import MODEL_LABELS, MODEL_ORDER, normalized_bar_chart
from .formatting import MISSING, fixed, mean_std, relative_score, text_table
from .reproduce import shared_config
from .results import RESULTS_FILE, Record, new_results, save_results

DEMO_BENCHMARK = "burgers"
DEMO_FILTERS = ("forward", "ekf", "enkf")


def demo_table(records: list[Record]) -> str:
    """The demo's plain-text table: final MSE per model and filter, max ||F_k||, time per EKF step; below it,
    when the records hold it, the final relative L2 error and its score per model and filter."""
    rows, relative = [], []
    for model in MODEL_ORDER:
        recs = {r["filter"]: r for r in records if r["model"] == model}
        if not recs:
            continue
        cells = [mean_std(recs[f]["final_mse_mean"], recs[f]["final_mse_std"], missing="diverged")
                 if f in recs else MISSING for f in DEMO_FILTERS]
        ekf = recs.get("ekf")
        norms = [v for v in (ekf or {}).get("max_forecast_norm") or [] if v is not None]
        seconds = ekf["da_step_seconds"] if ekf and ekf["da_step_seconds"] is not None else None
        rows.append([MODEL_LABELS[model], *cells, fixed(max(norms) if norms else None, 3),
                     fixed(None if seconds is None else 1e3 * seconds, 1)])
        relative.append([MODEL_LABELS[model], *[relative_score(recs[f].get("final_rel_l2_mean"),
                                                               recs[f].get("final_score_mean"))
                                                if f in recs else MISSING for f in DEMO_FILTERS]])
    table = text_table(["model", "forward run", "EKF", "EnKF (n=20)", "max|F| EKF", "EKF ms/step"], rows,
                       [9, 22, 22, 22, 12, 13])
    if all(cell == MISSING for row in relative for cell in row[1:]):  # records older than the relative error
        return table
    return (f"{table}\n\nrelative L2 error (score 100 (1 - rel. L2)), final frame, mean over trajectories\n"
            + text_table(["model", "forward run", "EKF", "EnKF (n=20)"], relative, [9, 22, 22, 22]))


def first_run_message(train: bool = False) -> str:
    """What the demo is about to do, in plain words: what it must generate or train first."""
    from ..home import data_home, dataset_path
    from ..models.checkpoint import checkpoint_path

    bench = get_benchmark(DEMO_BENCHMARK)
    todo = []
    if not dataset_path(DEMO_BENCHMARK, "paper").exists():
        todo.append(f"generating the Burgers data ({bench.generation_costs['paper'].time})")
    untrained = [MODEL_LABELS[kind] for kind in MODEL_ORDER
                 if not checkpoint_path(DEMO_BENCHMARK, kind, "lite", 32, 1, data_preset="paper").exists()]
    if train and untrained:
        todo.append(f"training and tuning the {'four' if len(untrained) == 4 else ', '.join(untrained)} lite "
                    f"model{'s' if len(untrained) > 1 else ''} (minutes for each neural one on one CPU core; "
                    "docs/training.md)")
    models = ("your own lite models" if not untrained else
              "the lite models shipped with dks-gym" if len(untrained) == 4 else
              f"the shipped lite models for {', '.join(untrained)} and your own for the others")
    run = "running the forward run, the EKF and the EnKF of each model on the 10 test trajectories"
    if train:
        return (f"dks-gym demo --train: {' and '.join(todo) + ', then ' if todo else ''}{run}. The data and "
                f"models are kept in {data_home()}.")
    return f"dks-gym demo: {' and '.join(todo) + ', then ' if todo else ''}{run} with {models}."


def _demo_models(ds: Dataset, *, train: bool, device: str, progress: bool) -> dict[str, LatentModel]:
    """The four lite models: the user's or the shipped ones, or (``train``) trained and tuned into the data home,
    resuming or reusing what is there (``dks-gym train``'s path)."""
    from ..assimilation import tune_if_missing
    from ..models import load_model, train_model

    models = {}
    for kind in MODEL_ORDER:
        if train:
            models[kind] = train_model(DEMO_BENCHMARK, kind, 32, "lite", 1, dataset=ds, device=device,
                                       progress=progress).model
            tune_if_missing(models[kind], ds, progress=progress)
        else:
            models[kind] = load_model(DEMO_BENCHMARK, kind, r=32, preset="lite", dataset=ds, device=device,
                                      progress=progress)
    return models


def run_demo(
    out: str | Path | None = None,
    *,
    device: str = "cpu",
    train: bool = False,
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Run the demo (see the module docstring); return the results document written to ``out/results.json.gz``
    (``out`` defaults to ``$DKS_GYM_HOME/demo``). ``train``: train and tune the models into the data home
    (resuming or reusing what is there) instead of taking the shipped ones."""
    from tqdm.auto import tqdm

    from ..dataset import DatasetMissing, generate_dataset, load_dataset
    from ..home import data_home
    from ..models.checkpoint import dataset_identity
    from ..models.shipped import is_shipped

    start = time.perf_counter()
    out = data_home() / "demo" if out is None else Path(out)
    log(first_run_message(train))
    try:
        ds = load_dataset(DEMO_BENCHMARK, "paper")
    except DatasetMissing:
        ds = load_dataset(DEMO_BENCHMARK, "paper", generate_dataset(DEMO_BENCHMARK, "paper", progress=progress))
    models = _demo_models(ds, train=train, device=device, progress=progress)
    shipped = [k for k, m in models.items() if is_shipped(getattr(m, "checkpoint_path", None))]
    trained = time.perf_counter()

    base = AssimilationConfig()  # the defaults a user meets: calibrated Q and P0
    bar = tqdm(total=len(DEMO_FILTERS) * len(models), desc="assimilating (model x filter)", unit="run",
               disable=not progress, dynamic_ncols=True)

    def advance(record: Record) -> None:
        bar.set_postfix_str(f"{record['model']} {record['filter']}", refresh=False)
        bar.update(1)

    records = run_filters(models, ds, experiment="demo", filters=DEMO_FILTERS, base=base, on_record=advance,
                          progress=progress)
    bar.close()

    config = dict(shared_config(base, ds, device), experiments=["demo"], wall_time_s=time.perf_counter() - start,
                  setup_time_s=trained - start, shipped_models=shipped)
    doc = stamp_protocol(new_results(DEMO_BENCHMARK, "lite", dataset_identity(ds), config, records))
    save_results(doc, out / RESULTS_FILE)

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
    if shipped:
        log(f"models: shipped with dks-gym ({', '.join(MODEL_LABELS[k] for k in shipped)}); train your own with "
            "`dks-gym demo --train` or `dks-gym train burgers`")
    log(f"figure: {figure}\nresults: {out / RESULTS_FILE}\n"
        f"total {time.perf_counter() - start:.0f} s (data and models {trained - start:.0f} s). "
        "For every experiment of the paper: `dks-gym reproduce burgers`.")
    return doc


__all__ = ["DEMO_BENCHMARK", "DEMO_FILTERS", "demo_table", "run_demo"]
