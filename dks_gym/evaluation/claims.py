"""The paper's qualitative claims (Section IV), evaluated on the records of the main experiment.

:func:`qualitative_checks` gives each claim, whether this run's records bear it out (None where they cannot
say) and the numbers that decide it; the main experiment prints them under its tables.
"""

from __future__ import annotations

import math

from .figures import MODEL_LABELS, MODEL_ORDER
from .formatting import fixed, sci
from .tabulate import Records, max_norm

MODELS = MODEL_ORDER  # koopman, pdmd, mlp, xlstm
NEURAL = ("koopman", "mlp", "xlstm")  # the models sharing the encoder-decoder: only the latent map differs


def qualitative_checks(records: Records) -> list[tuple[str, bool | None, str]]:
    """The paper's qualitative claims evaluated on the main experiment: (claim, holds or None, evidence)."""
    checks: list[tuple[str, bool | None, str]] = []
    for initial in ("approximate", "exact"):
        ekf = {m: records.find(experiment="main", model=m, filter="ekf", initial=initial) for m in MODELS}
        fwd = {m: records.find(experiment="main", model=m, filter="forward", initial=initial) for m in MODELS}
        if not all(ekf.values()) or not all(fwd.values()):
            continue
        error = {m: ekf[m]["final_mse_mean"] for m in MODELS}

        def lowest(models: tuple[str, ...]) -> str:
            return min(models, key=lambda m: math.inf if error[m] is None else error[m])

        checks.append((f"Koopman has the lowest EKF error ({initial} IC)", lowest(MODELS) == "koopman",
                       ", ".join(f"{MODEL_LABELS[m]} {sci(error[m])}" for m in MODELS)))
        claim = f"Koopman has the lowest EKF error of the three models sharing the encoder-decoder ({initial} IC)"
        checks.append((claim, lowest(NEURAL) == "koopman",
                       ", ".join(f"{MODEL_LABELS[m]} {sci(error[m])}" for m in NEURAL)))
        for m, lowers in (("koopman", True), ("pdmd", True), ("mlp", False), ("xlstm", False)):
            a, b = fwd[m]["final_mse_mean"], ekf[m]["final_mse_mean"]
            holds = None if a is None or b is None else (b < a if lowers else b > a)
            claim = (f"EKF lowers the error of {MODEL_LABELS[m]} ({initial} IC)" if lowers else
                     f"EKF raises the error of {MODEL_LABELS[m]} ({initial} IC; paper: in most cases)")
            checks.append((claim, holds, f"forward {sci(a)} -> EKF {sci(b)}"))
    norms = {m: max(filter(None, [max_norm(r) for r in records.select(model=m, r=32, T=1)]), default=None)
             for m in MODELS}
    if norms["koopman"] is not None:
        checks.append(("Koopman operator norm <= 1 (to 1e-5)", norms["koopman"] <= 1 + 1e-5,
                       f"max ||K|| = {fixed(norms['koopman'], 6)}"))
    for m in ("mlp", "xlstm"):
        if norms[m] is not None:
            checks.append((f"{MODEL_LABELS[m]} forecast Jacobian norm exceeds 1", norms[m] > 1,
                           f"max_k ||F_k|| = {fixed(norms[m], 3)}"))
    return checks


__all__ = ["qualitative_checks"]
