"""PDEBench's 1D Burgers files: import them into one dks-gym schema file, and export 1D data to them.

The layout followed is PDEBench's (https://github.com/pdebench/PDEBench): one HDF5 file per viscosity,
named ``1D_Burgers_Sols_Nu<value>.hdf5`` (the generator ``pdebench/data_gen/data_gen_NLE/BurgersEq/
burgers_multi_solution_Hydra.py`` names it from the viscosity ``epsilon``), holding

* ``tensor``: float32 ``(n_traj, n_t, n_x)``, u of every trajectory at every saved time and cell;
* ``x-coordinate``: ``(n_x,)``, the cell centres;
* ``t-coordinate``: the saved times. The generator saves ``it_tot + 1`` of them for ``it_tot`` frames,
  and PDEBench's readers drop the last one (``f["t-coordinate"][:-1]``); both lengths are accepted.

PDEBench's loaders (``pdebench/models/fno/utils.py``, ``FNODataset``) read ``tensor``, ``x-coordinate``
and ``t-coordinate`` and split each file's trajectories themselves: the first ``int(n * test_ratio)``
(``test_ratio`` 0.1) are the test set, the rest train. The import does the same by default
(``test_fraction``), or holds out whole files (viscosities) as the test split (``test=``), which is the
dks-gym benchmarks' way: test parameters unseen in training. ``max_per_file`` keeps the first trajectories
of each file, as PDEBench's ``num_samples_max`` does (a PDEBench Burgers file holds 10,000).

The parameter is the viscosity in the file name, ``nu``. Mind PDEBench's equation: its diffusion term is
``(nu / pi) u_xx`` (``epsilon * pi_inv`` in the generator), where the dks-gym Burgers benchmark's is
``nu u_xx``; the value stored is the file name's. Grid, time step and coordinates are the files' (PDEBench:
1024 cells on [0, 1], dt 0.01), so the import is a custom benchmark, ``pdebench_burgers`` unless named
otherwise; a file written by :func:`export_pdebench` from the dks-gym Burgers data imports back as the
``burgers`` benchmark when named so.
"""

from __future__ import annotations

import re
from collections.abc import Iterator, Sequence
from pathlib import Path

import h5py
import numpy as np

from ..atomic import atomic_path
from .importing import (ImportedFlow, LayoutError, benchmark_name, check_finite, open_source, uniform_step,
                        write_imported)
from .reader import Dataset
from .schema import SPLITS

#: The viscosity in a PDEBench file name: ``..._Nu<value>.hdf5`` (or ``.h5``).
NU_IN_NAME = re.compile(r"_Nu(?P<nu>[^_/]+?)\.(?:hdf5|h5)$")
#: PDEBench's own test share of each file (``FNODataset(test_ratio=0.1)``).
PDEBENCH_TEST_RATIO = 0.1
DEFAULT_NAME = "pdebench_burgers"


def viscosity_from_name(path: str | Path) -> float:
    """The viscosity a PDEBench file name carries, e.g. 0.001 for ``1D_Burgers_Sols_Nu0.001.hdf5``."""
    path = Path(path)
    match = NU_IN_NAME.search(path.name)
    try:
        value = float(match.group("nu")) if match else float("nan")
    except ValueError:
        value = float("nan")
    if not (np.isfinite(value) and value > 0):
        raise LayoutError(f"{path}: the file name carries no viscosity; PDEBench names its 1D Burgers files "
                          "'1D_Burgers_Sols_Nu<value>.hdf5' (e.g. 1D_Burgers_Sols_Nu0.001.hdf5): rename the file so")
    return value


def _inspect(path: Path) -> tuple[int, np.ndarray, np.ndarray]:
    """(n_traj, time (n_t,), x (n_x,)) of one file, checked against PDEBench's 1D layout."""
    where = str(path)
    with open_source(path) as f:
        for name in ("tensor", "x-coordinate", "t-coordinate"):
            if name not in f or not isinstance(f[name], h5py.Dataset):
                raise LayoutError(f"{where}: missing dataset {name!r} (PDEBench's 1D files hold 'tensor' "
                                  "(n_traj, n_t, n_x), 'x-coordinate' and 't-coordinate')")
        tensor, x, t = f["tensor"], np.asarray(f["x-coordinate"], np.float64), np.asarray(f["t-coordinate"], np.float64)
        if tensor.ndim != 3:
            raise LayoutError(f"{where}: dataset 'tensor' has shape {tensor.shape}; a 1D file holds (n_traj, n_t, n_x) "
                              "(2D and 3D PDEBench files are not read here)")
        n_traj, n_t, n_x = tensor.shape
        if x.shape != (n_x,):
            raise LayoutError(f"{where}: dataset 'x-coordinate' has shape {x.shape}; 'tensor' needs ({n_x},)")
        if t.shape not in ((n_t,), (n_t + 1,)):
            raise LayoutError(f"{where}: dataset 't-coordinate' has shape {t.shape}; 'tensor' needs ({n_t},) or "
                              f"({n_t + 1},) (PDEBench saves one time more than it has frames)")
        time = t[:n_t]
        uniform_step(time, f"{where}: 't-coordinate'")
    return n_traj, time, x


def _split_rows(n: int, held_out: bool, test_fraction: float) -> dict[str, np.ndarray]:
    """Which of a file's ``n`` kept trajectories go to each split."""
    if held_out:
        return {"train": np.arange(0), "test": np.arange(n)}
    n_test = int(n * test_fraction)  # PDEBench's rule: the first int(n * ratio) are test
    return {"train": np.arange(n_test, n), "test": np.arange(n_test)}


def read_pdebench(files: Sequence[str | Path], *, test: Sequence[str | Path] = (),
                  test_fraction: float | None = None, max_per_file: int | None = None,
                  name: str = DEFAULT_NAME) -> ImportedFlow:
    """Check PDEBench 1D Burgers ``files`` (and ``test`` files) and describe them as an :class:`ImportedFlow`
    (trajectories read lazily); the arguments are :func:`import_pdebench`'s."""
    test_paths = [Path(p) for p in test]
    if test_paths and test_fraction is not None:
        raise ValueError("hold out either whole files (test=...) or a fraction of each file (test_fraction=...)")
    fraction = PDEBENCH_TEST_RATIO if test_fraction is None else float(test_fraction)
    if not 0 <= fraction < 1:
        raise ValueError(f"test_fraction must lie in [0, 1), got {test_fraction}")
    if max_per_file is not None and max_per_file < 1:
        raise ValueError(f"max_per_file must be at least 1, got {max_per_file}")
    held = {p.resolve() for p in test_paths}
    # Each file once (a test file may be among ``files`` too, under another spelling of its path).
    unique: dict[Path, Path] = {}
    for path in [*map(Path, files), *test_paths]:
        unique.setdefault(path.resolve(), path)
    paths = list(unique.values())
    if not paths:
        raise ValueError("no PDEBench files given")
    described = []
    for path in paths:
        if not path.is_file():
            raise LayoutError(f"{path}: no such file")
        nu = viscosity_from_name(path)
        n_traj, time, x = _inspect(path)
        described.append((path, nu, min(n_traj, max_per_file or n_traj), time, x))
    first = described[0]
    for path, _, _, time, x in described[1:]:
        if len(time) != len(first[3]) or not np.allclose(time, first[3], rtol=1e-6, atol=0):
            raise LayoutError(f"{path}: its times ('t-coordinate') differ from {first[0]}'s; one import takes one grid")
        if x.shape != first[4].shape or not np.allclose(x, first[4], rtol=1e-6, atol=1e-12):
            raise LayoutError(f"{path}: its 'x-coordinate' differs from {first[0]}'s; one import takes one grid")
    # With files held out, the others are all train; else each file gives its first share to test.
    rows = {path: _split_rows(n, path.resolve() in held, 0.0 if held else fraction) for path, _, n, _, _ in described}
    params = {split: np.concatenate([np.full(len(rows[p][split]), nu) for p, nu, *_ in described]) for split in SPLITS}
    for split in SPLITS:
        if params[split].size == 0:
            how = ("name the files to hold out with test=... (--test FILE)" if split == "test"
                   else "keep some files out of test=...")
            raise LayoutError(f"the files give no {split} trajectories ({len(paths)} files); {how}")
    generator = {
        "name": "dks_gym.dataset.pdebench", "source": "PDEBench 1D Burgers", "parameter": "nu (file name)",
        "files": {split: [p.name for p, *_ in described if len(rows[p][split])] for split in SPLITS},
        "test": "whole files" if held else f"first int(n * {fraction:g}) of each file",
        "max_per_file": max_per_file,
    }
    return ImportedFlow(name=benchmark_name(name), channels=("u",), param_name="nu", time=first[3], coords=(first[4],),
                        params=params, trajectories=_trajectories([p for p, *_ in described], rows),
                        generator=generator)


def _trajectories(paths: list[Path], rows: dict[Path, dict[str, np.ndarray]]) -> Iterator[tuple[str, int, np.ndarray]]:
    for split in SPLITS:
        i = 0
        for path in paths:
            if not len(rows[path][split]):
                continue
            with h5py.File(path, "r") as f:
                tensor = f["tensor"]
                for index in rows[path][split]:
                    u = np.asarray(tensor[int(index)], dtype=np.float32)[:, None]  # (n_t, 1, n_x)
                    yield split, i, check_finite(u, f"{path}: trajectory {index}")
                    i += 1


def import_pdebench(files: Sequence[str | Path], out: str | Path, *, test: Sequence[str | Path] = (),
                    test_fraction: float | None = None, max_per_file: int | None = None,
                    name: str = DEFAULT_NAME, overwrite: bool = False) -> Path:
    """Import PDEBench 1D Burgers ``files`` into the dks-gym schema file ``out``; return ``out``.

    The test split is either the ``test`` files (whole viscosities, added to ``files`` if not among them) or,
    without them, the first ``int(n * test_fraction)`` trajectories of each file (PDEBench's own rule,
    default 0.1). ``max_per_file`` keeps each file's first trajectories only. ``name``: the benchmark name
    (``burgers`` restores the dks-gym Burgers benchmark, whose grid and dt the files must then have). Every
    file is checked before anything is written; a file that breaks the layout raises
    :class:`~dks_gym.dataset.importing.LayoutError` naming what is missing.
    """
    flow = read_pdebench(files, test=test, test_fraction=test_fraction, max_per_file=max_per_file, name=name)
    return write_imported(flow, out, overwrite=overwrite)


def export_pdebench(dataset: Dataset | str | Path, out_dir: str | Path) -> dict[str, list[Path]]:
    """Write a 1D single-channel dks-gym dataset (Burgers) as PDEBench files: ``out_dir/train`` and
    ``out_dir/test``, one ``1D_Burgers_Sols_Nu<value>.hdf5`` per viscosity (the exact value, ``repr``) with
    its trajectories in order; return the files of each split in order. ``out_dir`` appears whole or not at
    all, and must not exist yet (or be empty)."""
    ds = dataset if isinstance(dataset, Dataset) else Dataset(dataset)
    if len(ds.grid) != 1 or len(ds.channels) != 1:
        raise ValueError(f"PDEBench's 1D Burgers layout holds one channel on a 1D grid; {ds.path} has channels "
                         f"{list(ds.channels)} on the grid {ds.grid}")
    out_dir = Path(out_dir)
    if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
        raise FileExistsError(f"{out_dir} exists and is not an empty folder; choose a new one")
    # PDEBench saves one time more than it has frames (module docstring).
    t = np.append(ds.time, ds.time[-1] + ds.dt).astype(np.float32)
    written: dict[str, list[Path]] = {}
    with atomic_path(out_dir, directory=True) as tmp:
        for split in SPLITS:
            (tmp / split).mkdir()
            params = ds.params(split)
            for value in dict.fromkeys(params.tolist()):
                name = f"1D_Burgers_Sols_Nu{value!r}.hdf5"
                with h5py.File(tmp / split / name, "w") as f:
                    f.create_dataset("tensor", data=np.stack([ds.trajectory(split, int(i))[:, 0]
                                                              for i in np.flatnonzero(params == value)]))
                    f.create_dataset("x-coordinate", data=np.asarray(ds.coords[0], dtype=np.float32))
                    f.create_dataset("t-coordinate", data=t)
                written.setdefault(split, []).append(out_dir / split / name)
    return written
