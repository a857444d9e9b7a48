"""A results document and its protocol: which protocol it names, where its runs leave it, whether two compare.

:func:`stamp_protocol` writes the benchmark's :class:`~dks_gym.benchmarks.protocol.Protocol` into a document
(every writer calls it: ``reproduce``, ``demo``, the placement harness, and the migration of older files)::

    "protocol": {"name": "dks-v1", "version": 1, <the protocol's fields>,
                 "deviations": {field: the run's value}}      # the whole run's settings outside the protocol

and marks each record whose own settings leave it with ``"protocol_deviations": [field, ...]`` (a record
without the mark follows the protocol). The whole run's settings (:func:`run_settings`) are read from the
document: benchmark, model preset, data preset, split, noise seeds, sensor budget, faults, scored channels.
A record's own (:func:`record_settings`): its noise level, initial condition and test trajectories. So
``reproduce``'s ``noise`` experiment (10 % and 30 %), the exact initial condition of ``main`` and the single
trajectory of ``timing`` are marked records of a file that names ``dks-v1``; its ``latent`` and
``multistep`` experiments vary the model (r, T), which a protocol leaves free, like the model and the filter,
and a placement policy's layout is what a placement run compares, so neither is a deviation.

:func:`protocol_differences` lists what makes two documents incomparable: ``dks-gym compare`` refuses them.
"""

from __future__ import annotations

from typing import Any

from ..benchmarks.protocol import ALL, PROTOCOLS, get_protocol
from .results import ResultsDocument, ResultsError

#: Where a document keeps its protocol (top level, after ``preset``).
PROTOCOL_KEY = "protocol"
#: Where a record lists the protocol fields it departs from (absent: none).
RECORD_MARK = "protocol_deviations"


class ProtocolMismatch(ResultsError):
    """Two results documents were not made under the same protocol settings; the message lists the fields."""


def run_settings(doc: ResultsDocument) -> dict[str, Any]:
    """The settings every run of ``doc`` shares, by protocol field (what ``deviations`` are judged on)."""
    cfg = doc["config"]
    seeds = cfg.get("noise_seeds")
    return {
        "benchmark": doc["benchmark"],
        "model_preset": doc["preset"],
        "data_preset": doc["dataset"].get("preset", cfg.get("data_preset")),
        "split": cfg.get("split"),
        # every writer filters the whole split at once; a record that does not is marked (record_settings)
        "trajectories": cfg.get("trajectories", ALL),
        "noise_seeds": [int(s) for s in seeds] if seeds is not None else [cfg.get("noise_seed")],
        "n_sensors": cfg.get("n_sensors"),
        "faults": cfg.get("faults"),
        "scored_channels": cfg.get("scored_channels"),
    }


def record_settings(doc: ResultsDocument, record: dict[str, Any]) -> dict[str, Any]:
    """One record's own settings, by protocol field: noise level, initial condition, test trajectories."""
    out: dict[str, Any] = {"noise_level": record["noise"], "initial": record["initial"]}
    n_test = doc["config"].get("n_test")
    if "trajectories" in record and n_test is not None:
        # a placement run repeats the split once per noise seed: the set of trajectories is what counts
        ran = sorted({int(i) for i in record["trajectories"]})
        out["trajectories"] = ALL if ran == list(range(int(n_test))) else ran
    return out


def stamp_protocol(doc: ResultsDocument) -> ResultsDocument:
    """Name the benchmark's protocol in ``doc`` and mark the records that leave it (in place; returns ``doc``).

    Idempotent: a stamped document is stamped again to the same bytes. A custom benchmark (your own flow) has
    no protocol: its document is left without one, as a file written before protocols is."""
    if str(doc["benchmark"]).lower() not in PROTOCOLS:
        return doc
    protocol = get_protocol(doc["benchmark"])
    block = dict(protocol.to_dict(), deviations=protocol.deviations(run_settings(doc)))
    for record in doc["records"]:
        marks = list(protocol.deviations(record_settings(doc, record)))
        if marks:
            record[RECORD_MARK] = marks
        else:
            record.pop(RECORD_MARK, None)
    # placed after "preset", so that a reader sees it at the top of the file
    rebuilt: dict[str, Any] = {}
    for key, value in doc.items():
        if key != PROTOCOL_KEY:
            rebuilt[key] = value
        if key == "preset":
            rebuilt[PROTOCOL_KEY] = block
    if PROTOCOL_KEY not in rebuilt:
        rebuilt[PROTOCOL_KEY] = block
    doc.clear()
    doc.update(rebuilt)
    return doc


def _name(block: dict[str, Any] | None) -> str:
    return "none" if block is None else f"{block.get('name')} v{block.get('version')}"


def protocol_differences(a: ResultsDocument, b: ResultsDocument) -> list[str]:
    """What keeps ``a`` and ``b`` from being compared, one ``"field: A=..., B=..."`` per difference.

    Empty when both name the same protocol, version and fields and their runs share the same settings
    (:func:`run_settings`), or when neither names a protocol (files written before protocols: as before)."""
    pa, pb = a.get(PROTOCOL_KEY), b.get(PROTOCOL_KEY)
    if pa is None and pb is None:
        return []
    if pa is None or pb is None:
        return [f"protocol: A={_name(pa)}, B={_name(pb)} (name the protocol of the older file with "
                "`python -m dks_gym.evaluation.migrate FILE`)"]
    out = [f"{k}: A={pa.get(k)!r}, B={pb.get(k)!r}" for k in ("name", "version") if pa.get(k) != pb.get(k)]
    fields = [k for k in dict.fromkeys([*pa, *pb]) if k not in ("name", "version", "deviations")]
    differ = [k for k in fields if pa.get(k) != pb.get(k)]
    out += [f"{k} (protocol): A={pa.get(k)!r}, B={pb.get(k)!r}" for k in differ]
    sa, sb = run_settings(a), run_settings(b)
    return out + [f"{k}: A={sa[k]!r}, B={sb[k]!r}" for k in sa if sa[k] != sb[k] and k not in differ]


def check_comparable(a: ResultsDocument, b: ResultsDocument) -> None:
    """Raise :class:`ProtocolMismatch` listing :func:`protocol_differences`, if any."""
    differ = protocol_differences(a, b)
    if differ:
        raise ProtocolMismatch("A and B were not made under the same protocol, so their records would pair runs "
                               f"that are not comparable: {'; '.join(differ)} (--force compares them anyway)")


__all__ = ["PROTOCOL_KEY", "RECORD_MARK", "ProtocolMismatch", "check_comparable", "protocol_differences",
           "record_settings", "run_settings", "stamp_protocol"]
