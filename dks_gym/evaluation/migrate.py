"""``python -m dks_gym.evaluation.migrate PATH...``: name the protocol in results files of an older dks-gym.

Each results document given, or found under a folder given (``results.json.gz``, ``placement.json.gz`` and
their plain ``.json`` forms), is loaded, stamped with its benchmark's protocol
(:func:`~dks_gym.evaluation.conformance.stamp_protocol`: the protocol block, the records that leave it
marked) and written back byte-reproducibly when that changed it; nothing else in the file changes. A file
that names a protocol already is stamped again (the same bytes unless the protocol's fields changed).
"""

from __future__ import annotations

import copy
import sys
from collections.abc import Iterable, Sequence
from pathlib import Path

from .conformance import stamp_protocol
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


def migrate_file(path: str | Path) -> bool:
    """Stamp the protocol into one results file; return whether the file changed."""
    doc = load_results(path)
    stamped = stamp_protocol(copy.deepcopy(doc))
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
        print(f"stamped {path}")
    print(f"{len(changed)} of {len(files)} results files changed")
    return 0


__all__ = ["RESULTS_NAMES", "main", "migrate", "migrate_file", "results_files"]

if __name__ == "__main__":
    sys.exit(main())
