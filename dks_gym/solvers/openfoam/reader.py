"""Reading an OpenFOAM case with fluidfoam: its mesh geometry, its written times, its fields (binary or ascii)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .tools import OpenFOAMError, run_tool


@dataclass(frozen=True)
class MeshGeometry:
    """The 2D geometry of an OpenFOAM mesh as the resampler needs it (x, y only; z is the empty direction).

    ``boundary`` maps each non-empty patch to ``(face_centres (k, 2), owner_cells (k,))``.
    """

    cell_centres: np.ndarray
    cell_volumes: np.ndarray
    boundary: dict[str, tuple[np.ndarray, np.ndarray]]

    @property
    def n_cells(self) -> int:
        return int(self.cell_centres.shape[0])


def read_mesh(case_dir: Path) -> MeshGeometry:
    """Cell centres, cell volumes and boundary faces of the mesh in ``case_dir`` (blockMesh already run).

    Centres and volumes are OpenFOAM's own (``postProcess -func writeCellCentres / writeCellVolumes``),
    so the resampling uses the same geometry as the solver, curved edges included.
    """
    from fluidfoam import readscalar, readvector
    from fluidfoam.readof import OpenFoamFile

    case_dir = Path(case_dir)
    run_tool(case_dir, "postProcess", "-func", "writeCellCentres", "-time", "0", log_name="writeCellCentres")
    run_tool(case_dir, "postProcess", "-func", "writeCellVolumes", "-time", "0", log_name="writeCellVolumes")
    case = str(case_dir)
    centres = np.asarray(readvector(case, "0", "C", verbose=False), dtype=np.float64)[:2].T.copy()
    volumes = np.asarray(readscalar(case, "0", "V", verbose=False), dtype=np.float64)
    mesh_dir = case + "/constant/polyMesh/"
    owner = np.asarray(OpenFoamFile(mesh_dir, name="owner", verbose=False).values, dtype=np.int64)
    patches = OpenFoamFile(mesh_dir, name="boundary", verbose=False).boundaryface
    boundary: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for raw_name, entry in patches.items():
        name = raw_name.decode() if isinstance(raw_name, bytes) else str(raw_name)
        kind = entry.get(b"type", b"").decode() if isinstance(entry.get(b"type", b""), bytes) else ""
        n_faces = int(entry[b"nFaces"])
        if kind == "empty" or n_faces == 0:
            continue
        start = int(entry[b"startFace"])
        faces = np.asarray(readvector(case, "0", "C", boundary=name, verbose=False), dtype=np.float64)
        boundary[name] = (faces.reshape(3, -1)[:2].T.copy(), owner[start : start + n_faces].copy())
    return MeshGeometry(centres, volumes, boundary)


def time_directories(case_dir: Path) -> list[tuple[float, str]]:
    """``(time, directory name)`` of every written time in ``case_dir`` (0 included), sorted by time."""
    out = []
    for entry in Path(case_dir).iterdir():
        if not entry.is_dir():
            continue
        try:
            out.append((float(entry.name), entry.name))
        except ValueError:
            continue
    return sorted(out)


def select_times(case_dir: Path, times: Sequence[float], tol: float = 1e-6) -> list[str]:
    """Directory names of the written times matching ``times`` (within ``tol``); raise if one is missing."""
    written = time_directories(case_dir)
    values = np.array([t for t, _ in written])
    names = []
    for t in times:
        k = int(np.argmin(np.abs(values - t))) if values.size else -1
        if k < 0 or abs(values[k] - t) > tol * max(1.0, abs(t)):
            raise OpenFOAMError(
                f"{case_dir} has no output at t = {t:g} (written: {', '.join(n for _, n in written[:8])}...); "
                "check the solver log for an early stop"
            )
        names.append(written[k][1])
    return names


def read_frames(case_dir: Path, time_names: Sequence[str], fields: Sequence[tuple[str, int | None]]) -> np.ndarray:
    """Cell values (n_t, C, n_cells) float64 of ``fields`` = ``[(file, component or None), ...]``."""
    from fluidfoam import readfield

    case = str(case_dir)
    out = None
    for k, name in enumerate(time_names):
        cache: dict[str, np.ndarray] = {}
        for c, (field, component) in enumerate(fields):
            if field not in cache:
                cache[field] = np.asarray(readfield(case, name, field, verbose=False), dtype=np.float64)
            values = cache[field] if component is None else cache[field][component]
            if out is None:
                out = np.empty((len(time_names), len(fields), values.shape[-1]))
            out[k, c] = values
    if out is None:
        raise ValueError("read_frames needs at least one time and one field")
    return out
