"""How every table of dks-gym prints a number: one place, so one value prints the same in the reproduce
tables, the demo, the placement ranking, ``dks-gym compare`` and the README's results.

Errors and other scores print with three significant digits (:func:`sci`): plainly between 0.01 and 1000,
in scientific notation outside (``1.29e+03``, ``3.90e-04``); a missing or non-finite value prints as ``-``.
Ratios and times print with three significant digits (:func:`sig`), fractions with fixed decimals, log
ratios with their sign (:func:`signed`); a relative L2 error as a percentage (:func:`percent`) beside its
score 100 (1 - relative L2) (:func:`relative_score`); a confidence interval as ``[low, high]`` (:func:`interval`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

MISSING = "-"


def _finite(x: float | None) -> bool:
    return x is not None and math.isfinite(x)


def sci(x: float | None) -> str:
    """A score with three significant digits (``0.0123``, ``456``, ``1.29e+03``, ``3.90e-04``); ``-`` if missing."""
    if not _finite(x):
        return MISSING
    return f"{x:.3g}" if 1e-2 <= abs(x) < 1e3 else f"{x:.2e}"


def mean_std(mean: float | None, std: float | None, *, missing: str = MISSING) -> str:
    """``mean ± std`` with :func:`sci`; just the mean when ``std`` is None; ``missing`` when the mean is."""
    if mean is None:
        return missing
    return sci(mean) if std is None else f"{sci(mean)} ± {sci(std)}"


def interval(low: float | None, high: float | None, fmt: Callable[[float | None], str] = sci) -> str:
    """A confidence interval ``[low, high]``, its bounds printed by ``fmt`` (:func:`sci`: ``[0.0123, 0.0456]``;
    :func:`signed` for a log ratio); ``-`` if either is missing."""
    return f"[{fmt(low)}, {fmt(high)}]" if _finite(low) and _finite(high) else MISSING


def sig(x: float | None, digits: int = 3) -> str:
    """A ratio or a time with ``digits`` significant digits (``1.07``, ``0.5``, ``12.3``); ``-`` if missing."""
    return format(x, f".{digits}g") if _finite(x) else MISSING


def fixed(x: float | None, decimals: int = 3) -> str:
    """A fraction or a norm with a fixed number of decimals (``0.951``); ``-`` if missing."""
    return f"{x:.{decimals}f}" if _finite(x) else MISSING


def signed(x: float | None, decimals: int = 3) -> str:
    """A log ratio or a difference with its sign and a fixed number of decimals (``+0.123``, ``-1.50``)."""
    return f"{x:+.{decimals}f}" if _finite(x) else MISSING


def percent(x: float | None) -> str:
    """A fraction (a relative error) as a percentage with three significant digits, trailing zeros kept so that
    a column reads evenly (``12.3 %``, ``2.00 %``, ``0.456 %``, ``100 %``)."""
    return f"{format(100 * x, '#.3g').rstrip('.')} %" if _finite(x) else MISSING


def relative_score(relative: float | None, score: float | None) -> str:
    """A relative L2 error and its score 100 (1 - it), one decimal (``12.3 % (87.7)``, ``150 % (-50.0)``)."""
    return MISSING if not _finite(relative) else f"{percent(relative)} ({fixed(score, 1)})"


def cost(x: float | None, scale: float = 1.0, unit: str = "") -> str:
    """A cost (time, memory) scaled into ``unit``: three significant digits, ``1.2e-03`` below 0.01."""
    if not _finite(x):
        return MISSING
    v = x * scale
    return (f"{v:.3g}" if v >= 0.01 else f"{v:.1e}") + unit


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> str:
    """A GitHub markdown table (no trailing newline)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def text_table(header: Sequence[str], rows: Sequence[Sequence[str]], widths: Sequence[int],
               *, left: int = 1) -> str:
    """A plain-text table for a terminal: the first ``left`` columns left-aligned, the rest right-aligned in
    ``widths`` characters, a rule of dashes under the header (no trailing newline)."""
    def line(cells: Sequence[str]) -> str:
        return "".join(f"{c:<{w}}" if i < left else f"{c:>{w}}" for i, (c, w) in enumerate(zip(cells, widths)))

    head = line(header)
    return "\n".join([head, "-" * len(head)] + [line(row) for row in rows])


__all__ = ["MISSING", "cost", "fixed", "interval", "markdown_table", "mean_std", "percent", "relative_score", "sci",
           "sig", "signed", "text_table"]
