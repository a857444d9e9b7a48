"""The placement tables: one ranking (``placement.md``) and the error-vs-budget table (``budgets.md``), both made
from results documents alone, every number printed by :mod:`dks_gym.evaluation.formatting`.

``placement.md`` ranks the policies by time-averaged MSE (frames 1..n_t-1, frame 0 being the same initial
estimate for all) with final-time and time-averaged MSE mean and std across *episodes* (an episode = one test
trajectory under one noise seed, so the std mixes trajectory-to-trajectory and noise-to-noise spread), the
per-episode (paired) ratio to the paper layout, the paired comparison with the random layouts
(:func:`~dks_gym_agents.paired.paired_vs_random`) and the costs.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from dks_gym.envs import SensorFaults
from dks_gym.evaluation.formatting import (cost, fixed, interval, markdown_table, mean_std, relative_score, sci,
                                           signed)
from dks_gym.evaluation.results import load_results, save_results

from .paired import add_paired_intervals, add_paired_vs_random, paired_vs_random
from .records import PLACEMENT_FILE

RANKED_HEADER = ("rank", "policy", "time-avg MSE (mean ± std)", "final MSE (mean ± std)",
                 "time-avg / paper, paired (mean ± std)", "better than paper",
                 "log(MSE / random mean), paired (mean ± s.e.)", "better than random mean", "offline cost",
                 "per decision")


def _versus_paper(rec: dict[str, Any], paper: dict[str, Any] | None) -> list[str]:
    """The per-episode ratio to the paper layout (mean ± std) and the episodes where ``rec`` beats it."""
    if paper is None:
        return ["-", "-"]
    a = np.asarray(rec["per_trajectory_time_mean_mse"], dtype=float)
    b = np.asarray(paper["per_trajectory_time_mean_mse"], dtype=float)
    q = a / b
    return [f"{fixed(q.mean())} ± {fixed(q.std(ddof=1) if len(q) > 1 else 0.0)}", f"{int(np.sum(a < b))}/{len(q)}"]


def _versus_random(paired: dict[str, Any] | None) -> list[str]:
    """The paired log ratio to the random mean (mean ± s.e.) and the episodes won."""
    if paired is None:
        return ["-", "-"]
    return [f"{signed(paired['log_ratio_mean'])} ± {fixed(paired['log_ratio_se'])}",
            f"{paired['wins']}/{paired['n_episodes']}"]


def _random_interval(rec: dict[str, Any]) -> str:
    """The stored 95 % bootstrap interval of the paired log ratio to random (never recomputed here: another
    scipy may draw differently) and what it decides: better or worse than random, or undecided (includes 0)."""
    bounds = (rec.get("paired_vs_random") or {}).get("log_ratio_ci95")
    if bounds is None:
        return "-"
    verdict = "better" if bounds[1] < 0 else "worse" if bounds[0] > 0 else "includes 0"
    return f"{interval(*bounds, fmt=signed)} {verdict}"


INTERVAL_NOTE = ("95 % CI: the percentile bootstrap interval of the mean paired log ratio to random "
                 "(scipy.stats.bootstrap, resampled within each trajectory when it has several noise seeds: the test "
                 "trajectories held fixed), as "
                 "stored in placement.json.gz; 'better' (below 0) or 'worse' (above 0) than the random mean, or "
                 "'includes 0': the episodes do not decide.")


def _ranked_notes(doc: dict[str, Any], paired: dict[str, dict[str, Any]]) -> list[str]:
    """What the ranked table's columns mean, and the random layouts' spread: the lines under it."""
    cfg = doc["config"]
    notes = [
        "",
        f"{doc['benchmark']}, {cfg['model']} ({cfg['model_preset']}, r={cfg['r']}) with {cfg['filter']}, "
        f"m={cfg['n_sensors']}, noise level {cfg['noise_level']:g}; {cfg['n_episodes']} test episodes = "
        f"{cfg['n_test']} trajectories x {len(cfg['noise_seeds'])} noise seed(s) {cfg['noise_seeds']}, "
        f"{cfg['n_frames']} frames each. MSE in physical units over the scored channels; std = sample std "
        "across episodes (trajectory x noise seed: it mixes how hard the trajectories are with the noise); "
        "paired ratio = per-episode time-averaged MSE divided by the paper layout's on the "
        "same trajectory and noise. Paired vs random: per episode, log of the policy's time-averaged MSE over "
        "the mean of the random layouts' on the same episode (for a random-s row, the other seeds), mean ± "
        "standard error (std / sqrt(episodes)); negative = better than random; 'better than random mean' "
        "counts those episodes. Offline cost = fitting on the "
        "training split (incl. RL training, also when loaded from a checkpoint); per decision = one layout "
        "(static: per episode; adaptive: per step and trajectory).",
    ]
    randoms = [r["time_mean_mse_mean"] for r in doc["records"]
               if r["experiment"].startswith("placement/") and r["policy"].startswith("random-")]
    if len(randoms) > 1:
        own = [p["log_ratio_mean"] for k, p in paired.items() if k.startswith("random-")]
        notes.append(f"Random layouts ({len(randoms)} seeds): time-averaged MSE "
                     f"{mean_std(float(np.mean(randoms)), float(np.std(randoms, ddof=1)))} "
                     f"(mean ± std over seeds); their own paired log ratios "
                     f"against the other seeds' mean average {signed(float(np.mean(own)))} (the arithmetic mean is "
                     "pulled up by the worst layouts), the bar a policy must clear to beat a typical random layout; "
                     "placement.json.gz also holds the log ratio against the geometric mean "
                     "(paired_vs_random.log_ratio_geometric_mean), for which that bar is 0.")
    return notes


def ranked_table(doc: dict[str, Any]) -> str:
    """Markdown: policies ranked by time-averaged MSE, with final MSE, paired ratio to the paper layout, costs."""
    recs = [r for r in doc["records"] if r["experiment"].startswith("placement/")]
    policies = sorted((r for r in recs if r["policy"] != "forward"), key=lambda r: r["time_mean_mse_mean"])
    paper = next((r for r in recs if r["policy"] == "paper"), None)
    forward = next((r for r in recs if r["policy"] == "forward"), None)
    paired = paired_vs_random(doc)
    # Records older than the relative L2 error or the intervals lack them: their table prints as it did.
    relative = any(r.get("final_rel_l2_mean") is not None for r in recs)
    intervals = any((r.get("paired_vs_random") or {}).get("log_ratio_ci95") is not None for r in recs)

    def errors(rec: dict[str, Any]) -> list[str]:
        rel = [relative_score(rec.get("final_rel_l2_mean"), rec.get("final_score_mean"))] if relative else []
        versus = _versus_random(paired.get(rec["policy"]))
        return [mean_std(rec["time_mean_mse_mean"], rec["time_mean_mse_std"]),
                mean_std(rec["final_mse_mean"], rec["final_mse_std"]), *rel, *_versus_paper(rec, paper),
                versus[0], *([_random_interval(rec)] if intervals else []), versus[1]]

    rows = [[str(i), rec["policy"] + (" (adaptive)" if rec.get("adaptive") else ""), *errors(rec),
             cost(rec.get("offline_seconds"), 1, " s"), cost(rec.get("decision_seconds"), 1e3, " ms")]
            for i, rec in enumerate(policies, 1)]
    if forward is not None:
        rows.append(["-", "forward run (no sensors)", *errors(forward), "-", "-"])
    header = (*RANKED_HEADER[:4], *(["final rel. L2 (score)"] if relative else []), *RANKED_HEADER[4:7],
              *(["its 95 % CI (bootstrap)"] if intervals else []), *RANKED_HEADER[7:])
    notes = _ranked_notes(doc, paired) + ([INTERVAL_NOTE] if intervals else [])
    return "\n".join([markdown_table(header, rows), *notes]) + "\n"


def rewrite_tables(folder: str | Path) -> Path:
    """Recompute ``paired_vs_random`` and ``placement.md`` of a finished run from its ``placement.json.gz``
    (no filter runs): ``python -c "from dks_gym_agents.tables import rewrite_tables; rewrite_tables('DIR')"``."""
    folder = Path(folder)
    doc = add_paired_vs_random(load_results(folder / PLACEMENT_FILE))  # with its intervals
    save_results(doc, folder / PLACEMENT_FILE)
    (folder / "placement.md").write_text(ranked_table(doc))
    return folder / "placement.md"


def migrate_intervals(folder: str | Path) -> list[Path]:
    """Give the placement documents under ``folder`` the paired intervals they lack
    (:func:`~dks_gym_agents.paired.add_paired_intervals`; the records' own intervals come from
    ``python -m dks_gym.evaluation.migrate``) and rewrite their ``placement.md``; return the documents changed:
    ``python -c "from dks_gym_agents.tables import migrate_intervals; migrate_intervals('DIR')"``."""
    changed = []
    for path in sorted(Path(folder).rglob(PLACEMENT_FILE)):
        doc = load_results(path)
        before = json.dumps(doc)
        if json.dumps(add_paired_intervals(doc)) != before:
            save_results(doc, path)
            changed.append(path)
        (path.parent / "placement.md").write_text(ranked_table(doc))
    return changed


def budget_rows(docs: dict[int, dict[str, Any]]) -> dict[str, dict[int, dict[str, Any]]]:
    """``{policy: {m: record}}`` over the budgets' documents; the random layouts as one row, ``random``, the
    first seed's record (it holds the paired comparison with the others)."""
    rows: dict[str, dict[int, dict[str, Any]]] = {}
    for m, doc in docs.items():
        for rec in doc["records"]:
            name = rec.get("policy")
            if name is None or name.startswith("random-") and name != "random-0":
                continue
            rows.setdefault("random" if name == "random-0" else name, {})[m] = rec
    return rows


def describe_faults(faults: dict[str, Any] | None) -> str:
    """The fault settings that differ from none, as ``name value`` pairs ("none" without faults)."""
    scenario = SensorFaults.from_any(faults)
    return "none" if scenario is None else ", ".join(f"{k} {v}" for k, v in scenario.changed().items())


def _budget_cell(rec: dict[str, Any] | None, skipped: bool) -> str:
    """One policy at one budget: its time-averaged MSE and, in brackets, the paired log ratio to random ± se."""
    if rec is None:
        return "skipped" if skipped else "-"
    text = sci(rec.get("time_mean_mse_mean"))
    paired = rec.get("paired_vs_random")
    if paired:
        se = paired.get("log_ratio_se_trajectories")
        text += f" ({signed(paired['log_ratio_mean'], 2)}" + (f" ± {fixed(se, 2)})" if se is not None else ")")
    return text


def _relative_cell(rec: dict[str, Any] | None, skipped: bool) -> str:
    """One policy at one budget: its final-time relative L2 error and score."""
    if rec is None:
        return "skipped" if skipped else "-"
    return relative_score(rec.get("final_rel_l2_mean"), rec.get("final_score_mean"))


def budget_table(docs: dict[int, dict[str, Any]]) -> str:
    """The error-vs-budget table: per policy and m, time-averaged MSE and the paired log ratio to random ± se;
    then, where the records hold it, the final-time relative L2 error and its score."""
    budgets = sorted(docs)
    first = docs[budgets[0]]
    cfg = first["config"]
    lines = [f"# Sensor budgets: {first['benchmark']}, {cfg['model']} {cfg['filter']}", "",
             f"Time-averaged MSE over frames 1..n_t-1 of the {cfg['n_episodes']} test episodes; in brackets the "
             "paired log ratio to the random layouts of the same episodes (negative: better than random) ± its "
             "standard error over trajectories. Random: the first seeded layout's MSE, the ratio of the mean of "
             f"the others. Faults: {describe_faults(cfg.get('faults'))}.", ""]
    skipped = {(name, m): reason for m, doc in docs.items()
               for name, reason in doc["config"].get("skipped_policies", {}).items()}
    rows = budget_rows(docs)
    names = list(dict.fromkeys([*rows, *(name for name, _ in skipped)]))
    header = ["policy", *(f"m = {m}" for m in budgets)]
    lines.append(markdown_table(header, [[name, *(_budget_cell(rows.get(name, {}).get(m), (name, m) in skipped)
                                                  for m in budgets)] for name in names]))
    if any(rec.get("final_rel_l2_mean") is not None for by_m in rows.values() for rec in by_m.values()):
        # records older than the relative L2 error lack it: their page prints as it did
        lines += ["", "Final-time relative L2 error ‖x̂ − x‖ / ‖x‖ over the scored channels (mean over the "
                  "episodes) and in brackets its score 100 (1 − relative L2); random: the first seeded layout.", "",
                  markdown_table(header, [[name, *(_relative_cell(rows.get(name, {}).get(m), (name, m) in skipped)
                                                   for m in budgets)] for name in names])]
    for (name, m), reason in sorted(skipped.items(), key=lambda item: item[0][1]):
        lines.append(f"\n{name} skipped at m = {m}: {reason}")
    return "\n".join(lines) + "\n"


__all__ = ["budget_rows", "budget_table", "describe_faults", "migrate_intervals", "ranked_table", "rewrite_tables"]
