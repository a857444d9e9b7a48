"""The placement evaluation harness: every policy on the test split, identical noise, one ranked table.

:func:`evaluate_placement` (and ``dks-gym evaluate-placement``) fits each policy on the training split,
then filters every test trajectory with its layouts as one batch (static policies: one layout per episode,
:func:`~dks_gym_agents.scoring.run_layouts`; adaptive ones: a layout per step,
:func:`~dks_gym_agents.scoring.run_adaptive`).
The measurement noise depends only on (noise seed, split, trajectory, frame, cell), so every policy is
judged on the same noise realization, and a cell read by two policies reads the same value.

What it takes: the task (:class:`~dks_gym_agents.policies.PlacementTask`: data, model, filter settings,
sensor budget), the policies (names looked up in a registry, :data:`~dks_gym_agents.registry.POLICIES`, or
policy objects) and the scenario (:class:`~dks_gym_agents.scenario.Scenario`: noise seeds, faults,
constraint, SHRED baselines). What it writes to ``out``: ``placement.json.gz`` (:mod:`dks_gym_agents.records`;
with random layouts in the run every record also gets ``paired_vs_random``, :mod:`dks_gym_agents.paired`),
``placement.md`` (:func:`~dks_gym_agents.tables.ranked_table`) and ``placement_layouts.png``
(:func:`~dks_gym_agents.figures.layout_figure`).
"""

from __future__ import annotations

import concurrent.futures as cf
import dataclasses
import time
from pathlib import Path
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from dks_gym.assimilation import AssimilationResult
from dks_gym.envs import SensorFaults
from dks_gym.evaluation.conformance import stamp_protocol
from dks_gym.evaluation.results import save_results
from dks_gym.parallel import map_tasks

from .figures import layout_figure
from .paired import add_paired_vs_random
from .policies import AdaptivePolicy, PlacementPolicy, PlacementTask, StaticPolicy, constraint_candidates
from .records import PLACEMENT_FILE, PolicyResult, placement_document
from .registry import DEFAULT_POLICIES, POLICIES, PolicyFactory, make_policies
from .scenario import Scenario, episodes
from .scoring import run_adaptive, run_layouts
from .shred_baseline import evaluate_shred
from .tables import ranked_table


def evaluate_policy(task: PlacementTask, policy: PlacementPolicy, trajectories: np.ndarray | None = None,
                    noise_seeds: Sequence[int] | None = None) -> PolicyResult:
    """Fit ``policy`` on the training split (unless fitted) and run it on the test episodes (:func:`episodes`)."""
    ds, config = task.dataset, task.config
    index, seeds = episodes(task, trajectories, noise_seeds)
    if policy.task is None:
        policy.fit(task)
    if isinstance(policy, AdaptivePolicy):
        result = run_adaptive(task.model, ds, policy.decide, policy.candidates, index, config, noise_seeds=seeds)
        per_decision = float(result.extras["decision_seconds"].mean() / len(index))
        return PolicyResult(policy, result, result.extras["layouts"], per_decision)
    if not isinstance(policy, StaticPolicy):
        raise TypeError(f"{type(policy).__name__} is neither a StaticPolicy nor an AdaptivePolicy")
    tic = time.perf_counter()
    layouts = policy.episode_layouts(ds.params(config.split)[index])
    per_decision = (time.perf_counter() - tic) / len(index)
    result = run_layouts(task.model, ds, layouts, index, config, noise_seeds=seeds)
    return PolicyResult(policy, result, layouts, per_decision)


def fit_and_evaluate(task: PlacementTask, policy: PlacementPolicy, faults: SensorFaults | None,
                     noise_seeds: Sequence[int], skip_unfit: bool) -> tuple[PolicyResult | None, str | None]:
    """Task: fit ``policy`` on the training split without faults (a layout is chosen before it breaks) unless
    fitted, then run it on the test episodes with ``faults`` (None: the task's own). Returns its result, or,
    with ``skip_unfit``, (None, why) for a policy that cannot be fitted (e.g. QR asked for more sensors than
    the data hold POD modes)."""
    if policy.task is None:
        try:
            policy.fit(task)
        except ValueError as exc:
            if not skip_unfit:
                raise
            return None, str(exc)
    if faults is not None:
        task = dataclasses.replace(task, config=task.config.replace(faults=faults))
    return evaluate_policy(task, policy, noise_seeds=noise_seeds), None


def run_policies(task: PlacementTask, policies: Sequence[PlacementPolicy], faults: SensorFaults | None,
                 noise_seeds: Sequence[int], *, skip_unfit: bool, log: Callable[[str], None],
                 executor: cf.Executor | None = None) -> tuple[list[PolicyResult], dict[str, str]]:
    """:func:`fit_and_evaluate` for every policy, spread over ``executor`` (:func:`~dks_gym.parallel.map_tasks`;
    with one, the results hold the policies as fitted on the workers), logged and returned in the policies'
    order; with ``skip_unfit``, the policies that could not be fitted are left out and said why, by name."""
    results: list[PolicyResult] = []
    skipped: dict[str, str] = {}
    tasks = [(task, policy, faults, noise_seeds, skip_unfit) for policy in policies]
    for policy, (pr, why) in zip(policies, map_tasks(fit_and_evaluate, tasks, executor)):
        if pr is None:
            log(f"{policy.name:>14}: skipped at m = {task.n_sensors} ({why})")
            skipped[policy.name] = str(why)
            continue
        log(f"{pr.name:>14}: fit {pr.policy.fit_seconds:8.2f} s, time-avg MSE {pr.time_mean_mse.mean():.3e}, "
            f"final MSE {pr.result.final_mse_mean:.3e}")
        results.append(pr)
    if not results:
        raise ValueError(f"no policy could be fitted at m = {task.n_sensors}: {skipped}")
    return results, skipped


def forward_run(task: PlacementTask, results: Sequence[PolicyResult], seeds: Sequence[int]) -> AssimilationResult:
    """The open-loop model on the same episodes (no assimilation), the reference row of every ranking; its
    readings (unused) come from the first static policy's layouts, else the paper layout."""
    index, episode_seeds = episodes(task, noise_seeds=seeds)
    static = next((pr.layouts for pr in results if not pr.policy.adaptive), None)
    layouts = static if static is not None else np.repeat(task.benchmark.paper_layout(task.n_sensors)[None],
                                                          len(index), 0)
    return run_layouts(task.model, task.dataset, layouts, index, task.config.replace(kind="forward"),
                       noise_seeds=episode_seeds)


def shred_rows(task: PlacementTask, results: Sequence[PolicyResult], scenario: Scenario, seeds: Sequence[int],
               skipped: dict[str, str], log: Callable[[str], None],
               executor: cf.Executor | None = None) -> list[dict[str, Any]]:
    """The scenario's SHRED baselines as records, trained over ``executor``; one whose policy is not in the run
    goes to ``skipped``."""
    by_name = {pr.name: pr for pr in results}
    for name in scenario.shred:
        if name not in by_name:
            log(f"{'shred-' + name:>14}: skipped ({name!r} is not in this run)")
            skipped[f"shred-{name}"] = f"{name!r} is not in this run"
    tasks = [(task, by_name[name], seeds, scenario.shred_config, executor is None)
             for name in scenario.shred if name in by_name]
    records = []
    for rec in map_tasks(evaluate_shred, tasks, executor):
        log(f"{rec['policy']:>14}: fit {rec['fit_seconds']:8.2f} s, time-avg MSE {rec['time_mean_mse_mean']:.3e}, "
            f"final MSE {rec['final_mse_mean']:.3e} (POD floor {rec['pod_floor_time_mean_mse']:.1e})")
        records.append(rec)
    return records


def evaluate_placement(
    task: PlacementTask,
    policies: Sequence[str | PlacementPolicy] | str = DEFAULT_POLICIES,
    scenario: Scenario | None = None,
    *,
    registry: Mapping[str, PolicyFactory] = POLICIES,
    skip_unfit: bool = False,
    out: str | Path | None = None,
    log: Callable[[str], None] = print,
    executor: cf.Executor | None = None,
) -> tuple[dict[str, Any], list[PolicyResult]]:
    """Fit and run ``policies`` on the task's test split under ``scenario`` (default: one noise seed, no
    faults, every fluid cell); write JSON, table and figure to ``out``.

    Returns the results document and the per-policy results. ``policies``: names (a list or comma-separated)
    built by ``registry`` (:data:`~dks_gym_agents.registry.POLICIES`: each policy's knobs bound there) or
    :class:`PlacementPolicy` objects. Episodes: every test trajectory under the scenario's noise seeds, from
    the task's own. Learned policies built here save their checkpoints and learning curves under
    ``out/agents``. ``skip_unfit``: leave out (and record in ``config.skipped_policies``) a policy that cannot
    be fitted, e.g. QR with more sensors than the data have POD modes, instead of stopping. ``executor``
    (``distributed.Client.get_executor()``, a process pool; default: this process) fits and runs the policies,
    then trains the SHRED baselines, on its workers (:func:`~dks_gym.parallel.map_tasks`): the same documents
    but for the measured times; the results then hold the policies as fitted there.
    """
    start = time.perf_counter()
    scenario = Scenario() if scenario is None else scenario
    allowed = constraint_candidates(task.dataset, scenario.constraint)
    if allowed is not None:
        task = dataclasses.replace(task, candidates=allowed)
    out = Path(out) if out is not None else None
    chosen = make_policies(policies, registry, agents=None if out is None else out / "agents")
    seeds = scenario.seeds(task)
    results, skipped = run_policies(task, chosen, scenario.faults, seeds, skip_unfit=skip_unfit, log=log,
                                    executor=executor)
    if scenario.faults is not None:
        task = dataclasses.replace(task, config=task.config.replace(faults=scenario.faults))
    forward = forward_run(task, results, seeds)
    estimators = shred_rows(task, results, scenario, seeds, skipped, log, executor)
    doc = placement_document(task, results, forward, wall_time=time.perf_counter() - start)
    doc["records"].extend(estimators)
    doc = add_paired_vs_random(doc)
    doc["config"]["skipped_policies"] = skipped
    stamp_protocol(doc)  # again: the SHRED records joined after placement_document marked its own
    if out is not None:
        save_results(doc, out / PLACEMENT_FILE)
        (out / "placement.md").write_text(ranked_table(doc))
        layout_figure(task, results, out / "placement_layouts.png")
        log(f"wrote {out / PLACEMENT_FILE}, {out / 'placement.md'}, {out / 'placement_layouts.png'}")
    return doc, results


__all__ = ["evaluate_placement", "evaluate_policy", "fit_and_evaluate", "forward_run", "run_policies", "shred_rows"]
