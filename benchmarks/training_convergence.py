"""The lite schedule's convergence before and after the faster training: validation loss against steps and time.

Trains each neural lite model (r = 32, T = 1, seed 0) of one benchmark on its ``paper`` data with
``train_model`` and records every validation: the step, the wall and CPU seconds up to that step since
``train_model`` was called (the validations before it included) and the validation loss; and, after it, the
forward run's final MSE over the test split (frame 0 encoded, the latent map rolled to the last frame, decoded;
the one-step validation loss does not pin it). The checkpoints go
to a temporary directory, or with ``--keep`` to the data home, where ``dks-gym train`` writes them
(``dks-gym demo --train`` then takes them). ``--before`` trains in the formulation and with the schedule the
shipped lite models were trained with (``perf.before_formulation``, the shipped file's ``schedule``, Adam's
plain loop): its losses are those of the shipped models' runs bit for bit (the shipped file's best
validation loss is recorded beside it). Without it, today's package and lite preset, or the preset with
``--steps``, ``--batch-size``, ``--lr``, ``--warmup``, ``--validations`` or ``--clip-norm`` in place of its own (how
docs/training.md's schedules were compared). ``--pair`` runs each model's before and after run in two
processes at once, so that a shared machine's load falls on both alike.
One torch thread unless ``--threads``.

    OMP_NUM_THREADS=1 python benchmarks/training_convergence.py burgers --out after.json
    OMP_NUM_THREADS=1 python benchmarks/training_convergence.py burgers --before --out before.json
    OMP_NUM_THREADS=1 python benchmarks/training_convergence.py burgers --pair before.json after.json
    python benchmarks/training_convergence.py --plot before.json after.json --figure docs/figures/x.png
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

import dks_gym.models.training as training
from dks_gym.atomic import atomic_write_text
from dks_gym.dataset import load_dataset
from dks_gym.models import TrainingSchedule, train_model, training_schedule
from dks_gym.models.checkpoint import read_checkpoint
from dks_gym.models.shipped import find_shipped

sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(1, str(Path(__file__).parent.parent / "validation"))
from forecast_vs_persistence import forecast_errors  # noqa: E402  (the one decoded-forecast error)
from perf import before_formulation  # noqa: E402  (the one definition of "before")


def train_before(benchmark: str, kind: str, dataset: Any, path: Path, **kwargs: Any) -> Any:
    """``train_model`` in the shipped model's formulation, schedule and optimizer."""
    build, adam = training.build_model, training.adam

    def build_before(*args: Any, **kw: Any) -> Any:
        net = build(*args, **kw)
        before_formulation(net)
        return net

    shipped = find_shipped(benchmark, kind)
    schedule = TrainingSchedule(**shipped.metadata["schedule"])
    training.build_model = build_before
    training.adam = lambda net, lr: torch.optim.Adam(net.parameters(), lr=lr)
    try:
        return train_model(benchmark, kind, 32, "lite", 1, dataset=dataset, schedule=schedule, path=path, **kwargs)
    finally:
        training.build_model, training.adam = build, adam


def run(benchmark: str, kind: str, before: bool, keep: bool = False, seed: int = 0,
        schedule: TrainingSchedule | None = None) -> dict[str, Any]:
    """Train one model; its validation curve (step, seconds, loss) and summary. ``keep``: write the checkpoint
    where ``dks-gym train`` writes it (the data home's), so that ``dks-gym demo --train`` takes it;
    ``schedule``: another than the lite preset's."""
    dataset = load_dataset(benchmark, "paper")
    times: dict[int, tuple[float, float]] = {}
    start, cpu_start = time.perf_counter(), time.process_time()

    def on_step(step: int, terms: torch.Tensor) -> None:
        # Wall and CPU seconds before this step's validation, after the earlier ones. With one thread the CPU
        # time leaves out the time a neighbour's job held the core, which the wall time of a shared machine has.
        times[step] = (time.perf_counter() - start, time.process_time() - cpu_start)

    with tempfile.TemporaryDirectory() as tmp:
        path = None if keep else Path(tmp) / "model.safetensors"
        kwargs = {"path": path, "progress": False, "resume": False, "on_step": on_step, "seed": seed}
        result = (train_before(benchmark, kind, dataset, **kwargs) if before else
                  train_model(benchmark, kind, 32, "lite", 1, dataset=dataset, schedule=schedule, **kwargs))
        wall, cpu = time.perf_counter() - start, time.process_time() - cpu_start
        ckpt = read_checkpoint(result.path, optimizer=False)
    validation = ckpt.training["validation"].tolist()
    meta = ckpt.metadata
    # The one-step validation loss does not pin the long horizon: the whole test trajectories' forward run
    # (encode frame 0, roll the latent map to the last frame, decode; MSE over the test trajectories).
    forward = forecast_errors(result.model, dataset, dataset.n_frames - 1, dataset.n_frames)["model_mse"]
    return {"model": kind, "seed": seed, "schedule": meta["schedule"], "steps_done": result.steps_done,
            "train_time_s": meta["train_time_s"], "wall_s": wall, "cpu_s": cpu,
            "best_validation_loss": result.best_validation_loss,
            "best_step": meta["best_step"], "stopped_early": result.stopped_early, "forward_run_mse": forward,
            "shipped_best_validation_loss": find_shipped(benchmark, kind).metadata["best_validation_loss"],
            "validation": [[int(row[0]), *times[int(row[0])], row[1]] for row in validation]}


def plot(before: dict[str, Any], after: dict[str, Any], figure: Path) -> None:
    """Validation loss against the run's CPU time, before (dashed) and after (solid), one colour per model."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 3.6), dpi=80)
    for i, (old, new) in enumerate(zip(before["runs"], after["runs"])):
        for run_, style, label in ((old, "--", "before"), (new, "-", "after")):
            step, _, cpu, loss = zip(*run_["validation"])
            ax.loglog(cpu, loss, style, color=f"C{i}", label=f"{run_['model']} {label}")
        ax.axhline(1.05 * old["best_validation_loss"], color=f"C{i}", lw=0.5)
    ax.set_xlabel("CPU time of the training run, s (one thread)")
    ax.set_ylabel("validation loss")
    ax.set_title(f"{after['benchmark']} lite: thin lines at 1.05 x the best before", fontsize=9)
    ax.legend(fontsize=7, ncol=3)
    fig.tight_layout()
    fig.savefig(figure)


def pair(benchmark: str, models: list[str], threads: int, before_out: Path, after_out: Path,
         after_options: list[str]) -> None:
    """For each model in turn, the before run and the after run (``--keep``, with ``after_options``: the
    schedule options given) in two processes at once; their results gathered into ``before_out`` and
    ``after_out``."""
    results: dict[Path, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for kind in models:
            outs = {before_out: Path(tmp) / f"{kind}-before.json", after_out: Path(tmp) / f"{kind}-after.json"}
            role = {before_out: ["--before"], after_out: ["--keep", *after_options]}
            procs = [subprocess.Popen([sys.executable, __file__, benchmark, "--models", kind, "--threads",
                                       str(threads), *role[out], "--out", str(part)]) for out, part in outs.items()]
            if any(proc.wait() for proc in procs):
                raise SystemExit(f"a {benchmark} {kind} run failed")
            for out, part in outs.items():
                row = json.loads(part.read_text())
                if out not in results:
                    results[out] = dict(row, runs=[])
                results[out]["runs"] += row["runs"]
                results[out]["loadavg_end"] = row["loadavg_end"]
    command = " ".join(["python benchmarks/training_convergence.py", *sys.argv[1:]])
    for out, result in results.items():
        out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out, json.dumps(dict(result, command=command), indent=1) + "\n")


#: The options that replace a field of the lite preset's schedule (the field: the name with "_" for "-").
SCHEDULE_OPTIONS = (("steps", int), ("batch-size", int), ("lr", float), ("warmup", float), ("validations", int),
                    ("clip-norm", float))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("benchmark", nargs="?", choices=["burgers", "cylinder", "dambreak"])
    parser.add_argument("--models", nargs="+", default=["koopman", "mlp", "xlstm"])
    parser.add_argument("--before", action="store_true", help="the shipped models' formulation and schedule")
    parser.add_argument("--keep", action="store_true",
                        help="write the checkpoints to the data home, as `dks-gym train` does (not with --before)")
    parser.add_argument("--seed", type=int, default=0)
    for name, kind in SCHEDULE_OPTIONS:
        parser.add_argument(f"--{name}", type=kind, help="in place of the lite preset's (with --steps its epochs "
                            "cap goes; its patience stays)" if name == "steps" else "in place of the lite preset's"
                            + (" (0: no clipping)" if name == "clip-norm" else ""))
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path)
    parser.add_argument("--pair", nargs=2, type=Path, metavar=("BEFORE", "AFTER"),
                        help="train each model before and after in two processes side by side (after with --keep "
                             "and the schedule options given)")
    parser.add_argument("--plot", nargs=2, type=Path, metavar=("BEFORE", "AFTER"))
    parser.add_argument("--figure", type=Path)
    args = parser.parse_args()
    if args.plot:
        before, after = (json.loads(p.read_text()) for p in args.plot)
        plot(before, after, args.figure)
        return
    # The schedule options given, by their command-line names.
    given = {name: value for name, _ in SCHEDULE_OPTIONS
             if (value := getattr(args, name.replace("-", "_"))) is not None}
    if args.pair:
        options = [f"--{name}={value}" for name, value in given.items()]
        pair(args.benchmark, args.models, args.threads, *args.pair, options)
        return
    torch.set_num_threads(args.threads)
    result: dict[str, Any] = {"benchmark": args.benchmark, "before": args.before, "torch": torch.__version__,
                              "threads": args.threads, "loadavg_start": list(os.getloadavg()),
                              "command": " ".join(["python benchmarks/training_convergence.py", *sys.argv[1:]]),
                              "runs": []}
    changes = {name.replace("-", "_"): value for name, value in given.items()}
    if changes.get("clip_norm") == 0:
        changes["clip_norm"] = None  # --clip-norm 0: no clipping (the former lite schedules)
    if changes and args.before:
        parser.error("--before trains with the shipped models' schedule; it takes no schedule options")
    schedule = dataclasses.replace(training_schedule(args.benchmark, "lite"), **changes) if changes else None
    if schedule is not None and args.steps is not None:
        schedule = dataclasses.replace(schedule, epochs=None)
    for kind in args.models:
        result["runs"].append(run(args.benchmark, kind, args.before, args.keep and not args.before, args.seed,
                                  schedule))
        row = result["runs"][-1]
        print(f"{args.benchmark} {kind}: best validation loss {row['best_validation_loss']:.4g} at step "
              f"{row['best_step']} of {row['steps_done']}, {row['wall_s']:.0f} s wall, {row['cpu_s']:.0f} s CPU, "
              f"forward run's final MSE {row['forward_run_mse']:.3g} "
              f"(shipped model: {row['shipped_best_validation_loss']:.4g})", flush=True)
    result["loadavg_end"] = list(os.getloadavg())
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out, json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
