"""Where a training step's time goes: torch.profiler over the Adam steps of ``fit_steps``, by phase.

For each configuration (benchmark and training preset, the Koopman model at r = 32, T = 1, the ``paper``
data) the model, Adam and the window sampler are built by ``plan_training`` and ``set_up_training``, as
``train_model`` builds them, and the steps are run by ``fit_steps`` itself (no checkpoint is written: the
plan's checkpoint path is a temporary directory). After a few warm-up steps, N steps are timed without the
profiler, then N more under ``torch.profiler`` (CPU activity) with ``record_function`` labels that this
script wraps around the phases at run time (the package is not changed):

- sampling: ``WindowSampler.sample`` (drawing the windows from the in-memory split);
- encoder: ``encode`` (normalization, the convolutional encoder and the parameter embedding);
- latent map: ``forecast`` (the embedding, the generator MLPs and the matrix exponential: in training mode
  ``koopman.taylor_matrix_exp``'s float32 matrix products; before it, float64 ``matrix_exp``, whose
  ``aten::linalg_matrix_exp`` and backward are reported apart, zero now);
- decoder: ``decode_normalized``;
- loss: the rest of ``training_loss`` (targets, stacking, the three means);
- backward: ``Tensor.backward``; optimizer: Adam's ``zero_grad``, the gradients' clipping and ``step``;
- rest: the step's wall time less the phases above (the loop, the learning-rate update, moving the batch).

``outside torch ops`` is the step's wall time less the time inside top-level ``aten::`` operators: the Python
and dispatch overhead spread over every phase. The validation passes of the lite schedules (every 2-3 % of
the steps) are left out. One torch thread unless ``--threads``.

    OMP_NUM_THREADS=1 python benchmarks/profile_training.py     # benchmarks/results/profile_training.json
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import torch
from torch.profiler import ProfilerActivity, profile, record_function

import dks_gym.models.training as training
from dks_gym.atomic import atomic_write_text
from dks_gym.dataset import load_dataset

# name: (benchmark, preset, profiled steps)
CONFIGS = {
    "burgers-lite": ("burgers", "lite", 30),
    "burgers-paper": ("burgers", "paper", 10),
    "cylinder-lite": ("cylinder", "lite", 10),
}
PHASES = ("sampling", "encoder", "latent map", "decoder", "loss", "backward", "optimizer", "rest")


def set_up(benchmark: str, preset: str, r: int, seed: int, tmp: Path) -> tuple[Any, Any]:
    """The plan and the run (model, Adam, sampler) of a Koopman training run, as ``train_model`` sets them up."""
    dataset = load_dataset(benchmark, "paper")
    plan = training.plan_training(benchmark, "koopman", r, preset, 1, dataset=dataset, path=tmp / "profile.pt",
                                  schedule=None, seed=seed, device=torch.device("cpu"), checkpoint_every=None)
    return plan, training.set_up_training(plan, None, in_memory=None, progress=False)


def run_steps(plan: Any, run: Any, start: int, n: int) -> float:
    """``n`` steps of ``fit_steps`` from step ``start`` (no validation, no checkpoint); their wall time, s."""
    state = run.state
    tic = time.perf_counter()
    training.fit_steps(state.net, state.optimizer, state.sampler, start=start, steps=start + n,
                       batch_size=plan.schedule.batch_size, losses=state.losses, progress=False,
                       lr_at=plan.schedule.lr_at, clip_norm=plan.schedule.clip_norm)
    return time.perf_counter() - tic


def labelled(fn: Any, label: str) -> Any:
    """``fn`` run inside ``record_function(label)``."""
    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        with record_function(label):
            return fn(*args, **kwargs)
    return wrapper


@contextmanager
def phase_labels(run: Any) -> Iterator[None]:
    """Wrap the phases of a step in ``record_function`` labels for the duration of the block."""
    net, optimizer = run.state.net, run.state.optimizer
    targets = [(run.state.sampler, "sample", "sampling"), (net, "encode", "encoder"),
               (net, "forecast", "latent map"), (net, "decode_normalized", "decoder"),
               (optimizer, "zero_grad", "optimizer"), (torch.nn.utils, "clip_grad_norm_", "optimizer"),
               (optimizer, "step", "optimizer"),
               (training, "training_loss", "loss"), (torch.Tensor, "backward", "backward")]
    originals = [(obj, name, getattr(obj, name), name in vars(obj)) for obj, name, _ in targets]
    try:
        for obj, name, label in targets:
            setattr(obj, name, labelled(getattr(obj, name), label))
        yield
    finally:
        for obj, name, original, own in originals:
            if own:
                setattr(obj, name, original)
            else:
                delattr(obj, name)  # an instance attribute shadowing the class's method


def has_ancestor(event: Any, prefix: str) -> bool:
    """Whether the name of an event enclosing ``event`` starts with ``prefix``."""
    parent = event.cpu_parent
    while parent is not None:
        if parent.name.startswith(prefix):
            return True
        parent = parent.cpu_parent
    return False


def phase_of(event: Any) -> str:
    """The innermost phase label enclosing ``event`` ("rest" outside every phase)."""
    parent = event.cpu_parent
    while parent is not None and parent.name not in PHASES:
        parent = parent.cpu_parent
    return "rest" if parent is None else parent.name


def top(values: dict[str, float], k: int = 5) -> dict[str, float]:
    """The ``k`` largest entries of ``values``."""
    return dict(sorted(values.items(), key=lambda item: -item[1])[:k])


def attribute(events: Any, n_steps: int, wall_ms: float) -> dict[str, Any]:
    """Per-step milliseconds of each phase, of ``matrix_exp`` and of the time outside torch operators.

    An event inside another of the same name is not counted again; the backward of ``matrix_exp`` calls
    ``matrix_exp`` itself, so the forward's time counts the calls outside the autograd engine only.
    """
    total: dict[str, float] = {}
    torch_ops = matrix_exp = 0.0
    ops: dict[str, dict[str, float]] = {phase: {} for phase in PHASES}  # top-level aten ops by phase
    for ev in events:
        if has_ancestor(ev, ev.name):
            continue
        ms = ev.time_range.elapsed_us() / 1e3 / n_steps
        total[ev.name] = total.get(ev.name, 0.0) + ms
        if ev.name.startswith("aten::") and not has_ancestor(ev, "aten::"):
            torch_ops += ms
            by_phase = ops[phase_of(ev)]
            by_phase[ev.name] = by_phase.get(ev.name, 0.0) + ms
        if ev.name == "aten::linalg_matrix_exp" and not has_ancestor(ev, "autograd::engine"):
            matrix_exp += ms
    ms = {phase: total.get(phase, 0.0) for phase in PHASES[:-1]}
    ms["loss"] -= ms["encoder"] + ms["latent map"] + ms["decoder"]  # training_loss encloses the three
    ms["rest"] = wall_ms - sum(ms.values())
    backward = {name.split(": ", 1)[1]: value for name, value in total.items()
                if name.startswith("autograd::engine::evaluate_function: ")}
    return {"ms": ms, "fraction": {k: v / wall_ms for k, v in ms.items()}, "matrix_exp_forward_ms": matrix_exp,
            "matrix_exp_backward_ms": backward.get("LinalgMatrixExpBackward0", 0.0),
            "torch_ops_ms": torch_ops, "outside_torch_ops_ms": wall_ms - torch_ops,
            "backward_top_ms": top(backward), "forward_top_ops_ms": {phase: top(ops[phase]) for phase in
                                                                    ("encoder", "latent map", "decoder")}}


def profile_config(name: str, r: int, seed: int, warmup: int, steps: int | None) -> dict[str, Any]:
    """Warm up, time ``steps`` steps, then profile as many; the attribution of one configuration."""
    benchmark, preset, default_steps = CONFIGS[name]
    n = steps or default_steps
    with tempfile.TemporaryDirectory() as tmp:
        plan, run = set_up(benchmark, preset, r, seed, Path(tmp))
        run_steps(plan, run, 0, warmup)
        plain_s = run_steps(plan, run, warmup, n)
        with phase_labels(run), profile(activities=[ProfilerActivity.CPU], record_shapes=False) as prof:
            profiled_s = run_steps(plan, run, warmup + n, n)
    wall_ms = profiled_s * 1e3 / n
    return {"benchmark": benchmark, "preset": preset, "r": r, "T": 1, "batch": plan.schedule.batch_size,
            "steps_profiled": n, "warmup": warmup, "ms_per_step_unprofiled": plain_s * 1e3 / n,
            "ms_per_step_profiled": wall_ms, **attribute(prof.events(), n, wall_ms)}


def print_table(name: str, row: dict[str, Any]) -> None:
    """One configuration's phases, ms per step and per cent of the step."""
    print(f"\n{name} (batch {row['batch']}): {row['ms_per_step_profiled']:.1f} ms/step profiled, "
          f"{row['ms_per_step_unprofiled']:.1f} unprofiled")
    for phase in PHASES:
        print(f"  {phase:<12} {row['ms'][phase]:9.2f} ms  {100 * row['fraction'][phase]:5.1f} %")
    print(f"  matrix_exp forward {row['matrix_exp_forward_ms']:.2f} ms, backward {row['matrix_exp_backward_ms']:.2f}"
          f" ms; outside torch ops {row['outside_torch_ops_ms']:.2f} ms")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--configs", nargs="+", choices=list(CONFIGS), default=list(CONFIGS))
    parser.add_argument("--steps", type=int, default=None, help="profiled steps (default: per configuration)")
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--r", type=int, default=32)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=str(Path(__file__).parent / "results" / "profile_training.json"))
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    result: dict[str, Any] = {"torch": torch.__version__, "threads": args.threads,
                              "loadavg_start": list(os.getloadavg()),
                              "command": " ".join(["python benchmarks/profile_training.py", *sys.argv[1:]]),
                              "configs": {}}
    for name in args.configs:
        row = profile_config(name, args.r, args.seed, args.warmup, args.steps)
        result["configs"][name] = row
        print_table(name, row)
    result["loadavg_end"] = list(os.getloadavg())
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, json.dumps(result, indent=1) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
