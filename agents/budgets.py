"""The sensor-budget study: one ranking per sensor count m, then the error-vs-budget table and figure.

:func:`evaluate_budgets` runs :func:`~dks_gym_agents.evaluate.evaluate_placement` at each budget
(``out/m<m>``), then writes ``out/budgets.md`` (:func:`~dks_gym_agents.tables.budget_table`) and
``out/budgets.png`` (:func:`~dks_gym_agents.figures.budget_figure`). A sweep can be resumed: each budget's
``placement.json.gz`` is written when that budget is done, and a later call with the same settings keeps it.
"""

from __future__ import annotations

import concurrent.futures as cf
import copy
import dataclasses
import json
from pathlib import Path
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from dks_gym.envs import SensorFaults
from dks_gym.evaluation.results import load_results

from .evaluate import evaluate_placement
from .figures import budget_figure
from .policies import PlacementPolicy, PlacementTask
from .records import PLACEMENT_FILE
from .registry import DEFAULT_POLICIES, POLICIES, PolicyFactory
from .scenario import Scenario
from .tables import budget_table


def evaluate_budgets(task: PlacementTask, budgets: Sequence[int], scenario: Scenario | None = None,
                     policies: Sequence[str | PlacementPolicy] | str = DEFAULT_POLICIES, *,
                     registry: Mapping[str, PolicyFactory] = POLICIES, out: str | Path, resume: bool = False,
                     log: Callable[[str], None] = print,
                     executor: cf.Executor | None = None) -> dict[int, dict[str, Any]]:
    """:func:`~dks_gym_agents.evaluate.evaluate_placement` at each sensor budget m in ``budgets`` (the task with
    ``n_sensors = m``, ``out/m{m}``), then ``out/budgets.md`` and ``out/budgets.png``: per policy and budget the
    time-averaged MSE and its paired log ratio to the random layouts of the same episodes, with the standard
    error over trajectories (the error-vs-budget curves with paired confidence bands). A policy that cannot be
    fitted at a budget is left out there and said so.
    Your own policy objects rank beside the named ones: each budget fits a fresh copy of an unfitted one (a
    fitted policy holds one budget's layout and is refused with several budgets).
    ``resume``: keep the budgets an earlier call with the same settings wrote to ``out`` (each budget's
    ``placement.json.gz`` is written when that budget is done) instead of rerunning them, and show every budget
    in ``out`` in the table and figure: an interrupted sweep goes on where it stopped, a later call adds budgets.
    ``executor``: where each budget's policies are fitted and run (:func:`~dks_gym_agents.evaluate.evaluate_placement`).
    """
    budgets = sorted({int(m) for m in budgets})
    scenario = Scenario() if scenario is None else scenario
    if not budgets or budgets[0] < 1:
        raise ValueError(f"budgets must be positive sensor counts, got {budgets!r}")
    if isinstance(policies, str):
        policies = [n.strip() for n in policies.split(",") if n.strip()]
    if len(budgets) > 1 and any(isinstance(p, PlacementPolicy) and p.task is not None for p in policies):
        raise ValueError("a fitted policy object holds one budget's layout; pass it unfitted (each budget fits a "
                         "copy) or by name to compare budgets")
    out = Path(out)
    kept = finished_budgets(out, task, scenario) if resume else {}
    docs = {}
    for m in budgets:
        if m in kept:
            log(f"budget m = {m}: kept {out / f'm{m}' / PLACEMENT_FILE}")
            continue
        log(f"budget m = {m}")
        at_m = dataclasses.replace(task, config=task.config.replace(n_sensors=m))
        fresh = [copy.deepcopy(p) if isinstance(p, PlacementPolicy) else p for p in policies]
        docs[m], _ = evaluate_placement(at_m, fresh, scenario, registry=registry, skip_unfit=True,
                                        out=out / f"m{m}", log=log, executor=executor)
    docs = dict(sorted({**kept, **docs}.items()))
    if kept:
        same_settings(docs, out)
    (out / "budgets.md").write_text(budget_table(docs))
    budget_figure(docs, out / "budgets.png")
    log(f"wrote {out / 'budgets.md'}, {out / 'budgets.png'}")
    return docs


#: Config entries that may differ between the budgets of one sweep (the budget itself, when and how it ran).
_PER_RUN = ("n_sensors", "policies", "skipped_policies", "created", "wall_time_s", "dks_gym_version",
            "torch_version", "python")


def _policy_names(doc: dict[str, Any]) -> set[str]:
    """The policies a run was asked for: those it ran, the SHRED rows and those it skipped."""
    cfg = doc["config"]
    return (set(cfg["policies"]) | set(cfg.get("skipped_policies", {}))
            | {r["policy"] for r in doc["records"] if str(r.get("policy", "")).startswith("shred-")})


def same_settings(docs: dict[int, dict[str, Any]], out: Path) -> None:
    """Refuse budgets of ``out`` that were made with other settings than the first one (all but the budget)."""
    first_m = min(docs)
    first = docs[first_m]
    # as stored: a budget run now holds tuples (the faults' slow_sensors) where one read back holds lists
    stored = {m: json.loads(json.dumps(doc["config"])) for m, doc in docs.items()}
    for m, doc in docs.items():
        differ = sorted(k for k in set(stored[first_m]) | set(stored[m]) if k not in _PER_RUN
                        and stored[first_m].get(k) != stored[m].get(k))
        if doc["benchmark"] != first["benchmark"]:
            differ.insert(0, "benchmark")
        if _policy_names(doc) != _policy_names(first):
            differ.append("policies")
        if differ:
            raise ValueError(f"{out / f'm{m}'} was made with other settings than {out / f'm{first_m}'} "
                             f"({', '.join(differ)} differ); write to another --out or delete the stale budget")


def finished_budgets(out: Path, task: PlacementTask, scenario: Scenario) -> dict[int, dict[str, Any]]:
    """The budgets an earlier sweep finished in ``out`` (``m<m>/placement.json.gz``), checked against each other and
    against this call's benchmark, model, filter, noise and faults."""
    docs = {int(p.parent.name[1:]): load_results(p) for p in out.glob(f"m*/{PLACEMENT_FILE}")
            if p.parent.name[1:].isdigit()}
    if not docs:
        return {}
    same_settings(docs, out)
    doc = docs[min(docs)]
    cfg = doc["config"]
    asked = {"benchmark": (doc["benchmark"], task.benchmark.name),
             "model": (cfg["model"], task.model.kind),
             "filter": (cfg["filter"], task.config.filter.kind),
             "model_preset": (cfg["model_preset"], task.model_preset),
             "noise_level": (cfg["noise_level"], task.config.noise_level),
             "noise_seeds": (len(cfg["noise_seeds"]), scenario.noise_seeds),
             "faults": (SensorFaults.from_any(cfg.get("faults")), scenario.faults),
             "noise_seed": (cfg["noise_seed"], task.config.noise_seed)}
    differ = [k for k, (was, now) in asked.items() if was != now]
    if differ:
        raise ValueError(f"{out} holds budgets {sorted(docs)} made with other settings ({', '.join(differ)} "
                         "differ); write to another --out, or leave out --resume to overwrite them")
    return docs


__all__ = ["evaluate_budgets", "finished_budgets", "same_settings"]
