"""The placement benchmark's summary: every benchmark and scenario of a benchmark folder in one page.

A benchmark folder holds ``<benchmark>/<scenario>/m<m>/placement.json.gz``, as ``dks-gym evaluate-placement
BENCHMARK --budgets ... --out FOLDER/<benchmark>/<scenario>`` writes them (a scenario is a fault setting
such as ``none`` or ``default``, or a constraint such as ``surface-none``). :func:`write_summary` writes one
page: the reading (``FOLDER/reading.md``, written by a person), then per benchmark and scenario the
error-vs-budget figure and the best filter policy at each budget beside the random layouts, the forward run
and SHRED; the cost of the faults per policy (scenario ``default`` against ``none``, ``wall-default`` against
``wall-none``, ...). Regenerate it with ``python -m dks_gym_agents.summary FOLDER OUT.md``.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, Iterable

import numpy as np

from dks_gym.evaluation.formatting import fixed, markdown_table, sci
from dks_gym.evaluation.results import load_results

from .records import PLACEMENT_FILE
from .tables import describe_faults


SUMMARY_HEADER = ("m", "best filter policy", "random mean", "SHRED (QR layout)", "SHRED / filter on QR",
                  "forward run")


def load_benchmark(folder: str | Path) -> dict[str, dict[str, dict[int, dict[str, Any]]]]:
    """``{benchmark: {scenario: {m: placement document}}}`` of a benchmark folder."""
    out: dict[str, dict[str, dict[int, dict[str, Any]]]] = {}
    for path in sorted(Path(folder).glob(f"*/*/m*/{PLACEMENT_FILE}")):
        m = int(path.parent.name[1:])
        out.setdefault(path.parents[2].name, {}).setdefault(path.parents[1].name, {})[m] = load_results(path)
    if not out:
        raise FileNotFoundError(f"no <benchmark>/<scenario>/m<m>/placement.json.gz under {folder}")
    # "none" (no faults, every allowed cell) first: the reference the other scenarios are read against
    return {bench: dict(sorted(scenarios.items(), key=lambda item: (item[0] != "none", item[0])))
            for bench, scenarios in out.items()}


def _by_policy(doc: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return {r["policy"]: r for r in doc["records"] if r.get("policy")}


def _random_mean(recs: dict[str, dict[str, Any]]) -> float | None:
    values = [r["time_mean_mse_mean"] for name, r in recs.items() if name.startswith("random-")]
    return float(np.mean(values)) if values else None


def _is_filter_policy(name: str) -> bool:
    return name != "forward" and not name.startswith(("random-", "shred-"))


def fault_pairs(scenarios: Iterable[str]) -> list[tuple[str, str]]:
    """``(faulted, clean)`` scenario pairs that differ only by the faults: ``default`` and ``none``,
    ``wall-default`` and ``wall-none``, ..."""
    names = set(scenarios)
    return [(s, s[: -len("default")] + "none") for s in sorted(names)
            if (s == "default" or s.endswith("-default")) and s[: -len("default")] + "none" in names]


def _fault_cost_table(bench: str, faulted: str, clean: str, with_faults: dict[int, dict[str, Any]],
                      without: dict[int, dict[str, Any]]) -> list[str]:
    """Per policy and budget the MSE of scenario ``faulted`` over that of its pair ``clean`` (:func:`fault_pairs`)."""
    budgets = sorted(set(with_faults) & set(without))
    if not budgets:
        return []
    where = "" if faulted == "default" else f", {faulted.removesuffix('-default')}"
    lines = [f"### {bench}: what the default faults cost{where}", "",
             f"Time-averaged MSE of `{faulted}` over `{clean}`, per policy and budget "
             "(the same episodes and noise; > 1: the faults cost).", ""]
    names = [n for n in _by_policy(without[budgets[0]]) if not n.startswith("random-")]
    rows = []
    for name in [*names, "random mean"]:
        cells = []
        for m in budgets:
            a, b = _by_policy(with_faults[m]), _by_policy(without[m])
            if name == "random mean":
                x, y = _random_mean(a), _random_mean(b)
            else:
                x = a.get(name, {}).get("time_mean_mse_mean")
                y = b.get(name, {}).get("time_mean_mse_mean")
            cells.append(fixed(x / y, 2) if x and y else "-")
        rows.append([name, *cells])
    lines.append(markdown_table(["policy", *(f"m = {m}" for m in budgets)], rows))
    return [*lines, ""]


def summary_table(runs: dict[str, dict[str, dict[int, dict[str, Any]]]], figures: str | None = None) -> str:
    """The tables of :func:`write_summary`; ``figures``: the runs' folder relative to the page, to show each
    scenario's budgets.png."""
    lines = [
             "Time-averaged MSE over the test episodes (frames 1..n_t-1, physical units of the scored channels); "
             "per budget m the best filter policy, the mean of the random layouts, SHRED on the QR layout and the "
             "forward run (no sensors). Paired log ratios, standard errors and every policy's row are in each "
             "scenario's budgets.md.", ""]
    for bench, scenarios in runs.items():
        for scenario, docs in scenarios.items():
            budgets = sorted(docs)
            cfg = docs[budgets[0]]["config"]
            lines += [f"## {bench}, {scenario}", ""]
            if figures is not None:
                lines += [f"![{bench}, {scenario}: error vs budget]({figures}/{bench}/{scenario}/budgets.png)", ""]
            lines += [f"{cfg['model']} ({cfg['model_preset']}) {cfg['filter']}, noise level {cfg['noise_level']:g}, "
                      f"{cfg['n_episodes']} episodes, faults: {describe_faults(cfg.get('faults'))}"
                      + (", constrained candidates" if cfg.get("constrained") else "") + ".", ""]
            rows = []
            for m in budgets:
                recs = _by_policy(docs[m])
                ranked = sorted((r for n, r in recs.items() if _is_filter_policy(n)),
                                key=lambda r: r["time_mean_mse_mean"])
                best = ranked[0] if ranked else None
                shred, qr = recs.get("shred-qr"), recs.get("qr")
                ratio = fixed(shred["time_mean_mse_mean"] / qr["time_mean_mse_mean"], 2) if shred and qr else "-"
                rows.append([str(m), f"{best['policy'] if best else '-'} {sci(best and best['time_mean_mse_mean'])}",
                             sci(_random_mean(recs)), sci(shred and shred["time_mean_mse_mean"]), ratio,
                             sci(recs.get("forward", {}).get("time_mean_mse_mean"))])
            lines.append(markdown_table(SUMMARY_HEADER, rows))
            lines.append("")
        for faulted, clean in fault_pairs(scenarios):
            lines += _fault_cost_table(bench, faulted, clean, scenarios[faulted], scenarios[clean])
    return "\n".join(lines)


def summary_page(folder: str | Path, out: str | Path) -> str:
    """The page :func:`write_summary` writes to ``out``: ``folder/reading.md`` (if any), then the tables and
    figures of the runs under ``folder`` (figures linked relative to ``out``)."""
    import os

    head = ["# Placement benchmark: every benchmark, scenario and budget", "",
            f"Regenerate this page from the runs with `python -m dks_gym_agents.summary {folder} {out}`; each "
            "run's command is in the reading below.", ""]
    folder, out = Path(folder), Path(out)
    reading = folder / "reading.md"
    if reading.exists():
        head += [reading.read_text().strip(), ""]
    rel = Path(os.path.relpath(folder, out.parent)).as_posix()
    return "\n".join(head) + "\n" + summary_table(load_benchmark(folder), figures=rel) + "\n"


def write_summary(folder: str | Path, out: str | Path) -> Path:
    """Write :func:`summary_page` to ``out``; returns ``out``."""
    Path(out).write_text(summary_page(folder, out))
    return Path(out)


if __name__ == "__main__":
    if len(sys.argv) != 3:
        raise SystemExit("usage: python -m dks_gym_agents.summary FOLDER OUT.md")
    print(write_summary(sys.argv[1], sys.argv[2]))
