"""``dks-gym compare``: the records of two results files paired by their key, with the ratios B / A.

Two files compare only when they were made under the same protocol settings
(:func:`~dks_gym.evaluation.conformance.protocol_differences`); ``force`` compares them anyway.
"""

from __future__ import annotations

from typing import Any

from .conformance import check_comparable, protocol_differences
from .formatting import MISSING, percent, sci, sig
from .results import RECORD_KEY, ResultsDocument, record_key, validate
from .tabulate import max_norm


def _ratio(a: float | None, b: float | None) -> float | None:
    if a is None or b is None or a == 0:
        return None
    return b / a


def compare(a: ResultsDocument, b: ResultsDocument, *, force: bool = False) -> list[dict[str, Any]]:
    """Pair the records of ``a`` and ``b`` by key; per pair the values and the ratios B / A.

    Raises :class:`~dks_gym.evaluation.conformance.ProtocolMismatch`, naming the fields that differ, when the
    two were made under different protocol settings, unless ``force``.

    Each row: the key fields, ``mse_a``, ``mse_b``, ``mse_ratio`` (final_mse_mean B / A), ``norm_ratio``
    (max over trajectories of max_forecast_norm), ``time_ratio`` (da_step_seconds), ``rel_a``, ``rel_b``,
    ``rel_ratio`` (final_rel_l2_mean; None where a record predates it). Records present in only one file are
    listed with ``only`` = "a" or "b" and no ratios.
    """
    validate(a)
    validate(b)
    if not force:
        check_comparable(a, b)
    index_b = {record_key(r): r for r in b["records"]}
    rows: list[dict[str, Any]] = []
    for ra in a["records"]:
        key = record_key(ra)
        row = dict(zip(RECORD_KEY, key))
        rb = index_b.pop(key, None)
        if rb is None:
            rows.append(dict(row, only="a", mse_a=ra["final_mse_mean"]))
            continue
        norm_a, norm_b = max_norm(ra), max_norm(rb)
        rows.append(dict(
            row, only=None, mse_a=ra["final_mse_mean"], mse_b=rb["final_mse_mean"],
            mse_ratio=_ratio(ra["final_mse_mean"], rb["final_mse_mean"]),
            norm_a=norm_a, norm_b=norm_b, norm_ratio=_ratio(norm_a, norm_b),
            time_ratio=_ratio(ra["da_step_seconds"], rb["da_step_seconds"]),
            rel_a=ra.get("final_rel_l2_mean"), rel_b=rb.get("final_rel_l2_mean"),
            rel_ratio=_ratio(ra.get("final_rel_l2_mean"), rb.get("final_rel_l2_mean")),
        ))
    rows.extend(dict(zip(RECORD_KEY, key), only="b", mse_b=rb["final_mse_mean"]) for key, rb in index_b.items())
    return rows


def format_comparison(a: ResultsDocument, b: ResultsDocument, rows: list[dict[str, Any]] | None = None, *,
                      force: bool = False) -> str:
    """A plain-text table of :func:`compare` (ratios B / A), with a note when the two files differ in setup
    (``force``: as :func:`compare`); with the relative L2 errors A and B and their ratio when a pair of records
    holds both."""
    rows = compare(a, b, force=force) if rows is None else rows
    relative = any(row.get("rel_a") is not None and row.get("rel_b") is not None for row in rows)
    notes = [f"note: not the same protocol settings (compared with --force): {d}" for d in protocol_differences(a, b)]
    for name in ("benchmark", "preset"):
        if a[name] != b[name]:
            notes.append(f"note: {name} differs: A={a[name]!r}, B={b[name]!r}")
    if a["dataset"].get("fingerprint") != b["dataset"].get("fingerprint"):
        notes.append("note: the two files were computed on different datasets (fingerprints differ)")
    head = (f"{'experiment':<14}{'model':<9}{'filter':<8}{'initial':<12}{'noise':>6}{'r':>4}{'T':>3}{'n':>4}"
            f"{'MSE A':>11}{'MSE B':>11}{'B/A':>8}{'|F| B/A':>9}{'time B/A':>10}"
            + (f"{'rel. L2 A':>11}{'rel. L2 B':>11}{'B/A':>8}" if relative else ""))
    lines = notes + [head, "-" * len(head)]
    for row in rows:
        n = "-" if row["n_members"] is None else str(row["n_members"])
        prefix = (f"{row['experiment']:<14}{row['model']:<9}{row['filter']:<8}{row['initial']:<12}"
                  f"{row['noise']:>6g}{row['r']:>4}{row['T']:>3}{n:>4}")
        if row["only"]:
            mse = row.get("mse_a") if row["only"] == "a" else row.get("mse_b")
            cols = (sci(mse), MISSING) if row["only"] == "a" else (MISSING, sci(mse))
            lines.append(f"{prefix}{cols[0]:>11}{cols[1]:>11}   only in {row['only'].upper()}")
        else:
            lines.append(f"{prefix}{sci(row['mse_a']):>11}{sci(row['mse_b']):>11}{sig(row['mse_ratio']):>8}"
                         f"{sig(row['norm_ratio']):>9}{sig(row['time_ratio']):>10}"
                         + (f"{percent(row.get('rel_a')):>11}{percent(row.get('rel_b')):>11}"
                            f"{sig(row.get('rel_ratio')):>8}"
                            if relative else ""))
    return "\n".join(lines)


__all__ = ["compare", "format_comparison"]
