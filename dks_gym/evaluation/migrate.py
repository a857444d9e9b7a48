"""``python -m dks_gym.evaluation.migrate PATH...``: bring results files of an older dks-gym up to date.

Each results document given, or found under a folder given (``results.json.gz``, ``placement.json.gz`` and
their plain ``.json`` forms), is loaded, stamped with its benchmark's protocol
(:func:`~dks_gym.evaluation.conformance.stamp_protocol`: the protocol block, the records that leave it
marked), given the interval fields its records lack (:func:`add_intervals`: the interquartile mean and the
95 % bootstrap interval, computed from the per-episode values the records store) and written back
byte-reproducibly when that changed it; nothing else in the file changes. A file that names a protocol
already is stamped again (the same bytes unless the protocol's fields changed); interval fields a record
holds are kept as they are (a bootstrap may draw differently under another scipy), so a second run changes
nothing.
"""

from __future__ import annotations

import copy
import sys
from collections.abc import Iterable, Sequence
from pathlib import Path

from typing import Any

from .conformance import stamp_protocol
from .intervals import INTERVAL_SOURCES, interval_fields
from .results import RESULTS_FILE, load_results, save_results

#: The names results documents go by: reproduce's and the demo's, and the placement harness's
#: (``dks_gym_agents.records.PLACEMENT_FILE``, a later stage than this one; a test checks they agree).
RESULTS_NAMES = (RESULTS_FILE, "placement.json.gz", "results.json", "placement.json")


def results_files(paths: Iterable[str | Path]) -> list[Path]:
    """The results documents among ``paths``: files as given, folders searched for :data:`RESULTS_NAMES`."""
    out: list[Path] = []
    for path in map(Path, paths):
        if path.is_dir():
            out += sorted(p for name in RESULTS_NAMES for p in path.rglob(name))
        elif path.exists():
            out.append(path)
        else:
            raise FileNotFoundError(f"no results file or folder at {path}")
    return list(dict.fromkeys(out))


def add_intervals(doc: dict[str, Any]) -> dict[str, Any]:
    """Give each record the interval fields it lacks (:func:`~dks_gym.evaluation.intervals.interval_fields`,
    from its stored per-episode values), appended after its other fields; those it holds stay. In place."""
    for record in doc["records"]:
        wanted = [f"{prefix}_{kind}" for prefix, source in INTERVAL_SOURCES if record.get(source) is not None
                  for kind in ("iqm", "ci95")]
        if any(name not in record for name in wanted):
            for name, value in interval_fields(record).items():
                record.setdefault(name, value)
    return doc


def migrate_file(path: str | Path) -> bool:
    """Stamp the protocol into one results file and add its missing intervals; return whether it changed."""
    doc = load_results(path)
    stamped = add_intervals(stamp_protocol(copy.deepcopy(doc)))
    if stamped == doc and list(stamped) == list(doc):
        return False
    save_results(stamped, path)
    return True


def migrate(paths: Iterable[str | Path]) -> list[Path]:
    """Stamp every results file among ``paths`` (:func:`results_files`); return those that changed."""
    return [path for path in results_files(paths) if migrate_file(path)]


def main(argv: Sequence[str] | None = None) -> int:
    """The command line: migrate the files and folders named, print what changed."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help"):
        print(__doc__.splitlines()[0])
        return 0 if args else 2
    files = results_files(args)
    changed = [path for path in files if migrate_file(path)]
    for path in changed:
        print(f"migrated {path}")
    print(f"{len(changed)} of {len(files)} results files changed")
    return 0


__all__ = ["RESULTS_NAMES", "add_intervals", "main", "migrate", "migrate_file", "results_files"]

if __name__ == "__main__":
    sys.exit(main())
