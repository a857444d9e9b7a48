"""``dks-gym leaderboard``: one ranked table per benchmark of the runs made under its protocol, from results files.

Each results file (``dks-gym reproduce``'s, or :func:`~dks_gym.evaluation.estimators.score_estimator`'s) gives
rows: of a reproduce file, each (model, filter) of its ``calibrated`` experiment (the filters with Q and P0
calibrated from each model's own errors: the settings dks-gym recommends, and the runs that score their predictive
std), or of its ``main`` and ``enkf`` experiments where it has no ``calibrated`` runs; of an estimator's file,
each record. A run ranks only when it was made under its benchmark's protocol exactly
(:mod:`~dks_gym.evaluation.conformance`): a file naming no protocol, another protocol or version, settings that
leave it (``protocol.deviations``: another model preset, noise seeds, ...) or a placement ranking (its runs read
the policies' layouts) is refused as a whole, and a record marked with ``protocol_deviations`` (the exact initial
condition, another noise level, one trajectory) is left out; the page says which and why.

The rows are sorted by the final relative L2 error (mean over the test episodes) and printed with the cells of
:mod:`~dks_gym.evaluation.formatting` through the one table builder, :func:`~dks_gym.evaluation.tabulate.tabulate`.
The page names the command that made it, so it regenerates byte for byte from the files it names.
"""

from __future__ import annotations

import os
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..atomic import atomic_path
from ..benchmarks.protocol import get_protocol
from .conformance import PROTOCOL_KEY, RECORD_MARK
from .figures import FILTER_LABELS, MODEL_LABELS
from .formatting import fixed, interval, percent, sci
from .results import RESULTS_FILE, Record, ResultsDocument, load_results, run_key
from .tabulate import Column, tabulate

#: The experiments of a reproduce file that give the latent models' rows, in order of preference.
PREFERRED = (("calibrated",), ("main", "enkf"))
#: How the page names an estimator whose record name is not how people write it.
ESTIMATOR_LABELS = {"shred": "SHRED"}
#: Where ``dks-gym leaderboard`` writes by default.
DEFAULT_OUT = Path("docs/results/leaderboard.md")


@dataclass(frozen=True)
class Entry:
    """One ranked run: its benchmark, how the page names it, its record and the file it comes from."""

    benchmark: str
    method: str
    record: Record
    source: str


def shown(path: str | Path) -> str:
    """``path`` as the page prints it: relative to the working directory when it lies under it, POSIX slashes."""
    path = Path(path)
    if path.is_absolute():
        try:
            path = path.relative_to(Path.cwd())
        except ValueError:
            pass
    return path.as_posix()


def results_file(path: str | Path) -> Path:
    """A results file, or the ``results.json.gz`` of a folder."""
    path = Path(path)
    return path / RESULTS_FILE if path.is_dir() else path


def refusal(doc: ResultsDocument) -> str | None:
    """Why no run of ``doc`` can rank under its benchmark's protocol, or None when its runs may."""
    block = doc.get(PROTOCOL_KEY)
    if block is None:
        return "it names no protocol (name it with `python -m dks_gym.evaluation.migrate FILE`)"
    ours = get_protocol(doc["benchmark"])
    if (block.get("name"), block.get("version")) != (ours.name, ours.version):
        return (f"it was made under protocol {block.get('name')} v{block.get('version')}; this dks-gym ranks "
                f"{ours.name} v{ours.version}")
    expected = ours.to_dict()
    differ = [k for k in expected if block.get(k) != expected[k]]
    if differ:
        return f"its protocol's fields differ from {ours.name} v{ours.version}'s: {', '.join(differ)}"
    if block.get("deviations"):
        return "its runs leave the protocol: " + ", ".join(
            f"{k} = {v!r} (the protocol's: {expected.get(k)!r})" for k, v in block["deviations"].items())
    if any("policy" in r for r in doc["records"]):
        return "it is a placement ranking: its runs read the policies' layouts, not the protocol's paper layout"
    return None


def method(record: Record) -> str:
    """How the page names a run: ``Koopman, calibrated EKF``, ``pDMD, EnKF n = 20``; an estimator by its name."""
    if record["filter"] == "none":
        return ESTIMATOR_LABELS.get(record["model"], record["model"])
    filt = FILTER_LABELS[record["filter"]] + (f" n = {record['n_members']}" if record["filter"] == "enkf" else "")
    calibrated = "calibrated " if record["experiment"] == "calibrated" and record["filter"] != "forward" else ""
    return f"{MODEL_LABELS.get(record['model'], record['model'])}, {calibrated}{filt}"


def candidates(doc: ResultsDocument) -> tuple[list[Record], str]:
    """The records of ``doc`` that could rank, each run once (experiments repeat runs), and which experiments
    gave the latent models' rows ("" when it holds none)."""
    records = doc["records"]
    present = {r["experiment"] for r in records if r["filter"] != "none"}
    chosen = next((e for e in PREFERRED if present & set(e)), ())
    picked = [r for e in chosen for r in records if r["experiment"] == e and r["filter"] != "none"]
    picked += [r for r in records if r["filter"] == "none"]
    once = {}
    for r in picked:
        once.setdefault(run_key(r), r)
    return list(once.values()), ", ".join(f"`{e}`" for e in chosen if e in present)


def collect(sources: Sequence[str | Path]) -> tuple[dict[str, list[Entry]], list[str], list[str]]:
    """The ranked entries of ``sources`` by benchmark (sorted by final relative L2 error), a note per file
    saying which experiments it contributed, and a line per file or group of records not ranked and why."""
    entries: dict[str, list[Entry]] = {}
    notes: list[str] = []
    skipped: list[str] = []
    for source in sources:
        path = results_file(source)
        doc, name = load_results(path), shown(path)
        why = refusal(doc)
        if why is not None:
            skipped.append(f"`{name}` ({doc['benchmark']}): {why}.")
            continue
        records, experiments = candidates(doc)
        ranked = [r for r in records if not r.get(RECORD_MARK)]
        left = Counter(field for r in records for field in r.get(RECORD_MARK, ()))
        if left:
            skipped.append(f"`{name}` ({doc['benchmark']}): {len(records) - len(ranked)} run(s) leave the protocol ("
                           + ", ".join(f"{k}: {n}" for k, n in sorted(left.items())) + ").")
        entries.setdefault(doc["benchmark"], []).extend(Entry(doc["benchmark"], method(r), r, name) for r in ranked)
        estimators = sum(r["filter"] == "none" for r in ranked)
        parts = ([f"the runs of {experiments}"] if experiments else []) + (
            [f"{estimators} estimator run(s)"] if estimators else [])
        notes.append(f"`{name}` ({doc['benchmark']}): {' and '.join(parts) or 'nothing to rank'}")
    for rows in entries.values():
        rows.sort(key=lambda e: (e.record.get("final_rel_l2_mean") is None,
                                 e.record.get("final_rel_l2_mean") or 0.0, e.method))
    return entries, notes, skipped


def _link(source: str, page: Path) -> str:
    """A markdown link from the page to the folder of a results file."""
    folder = Path(source).parent
    return f"[{folder.name}]({Path(os.path.relpath(folder, page.parent)).as_posix()}/)"


def columns(page: Path) -> list[Column]:
    """The leaderboard's columns; the coverage column only where some run scores a predictive std."""
    def get(row: dict[str, Any], name: str) -> Any:
        return row["entry"].record.get(name)

    return [
        Column("#", lambda row: str(row["rank"])),
        Column("method", lambda row: row["entry"].method),
        Column("rel. L2 (final)", lambda row: percent(get(row, "final_rel_l2_mean"))),
        Column("95 % CI", lambda row: interval(*(get(row, "final_rel_l2_ci95") or (None, None)), fmt=percent)),
        Column("IQM", lambda row: percent(get(row, "final_rel_l2_iqm")), optional=True),
        Column("score", lambda row: fixed(get(row, "final_score_mean"), 1)),
        Column("MSE (final)", lambda row: sci(get(row, "final_mse_mean"))),
        Column("95 % coverage (final)", lambda row: fixed(get(row, "final_coverage_mean"), 2), optional=True),
        Column("results", lambda row: _link(row["entry"].source, page)),
        Column("protocol", lambda row: row["protocol"]),
    ]


def leaderboard_page(sources: Sequence[str | Path], out: str | Path = DEFAULT_OUT) -> str:
    """The leaderboard page of ``sources`` (results files or their folders) as written to ``out`` (the page's
    links are relative to it and it names the command that made it)."""
    out = Path(shown(out))
    entries, notes, skipped = collect(sources)
    command = " ".join(["dks-gym leaderboard", *(shown(s) for s in sources), "--out", out.as_posix()])
    blocks = [
        "# Leaderboard",
        f"Made by\n\n```bash\n{command}\n```\n\nfrom the results files it names; rerun it to regenerate this page.",
        ("Each table ranks the runs made under its benchmark's protocol exactly by the relative L2 error "
         "‖x̂ − x‖ / ‖x‖ over the scored channels at the final frame, mean over the test episodes, with its 95 % "
         "stratified bootstrap interval and its interquartile mean (IQM: the mean of the middle half of the "
         "episodes) as stored in the results file; score: 100 (1 − relative L2); MSE: Eq. 18 at "
         "the final frame, physical units; 95 % coverage: the fraction of scored cells inside the method's central "
         "95 % interval at the final frame, where it gives a predictive std. A latent model's rows come from the "
         "`calibrated` experiment of `dks-gym reproduce` (Q and P0 calibrated from each model's own errors: the "
         "settings dks-gym recommends; the paper's Q = 1e-4 I runs are in each folder's tables.md), or from `main` "
         "and `enkf` where a file has no `calibrated` runs; an estimator's (a method without a filter) from "
         "`score_estimator` ([../estimators.md](../estimators.md)). Runs that leave the protocol are not ranked."),
    ]
    for benchmark, rows in sorted(entries.items()):
        protocol = get_protocol(benchmark)
        tag = f"{protocol.name} v{protocol.version}"
        table = tabulate([{"rank": i + 1, "entry": e, "protocol": tag} for i, e in enumerate(rows)], columns(out))
        blocks += [f"## {benchmark}", f"Protocol: {protocol.describe()}.", table]
    blocks += ["## Sources", "\n".join(f"- {note}." for note in notes) or "None."]
    if skipped:
        blocks += ["## Not ranked", "\n".join(f"- {line}" for line in skipped)]
    return "\n\n".join(blocks) + "\n"


def write_leaderboard(sources: Sequence[str | Path], out: str | Path = DEFAULT_OUT) -> Path:
    """Write :func:`leaderboard_page` to ``out`` atomically; return ``out``."""
    out = Path(out)
    text = leaderboard_page(sources, out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return out


__all__ = ["DEFAULT_OUT", "ESTIMATOR_LABELS", "PREFERRED", "Entry", "candidates", "collect", "columns",
           "leaderboard_page", "method", "refusal", "results_file", "shown", "write_leaderboard"]
