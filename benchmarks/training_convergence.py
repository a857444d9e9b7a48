"""The lite schedule's convergence before and after the faster training: validation loss against steps and time.

Trains each neural lite model (r = 32, T = 1, seed 0) of one benchmark on its ``paper`` data with
``train_model`` and records every validation: the step, the training time up to that step (the validations
before it included) and the validation loss. The checkpoints go to a temporary directory, or with ``--keep``
to the data home, where ``dks-gym train`` writes them (``dks-gym demo --train`` then takes them). ``--before``
trains in the formulation and with the schedule the shipped lite models were trained with
(``perf.before_formulation``, the shipped file's ``schedule``, Adam's plain loop): its losses are those of
the shipped models' runs bit for bit (the shipped file's best validation loss is recorded beside it).
Without it, today's package and lite preset. One torch thread unless ``--threads``.

    OMP_NUM_THREADS=1 python benchmarks/training_convergence.py burgers --out after.json
    OMP_NUM_THREADS=1 python benchmarks/training_convergence.py burgers --before --out before.json
    python benchmarks/training_convergence.py --plot before.json after.json --figure docs/figures/x.png
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

import dks_gym.models.training as training
from dks_gym.atomic import atomic_write_text
from dks_gym.dataset import load_dataset
from dks_gym.models import TrainingSchedule, train_model
from dks_gym.models.checkpoint import read_checkpoint
from dks_gym.models.shipped import find_shipped

sys.path.insert(0, str(Path(__file__).parent))
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


def run(benchmark: str, kind: str, before: bool, keep: bool = False) -> dict[str, Any]:
    """Train one model; its validation curve (step, seconds, loss) and summary. ``keep``: write the checkpoint
    where ``dks-gym train`` writes it (the data home's), so that ``dks-gym demo --train`` takes it."""
    dataset = load_dataset(benchmark, "paper")
    times: dict[int, float] = {}
    start = time.perf_counter()

    def on_step(step: int, terms: torch.Tensor) -> None:
        times[step] = time.perf_counter() - start  # before this step's validation, after the earlier ones

    with tempfile.TemporaryDirectory() as tmp:
        path = None if keep else Path(tmp) / "model.safetensors"
        kwargs = {"path": path, "progress": False, "resume": False, "on_step": on_step}
        result = (train_before(benchmark, kind, dataset, **kwargs) if before else
                  train_model(benchmark, kind, 32, "lite", 1, dataset=dataset, **kwargs))
        ckpt = read_checkpoint(result.path, optimizer=False)
    validation = ckpt.training["validation"].tolist()
    meta = ckpt.metadata
    return {"model": kind, "schedule": meta["schedule"], "steps_done": result.steps_done,
            "train_time_s": meta["train_time_s"], "best_validation_loss": result.best_validation_loss,
            "best_step": meta["best_step"], "stopped_early": result.stopped_early,
            "shipped_best_validation_loss": find_shipped(benchmark, kind).metadata["best_validation_loss"],
            "validation": [[int(row[0]), times[int(row[0])], row[1]] for row in validation]}


def plot(before: dict[str, Any], after: dict[str, Any], figure: Path) -> None:
    """Validation loss against training time, before (dashed) and after (solid), one colour per model."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 3.6), dpi=80)
    for i, (old, new) in enumerate(zip(before["runs"], after["runs"])):
        for run_, style, label in ((old, "--", "before"), (new, "-", "after")):
            curve = list(zip(*run_["validation"]))
            ax.loglog(curve[1], curve[2], style, color=f"C{i}", label=f"{run_['model']} {label}")
        ax.axhline(1.05 * old["best_validation_loss"], color=f"C{i}", lw=0.5)
    ax.set_xlabel("training time, s (one core)")
    ax.set_ylabel("validation loss")
    ax.set_title(f"{after['benchmark']} lite: thin lines at 1.05 x the best before", fontsize=9)
    ax.legend(fontsize=7, ncol=3)
    fig.tight_layout()
    fig.savefig(figure)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("benchmark", nargs="?", choices=["burgers", "cylinder", "dambreak"])
    parser.add_argument("--models", nargs="+", default=["koopman", "mlp", "xlstm"])
    parser.add_argument("--before", action="store_true", help="the shipped models' formulation and schedule")
    parser.add_argument("--keep", action="store_true",
                        help="write the checkpoints to the data home, as `dks-gym train` does (not with --before)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path)
    parser.add_argument("--plot", nargs=2, type=Path, metavar=("BEFORE", "AFTER"))
    parser.add_argument("--figure", type=Path)
    args = parser.parse_args()
    if args.plot:
        before, after = (json.loads(p.read_text()) for p in args.plot)
        plot(before, after, args.figure)
        return
    torch.set_num_threads(args.threads)
    result: dict[str, Any] = {"benchmark": args.benchmark, "before": args.before, "torch": torch.__version__,
                              "threads": args.threads, "loadavg_start": list(os.getloadavg()),
                              "command": " ".join(["python benchmarks/training_convergence.py", *sys.argv[1:]]),
                              "runs": []}
    for kind in args.models:
        result["runs"].append(run(args.benchmark, kind, args.before, args.keep and not args.before))
        row = result["runs"][-1]
        print(f"{args.benchmark} {kind}: best validation loss {row['best_validation_loss']:.4g} at step "
              f"{row['best_step']} of {row['steps_done']}, {row['train_time_s']:.0f} s (shipped model: "
              f"{row['shipped_best_validation_loss']:.4g})", flush=True)
    result["loadavg_end"] = list(os.getloadavg())
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out, json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
