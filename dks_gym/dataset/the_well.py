"""The Well's HDF5 layout: import a folder of its files into one dks-gym schema file, and export ours to it
(:func:`export_the_well`; any flow given as arrays, e.g. a solver's output: :func:`write_the_well`).

The layout followed is The Well's own specification and reader:

* https://polymathic-ai.org/the_well/data_format/ (``docs/data_format.md`` of
  https://github.com/PolymathicAI/the_well): root attributes ``dataset_name``, ``grid_type``,
  ``n_spatial_dims``, ``n_trajectories``, ``simulation_parameters`` and one attribute per listed parameter;
  groups ``dimensions`` (attribute ``spatial_dims``; datasets ``time`` and one per spatial axis),
  ``boundary_conditions`` (one group per condition, attribute ``bc_type``: wall, open or periodic, and a
  ``mask``), ``scalars``, and ``t0_fields`` / ``t1_fields`` / ``t2_fields`` (attribute ``field_names``;
  float32 fields ``(n_traj, n_steps, *grid)`` with a trailing axis of D vector or D x D tensor components,
  each with the attributes ``sample_varying``, ``time_varying`` and ``dim_varying``: an axis a field does not
  vary along is left out of its shape);
* its reader ``WellDataset`` (``the_well/data/datasets.py``): a dataset's files are the ``*.h5`` and
  ``*.hdf5`` of ``DIR/data/train``, ``DIR/data/valid`` and ``DIR/data/test``, read in sorted order; a
  tensor field's components are named ``FIELD_x``, ``FIELD_y``, ``FIELD_xy`` ... (the spatial axes' names);
  ``scripts/check_thewell_formatting.py``, which requires every group above.

How it maps onto the dks-gym schema (:mod:`.schema`):

* channels: every time-varying field, the t0 fields first, then each t1 and t2 field's components as
  channels of their own, in ``field_names`` order; a field constant along an axis, in time or over the
  trajectories is repeated along it. Fields that are not time-varying (The Well's "constant fields") are
  not state and are skipped, and listed in the ``generator`` attribute; the ``scalars`` likewise (the
  parameter is read from the root attribute).
* the parameter: the root attribute of the one simulation parameter that differs between the files (or the
  one listed; ``param=`` chooses among several). Each file holds one value, for all its trajectories.
* splits: ``train`` and ``test`` as they are; The Well's ``valid`` is appended to ``train`` (default: the
  dks-gym training holds out its own validation trajectories from train) or dropped (``valid="drop"``).
  The statistics are the written train split's.
* dt: from ``dimensions/time``, which must be evenly spaced.
* the benchmark: ``dataset_name`` (or ``name=``) made a benchmark name; a paper benchmark's name (a round trip
  of our own data) restores that benchmark, any other name is a custom benchmark.
* cell types: The Well has none. :func:`export_the_well` writes ours as a t0 field ``cell_type`` that is
  constant in time and over the trajectories (what The Well's reader serves as a constant field), with the
  attributes ``dks_gym_cell_type_codes`` (JSON ``{name: code}``) and ``dks_gym_solid_codes``; the importer
  restores the cell types from a field carrying those attributes. A vector field's ``dks_gym_components``
  attribute names its components the way the exported channels were named (``u``, ``v`` rather than
  ``velocity_x``, ``velocity_y``). The Well's readers ignore attributes they do not know.
"""

from __future__ import annotations

import itertools
import json
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from ..atomic import atomic_path
from .importing import (ImportedFlow, LayoutError, benchmark_name, check_finite, open_source, uniform_step,
                        write_imported)
from .reader import Dataset
from .schema import AXES, SPLITS, as_str, as_str_list

SOURCE_SPLITS = ("train", "valid", "test")
FIELD_GROUPS = ("t0_fields", "t1_fields", "t2_fields")
ROOT_ATTRS = ("dataset_name", "grid_type", "n_spatial_dims", "n_trajectories", "simulation_parameters")
CELL_TYPE_ATTR = "dks_gym_cell_type_codes"
SOLID_CODES_ATTR = "dks_gym_solid_codes"
COMPONENTS_ATTR = "dks_gym_components"
#: Channel names exported as one t1 field ``velocity``: the first ``ndim`` of one of these, all present.
VELOCITY_COMPONENTS = (("u", "v", "w"), ("Ux", "Uy", "Uz"))
#: The paper benchmarks' boundaries, for the exported ``boundary_conditions``: (axis, bc_type, ends), ends
#: "both", "low" or "high" (the benchmark modules' docstrings). A benchmark not listed exports none.
BOUNDARIES = {
    "burgers": (("x", "PERIODIC", "both"),),
    "cylinder": (("x", "OPEN", "both"), ("y", "WALL", "both")),
    "dambreak": (("x", "WALL", "both"), ("y", "WALL", "low"), ("y", "OPEN", "high")),
}


@dataclass
class _Field:
    """One field of a file: where it is, how its stored shape relates to (n_traj, n_t, *grid, *components)."""

    group: str
    name: str
    order: int  # tensor order: 0, 1 or 2
    sample_varying: bool
    time_varying: bool
    dim_varying: tuple[bool, ...]
    channels: tuple[str, ...]


@dataclass
class _File:
    """What one file holds, checked against the layout."""

    path: Path
    dataset_name: str
    grid_type: str
    spatial_dims: tuple[str, ...]
    coords: tuple[np.ndarray, ...]
    time: np.ndarray
    n_traj: int
    parameters: dict[str, Any]
    fields: list[_Field]
    skipped: list[str]
    boundaries: dict[str, str]
    cell_type: np.ndarray | None = None
    cell_type_codes: dict[str, int] = field(default_factory=dict)
    solid_codes: tuple[int, ...] = ()

    @property
    def grid(self) -> tuple[int, ...]:
        return tuple(len(c) for c in self.coords)

    @property
    def channels(self) -> tuple[str, ...]:
        return tuple(c for f in self.fields for c in f.channels)


def _need(f: h5py.File | h5py.Group, name: str, what: str, where: str) -> Any:
    """``f[name]``, or a LayoutError saying that ``what`` is missing."""
    if name not in f:
        raise LayoutError(f"{where}: missing {what}")
    return f[name]


def _attr(obj: h5py.File | h5py.Group | h5py.Dataset, name: str, where: str) -> Any:
    if name not in obj.attrs:
        owner = "" if obj.name == "/" else f" of {obj.name.lstrip('/')!r}"
        raise LayoutError(f"{where}: missing {'root ' if not owner else ''}attribute {name!r}{owner}")
    return obj.attrs[name]


def _inspect(path: Path) -> _File:
    """Read one file's description (not its fields) and check it against The Well's layout."""
    where = str(path)
    with open_source(path) as f:
        for name in ROOT_ATTRS:
            _attr(f, name, where)
        parameters = {p: _attr(f, p, where) for p in as_str_list(f.attrs["simulation_parameters"],
                                                                 "simulation_parameters")}
        n_traj = int(f.attrs["n_trajectories"])
        dims = _need(f, "dimensions", "group 'dimensions'", where)
        spatial = tuple(as_str_list(_attr(dims, "spatial_dims", where), "spatial_dims"))
        if len(spatial) != int(f.attrs["n_spatial_dims"]) or not 1 <= len(spatial) <= len(AXES):
            raise LayoutError(f"{where}: 'dimensions' lists the axes {list(spatial)} for n_spatial_dims = "
                              f"{f.attrs['n_spatial_dims']}; the dks-gym schema takes 1 to {len(AXES)} axes")
        coords = tuple(_coordinate(dims, d, where) for d in spatial)
        time = _time(dims, n_traj, where)
        boundaries = {name: as_str(_attr(bc, "bc_type", where)).upper() for name, bc in
                      _need(f, "boundary_conditions", "group 'boundary_conditions'", where).items()}
        _need(f, "scalars", "group 'scalars'", where)
        skipped = [f"scalars/{s}" for s in as_str_list(f["scalars"].attrs.get("field_names", []), "field_names")]
        file = _File(path, as_str(f.attrs["dataset_name"]), as_str(f.attrs["grid_type"]), spatial, coords, time,
                     n_traj, parameters, [], skipped, boundaries)
        for order, group in enumerate(FIELD_GROUPS):
            g = _need(f, group, f"group {group!r}", where)
            for name in as_str_list(_attr(g, "field_names", where), "field_names"):
                _add_field(file, g, name, order, where)
    if not file.fields:
        raise LayoutError(f"{where}: no time-varying field in {', '.join(FIELD_GROUPS)}: nothing to import")
    return file


def _coordinate(dims: h5py.Group, name: str, where: str) -> np.ndarray:
    ds = _need(dims, name, f"dataset 'dimensions/{name}' (an axis named in 'spatial_dims')", where)
    if bool(ds.attrs.get("sample_varying", False)) or ds.ndim != 1:
        raise LayoutError(f"{where}: 'dimensions/{name}' has shape {ds.shape}; the dks-gym schema needs one "
                          "coordinate array per axis, the same for every trajectory")
    return np.asarray(ds, dtype=np.float64)


def _time(dims: h5py.Group, n_traj: int, where: str) -> np.ndarray:
    ds = _need(dims, "time", "dataset 'dimensions/time'", where)
    time = np.asarray(ds, dtype=np.float64)
    if bool(_attr(ds, "sample_varying", where)):
        if time.ndim != 2 or time.shape[0] != n_traj or not np.array_equal(time, np.broadcast_to(time[0], time.shape)):
            raise LayoutError(f"{where}: 'dimensions/time' varies between the trajectories; the dks-gym schema "
                              "has one time axis for all of them")
        time = time[0]
    if time.ndim != 1:
        raise LayoutError(f"{where}: 'dimensions/time' has shape {time.shape}; expected (n_steps,)")
    uniform_step(time, f"{where}: 'dimensions/time'")
    return time


def _add_field(file: _File, group: h5py.Group, name: str, order: int, where: str) -> None:
    """Check one field's flags and shape; record it as channels, as the cell type, or as skipped."""
    ds = _need(group, name, f"dataset '{group.name.lstrip('/')}/{name}' (listed in its 'field_names')", where)
    label = f"{where}: '{group.name.lstrip('/')}/{name}'"
    sample, timed = bool(_attr(ds, "sample_varying", where)), bool(_attr(ds, "time_varying", where))
    ndim = len(file.spatial_dims)
    varying = tuple(bool(v) for v in np.asarray(_attr(ds, "dim_varying", where)).reshape(-1))
    if len(varying) != ndim:
        raise LayoutError(f"{label} has dim_varying {list(varying)}; expected one flag per axis {file.spatial_dims}")
    expected = ((file.n_traj,) if sample else ()) + ((len(file.time),) if timed else ()) + tuple(
        n for n, v in zip(file.grid, varying) if v) + (ndim,) * order
    if ds.shape != expected:
        raise LayoutError(f"{label} has shape {ds.shape}; its flags (sample_varying {sample}, time_varying "
                          f"{timed}, dim_varying {list(varying)}) and the file's dimensions give {expected}")
    if CELL_TYPE_ATTR in ds.attrs:
        _cell_type(file, ds, sample or timed or order or not all(varying), label)
        return
    if not timed:
        file.skipped.append(f"{group.name.lstrip('/')}/{name}")
        return
    suffixes = ["".join(p) for p in itertools.product(file.spatial_dims, repeat=order)]
    channels = (tuple(as_str_list(ds.attrs[COMPONENTS_ATTR], COMPONENTS_ATTR)) if COMPONENTS_ATTR in ds.attrs
                else tuple(f"{name}_{s}" if s else name for s in suffixes))
    if len(channels) != len(suffixes):
        raise LayoutError(f"{label}: attribute {COMPONENTS_ATTR!r} names {len(channels)} components, not "
                          f"{len(suffixes)}")
    file.fields.append(_Field(group.name.lstrip("/"), name, order, sample, timed, varying, channels))


def _cell_type(file: _File, ds: h5py.Dataset, varies: bool, label: str) -> None:
    values = np.asarray(ds)
    if varies or not np.array_equal(values, np.round(values)):
        raise LayoutError(f"{label} carries {CELL_TYPE_ATTR!r} but is not a constant scalar field of integer codes "
                          "on the whole grid (sample_varying and time_varying False, dim_varying all True)")
    file.cell_type = values.astype(np.int8)
    file.cell_type_codes = {str(k): int(v) for k, v in json.loads(as_str(ds.attrs[CELL_TYPE_ATTR])).items()}
    file.solid_codes = tuple(int(c) for c in np.asarray(ds.attrs.get(SOLID_CODES_ATTR, [])).reshape(-1))


def split_files(root: str | Path) -> dict[str, list[Path]]:
    """The files of each of The Well's splits under ``root`` (``root/data/SPLIT`` or ``root/SPLIT``), sorted
    by path as The Well's reader does; ``train`` and ``test`` must hold files, ``valid`` may be absent."""
    root = Path(root)
    base = next((b for b in (root / "data", root) if (b / "train").is_dir()), None)
    if base is None:
        raise LayoutError(f"{root}: no folder 'data/train' (nor 'train'); The Well keeps a dataset's files in "
                          "DIR/data/train, DIR/data/valid and DIR/data/test")
    out = {}
    for split in SOURCE_SPLITS:
        folder = base / split
        files = sorted({*folder.glob("*.h5"), *folder.glob("*.hdf5")}) if folder.is_dir() else []
        if split != "valid" and not files:
            raise LayoutError(f"{folder}: no .hdf5 or .h5 files (the {split!r} split of The Well's layout)")
        out[split] = files
    return out


def _choose_parameter(files: list[_File], param: str | None) -> str:
    """The simulation parameter that becomes the dks-gym parameter."""
    listed = list(files[0].parameters)
    for file in files[1:]:
        if list(file.parameters) != listed:
            raise LayoutError(f"{file.path}: simulation_parameters {list(file.parameters)} differ from "
                              f"{files[0].path}'s {listed}")
    if param is not None:
        if param not in listed:
            raise ValueError(f"parameter {param!r} is not one of the files' simulation_parameters {listed}")
        return param
    if len(listed) == 1:
        return listed[0]
    varying = [p for p in listed if len({repr(np.asarray(f.parameters[p]).tolist()) for f in files}) > 1]
    if len(varying) != 1:
        raise ValueError(f"the files list the simulation parameters {listed}, and {len(varying)} of them "
                         f"({varying}) differ between the files; choose the parameter with param= (--param)")
    return varying[0]


def _parameter_value(file: _File, param: str) -> float:
    try:
        value = float(np.asarray(file.parameters[param]).reshape(()))
    except (TypeError, ValueError) as exc:
        raise LayoutError(f"{file.path}: simulation parameter {param!r} is {file.parameters[param]!r}, not one "
                          "number (each file holds one value of it)") from exc
    if not np.isfinite(value):
        raise LayoutError(f"{file.path}: simulation parameter {param!r} is {value}")
    return value


def _check_alike(files: list[_File]) -> None:
    """Every file describes the same dataset: name, axes, grid, time, channels and cell types."""
    first = files[0]
    for file in files[1:]:
        for what, a, b in (("dataset_name", file.dataset_name, first.dataset_name),
                           ("spatial_dims", file.spatial_dims, first.spatial_dims),
                           ("grid", file.grid, first.grid), ("channels", file.channels, first.channels),
                           ("cell-type codes", file.cell_type_codes, first.cell_type_codes)):
            if a != b:
                raise LayoutError(f"{file.path}: {what} {a} differ from {first.path}'s {b}; one import takes one "
                                  "dataset")
        if len(file.time) != len(first.time) or not np.allclose(file.time, first.time, rtol=1e-6, atol=0):
            raise LayoutError(f"{file.path}: 'dimensions/time' differs from {first.path}'s")
        if (file.cell_type is None) != (first.cell_type is None) or (
                file.cell_type is not None and not np.array_equal(file.cell_type, first.cell_type)):
            raise LayoutError(f"{file.path}: its cell types differ from {first.path}'s")


def _read_trajectory(f: h5py.File, file: _File, index: int) -> np.ndarray:
    """Trajectory ``index`` of an open file as (n_t, C, *grid) float32, every field broadcast to full shape."""
    n_t, grid, ndim = len(file.time), file.grid, len(file.grid)
    parts = []
    for fl in file.fields:
        values = np.asarray(f[fl.group][fl.name][index] if fl.sample_varying else f[fl.group][fl.name][()],
                            dtype=np.float32)
        if not fl.time_varying:
            values = values[None]
        # Axes a field is constant along are absent from its shape: put them back with length 1, then broadcast.
        kept = tuple(n if v else 1 for n, v in zip(grid, fl.dim_varying))
        values = values.reshape((n_t if fl.time_varying else 1,) + kept + (ndim,) * fl.order)
        values = np.broadcast_to(values, (n_t, *grid) + (ndim,) * fl.order).reshape(n_t, *grid, -1)
        parts.append(np.moveaxis(values, -1, 1))
    fields = np.concatenate(parts, axis=1)
    return check_finite(np.ascontiguousarray(fields), f"{file.path}: trajectory {index}")


def _trajectories(files: dict[str, list[_File]]) -> Iterator[tuple[str, int, np.ndarray]]:
    for split in SPLITS:
        i = 0
        for file in files[split]:
            with h5py.File(file.path, "r") as f:
                for index in range(file.n_traj):
                    yield split, i, _read_trajectory(f, file, index)
                    i += 1


def read_the_well(root: str | Path, *, param: str | None = None, valid: str = "train",
                  name: str | None = None) -> ImportedFlow:
    """Check every file of The Well's dataset folder ``root`` and describe it as an :class:`ImportedFlow`
    (trajectories read lazily); ``param``, ``valid`` and ``name``: see :func:`import_the_well`."""
    if valid not in ("train", "drop"):
        raise ValueError(f"valid must be 'train' (append The Well's valid split to train) or 'drop', got {valid!r}")
    paths = split_files(root)
    described = {split: [_inspect(p) for p in paths[split]] for split in SOURCE_SPLITS}
    every = [f for split in SOURCE_SPLITS for f in described[split]]
    _check_alike(every)
    chosen = _choose_parameter(every, param)
    files = {"train": described["train"] + (described["valid"] if valid == "train" else []),
             "test": described["test"]}
    params = {split: np.concatenate([np.full(f.n_traj, _parameter_value(f, chosen)) for f in files[split]])
              for split in SPLITS}
    first = every[0]
    generator = {
        "name": "dks_gym.dataset.the_well", "source": "The Well", "dataset_name": first.dataset_name,
        "grid_type": first.grid_type, "parameter": chosen, "valid": valid,
        "files": {split: [p.name for p in paths[split]] for split in SOURCE_SPLITS},
        "skipped": sorted({s for f in every for s in f.skipped}),
        "boundary_conditions": first.boundaries,
    }
    return ImportedFlow(
        name=benchmark_name(name if name is not None else first.dataset_name), channels=first.channels,
        param_name=chosen, time=first.time, coords=first.coords, params=params, trajectories=_trajectories(files),
        generator=generator, cell_type=first.cell_type, cell_type_codes=first.cell_type_codes,
        solid_codes=first.solid_codes,
    )


def import_the_well(root: str | Path, out: str | Path, *, param: str | None = None, valid: str = "train",
                    observed: str | None = None, name: str | None = None, overwrite: bool = False) -> Path:
    """Import The Well's dataset folder ``root`` into the dks-gym schema file ``out``; return ``out``.

    ``param``: the simulation parameter to keep (default: the only one, or the only one that differs between
    the files). ``valid``: "train" appends The Well's valid split to train, "drop" leaves it out. ``observed``:
    the observed channel of a custom benchmark (default: the first channel). ``name``: the benchmark name
    (default: the files' ``dataset_name``). Every file is checked before anything is written; a file that
    breaks the layout raises :class:`~dks_gym.dataset.importing.LayoutError` naming what is missing.
    """
    flow = read_the_well(root, param=param, valid=valid, name=name)
    return write_imported(flow, out, observed=observed, overwrite=overwrite)


def _vector_channels(channels: tuple[str, ...], ndim: int) -> tuple[str, ...]:
    """The channels exported as the t1 field ``velocity`` (none on a 1D grid: there u is a scalar field)."""
    if ndim < 2:
        return ()
    for names in VELOCITY_COMPONENTS:
        if all(c in channels for c in names[:ndim]):
            return names[:ndim]
    return ()


@dataclass(frozen=True)
class WellFlow:
    """A flow as arrays, to be written in The Well's layout by :func:`write_the_well`.

    ``params``: the parameter of each trajectory, per split (``train``, ``test``); ``fields(split, rows)``: those
    trajectories as ``(len(rows), n_t, C, *grid)`` in the order of ``channels``; ``boundaries``: (axis,
    bc_type, ends) triples as in :data:`BOUNDARIES`; the cell types and their codes as in the dks-gym schema.
    """

    name: str
    channels: tuple[str, ...]
    param_name: str
    time: np.ndarray
    coords: tuple[np.ndarray, ...]
    params: dict[str, np.ndarray]
    fields: Callable[[str, np.ndarray], np.ndarray]
    boundaries: tuple[tuple[str, str, str], ...] = ()
    cell_type: np.ndarray | None = None
    cell_type_codes: dict[str, int] = field(default_factory=dict)
    solid_codes: tuple[int, ...] = ()


def export_the_well(dataset: Dataset | str | Path, out_dir: str | Path) -> dict[str, list[Path]]:
    """Write a dks-gym dataset in The Well's layout (:func:`write_the_well`), its benchmark's boundaries
    (:data:`BOUNDARIES`) and cell types included; return the files of each split."""
    ds = dataset if isinstance(dataset, Dataset) else Dataset(dataset)
    bench = ds.benchmark
    return write_the_well(WellFlow(
        name=bench.name, channels=tuple(ds.channels), param_name=ds.param_name, time=ds.time, coords=tuple(ds.coords),
        params={split: ds.params(split) for split in SPLITS},
        fields=lambda split, rows: np.stack([ds.trajectory(split, int(i)) for i in rows]),
        boundaries=BOUNDARIES.get(bench.name, ()), cell_type=ds.cell_type,
        cell_type_codes=dict(bench.cell_type_codes), solid_codes=tuple(bench.solid_codes)), out_dir)


def write_the_well(flow: WellFlow, out_dir: str | Path) -> dict[str, list[Path]]:
    """Write ``flow`` in The Well's layout: ``out_dir/data/train`` and ``out_dir/data/test``, one file per
    parameter value (its trajectories in their order, files named in the split's order); return the files of
    each split. The velocity components become the t1 field ``velocity``, the other channels t0 fields, the
    cell types a constant t0 field (module docstring). ``out_dir`` appears whole or not at all, and must not
    exist yet (or be empty)."""
    out_dir = Path(out_dir)
    if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
        raise FileExistsError(f"{out_dir} exists and is not an empty folder; choose a new one")
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    written: dict[str, list[Path]] = {}
    with atomic_path(out_dir, directory=True) as tmp:
        for split in SPLITS:
            params = np.asarray(flow.params[split], dtype=np.float64)
            values = list(dict.fromkeys(params.tolist()))
            (tmp / "data" / split).mkdir(parents=True)
            for k, value in enumerate(values):
                name = f"{flow.name}_{k:04d}_{benchmark_name(flow.param_name)}_{value:.6g}.hdf5"
                _export_file(flow, split, np.flatnonzero(params == value), value, tmp / "data" / split / name)
                written.setdefault(split, []).append(out_dir / "data" / split / name)
    return written


def _export_file(flow: WellFlow, split: str, rows: np.ndarray, value: float, path: Path) -> None:
    ndim = len(flow.coords)
    dims = AXES[:ndim]
    vector = _vector_channels(flow.channels, ndim)
    scalars = [c for c in flow.channels if c not in vector]
    with h5py.File(path, "w") as f:
        f.attrs.update({"dataset_name": flow.name, "grid_type": "cartesian", "n_spatial_dims": ndim,
                        "n_trajectories": len(rows), "simulation_parameters": [flow.param_name],
                        flow.param_name: float(value)})
        g = f.create_group("dimensions")
        g.attrs["spatial_dims"] = list(dims)
        g.create_dataset("time", data=np.asarray(flow.time, dtype=np.float32)).attrs["sample_varying"] = False
        for axis, values in zip(dims, flow.coords):
            g.create_dataset(axis, data=np.asarray(values, dtype=np.float32)).attrs.update(
                {"sample_varying": False, "time_varying": False})
        _export_boundaries(f.create_group("boundary_conditions"), flow.boundaries,
                           dict(zip(dims, (len(c) for c in flow.coords))))
        f.create_group("scalars").attrs["field_names"] = []
        flags = {"dim_varying": [True] * ndim, "sample_varying": True, "time_varying": True}
        t0 = f.create_group("t0_fields")
        fields = np.asarray(flow.fields(split, rows), dtype=np.float32)  # (n, n_t, C, *grid)
        for c in scalars:
            t0.create_dataset(c, data=fields[:, :, flow.channels.index(c)]).attrs.update(flags)
        if flow.cell_type is not None:
            ct = t0.create_dataset("cell_type", data=flow.cell_type.astype(np.float32))
            ct.attrs.update({"dim_varying": [True] * ndim, "sample_varying": False, "time_varying": False,
                             CELL_TYPE_ATTR: json.dumps(flow.cell_type_codes, sort_keys=True),
                             SOLID_CODES_ATTR: list(flow.solid_codes)})
        t0.attrs["field_names"] = scalars + (["cell_type"] if flow.cell_type is not None else [])
        t1 = f.create_group("t1_fields")
        t1.attrs["field_names"] = ["velocity"] if vector else []
        if vector:
            components = np.stack([fields[:, :, flow.channels.index(c)] for c in vector], axis=-1)
            t1.create_dataset("velocity", data=components).attrs.update({**flags, COMPONENTS_ATTR: list(vector)})
        f.create_group("t2_fields").attrs["field_names"] = []


def _export_boundaries(group: h5py.Group, boundaries: tuple[tuple[str, str, str], ...], sizes: dict[str, int]) -> None:
    for axis, kind, ends in boundaries:
        mask = np.zeros(sizes[axis], dtype=bool)
        mask[[0, -1] if ends == "both" else [0] if ends == "low" else [-1]] = True
        bc = group.create_group(f"{axis}_{kind.lower()}_{ends}")
        bc.attrs.update({"associated_dims": [axis], "associated_fields": [], "bc_type": kind,
                         "sample_varying": False, "time_varying": False})
        bc.create_dataset("mask", data=mask)
