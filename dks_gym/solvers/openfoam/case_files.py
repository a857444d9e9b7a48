"""OpenFOAM case files: the templates filled in, a block mesh's dictionary, a case written to disk.

The templates (``dks_gym/solvers/templates/``) hold every dictionary of the two cases as it is written, with
``$name`` placeholders; :func:`render` fills one in, :func:`block_mesh_dict` builds ``blockMeshDict`` and
:func:`write_case` writes a case's files, each atomically.
"""

from __future__ import annotations

import string
from collections.abc import Mapping, Sequence
from importlib import resources
from pathlib import Path

from ...atomic import atomic_write_text

#: The package holding ``templates/``: the solvers, beside the case modules that fill them in.
TEMPLATE_PACKAGE = "dks_gym.solvers"


def render(template: str, **values: str) -> str:
    """The case file ``templates/<template>`` (e.g. ``"cylinder/system/controlDict"``) with every ``$name``
    placeholder replaced by ``values[name]``; the values must match the placeholders exactly."""
    node = resources.files(TEMPLATE_PACKAGE) / "templates"
    for part in template.split("/"):
        node = node / part
    text = node.read_text(encoding="utf-8")
    pattern = string.Template.pattern
    wanted = {m.group("named") or m.group("braced") for m in pattern.finditer(text)} - {None}
    if wanted != set(values):
        raise ValueError(
            f"template {template} takes {sorted(wanted)}, got {sorted(values)}: missing "
            f"{sorted(wanted - set(values))}, unknown {sorted(set(values) - wanted)}"
        )
    return string.Template(text).substitute(values)


def block_mesh_dict(
    vertices: Sequence[str],
    blocks: Sequence[str],
    edges: Sequence[str],
    patches: Mapping[str, tuple[str, Sequence[str]]],
) -> str:
    """``system/blockMeshDict`` from its entry lines: vertices, blocks, curved edges (may be empty) and
    ``{patch: (type, face lines)}`` in the order they are written; the front and back are one empty patch."""
    boundary = "\n".join(
        f"    {name}\n    {{\n        type {kind};\n        faces\n        (\n"
        + "\n".join(faces)
        + "\n        );\n    }"
        for name, (kind, faces) in patches.items()
    )
    # The template's edge list ends right after the placeholder, so no edges leave no blank line.
    return render(
        "shared/system/blockMeshDict",
        vertices="\n".join(vertices),
        blocks="\n".join(blocks),
        edges="".join(f"{edge}\n" for edge in edges),
        boundary=boundary,
    )


def write_case(case_dir: Path, files: Mapping[str, str]) -> None:
    """Write ``{case-relative path: text}`` under ``case_dir``, creating directories; each file atomically,
    so a solver never reads a half-written dictionary."""
    for rel, text in files.items():
        target = Path(case_dir) / rel
        target.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(target, text)
