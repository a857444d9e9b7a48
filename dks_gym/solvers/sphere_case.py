"""The sphere-wake case on the batched lattice Boltzmann solver (:mod:`dks_gym.solvers.lbm`).

Units: lengths in R (sphere radius), velocities in U (inflow speed), time in R/U, pressure kinematic
(p / rho) in U^2 relative to the outlet, so the numbers mean the same as in the cylinder benchmark.
Re = U D / nu with D = 2R.

Domain (the benchmark's, :mod:`dks_gym.benchmarks.sphere`): x in [-8R, 16R] (8R upstream of the
centre, 15R of wake behind the sphere's rear), y in [-4R, 4R], z in [-4R, 4R], sphere of radius R at
the origin; blockage pi R^2 / (8R)^2 = 4.9 %. Faces:

* x = -8R: velocity inlet, uniform u = (U, 0, 0) (non-equilibrium extrapolation);
* x = 16R + ``sponge`` (4R): pressure outlet, p = 0 (non-equilibrium extrapolation, velocity from the
  neighbour plane), behind an absorbing layer in 16R < x < 16R + ``sponge`` that relaxes the flow toward
  the uniform inflow state (the stored grid ends at 16R);
* y = +-4R: no-slip walls (half-way bounce-back), as in the paper's Fig. 2c;
* z = +-4R: periodic (the sphere repeats every 8R in z; no wall there, so the wake can turn freely).

Lattice with ``resolution`` = r nodes per R: x_i = -8 + i / r (i = 0..(24 + sponge) r, inlet and outlet
nodes on the faces), y_j = -4 + (j - 1/2) / r (j = 0..8 r + 1; j = 0 and 8 r + 1 are the wall nodes, so the
walls lie exactly at y = +-4), z_k = -4 + (k + 1/2) / r (k = 0..8 r - 1). Body nodes are those with
x^2 + y^2 + z^2 < R^2 (a staircase sphere; the sphere centre lies between nodes in y and z).

Run: impulsive start from u = U everywhere in the fluid plus a small off-axis bump in v behind the
sphere (so that shedding, where it exists, does not have to wait for round-off), ``spin_up`` R/U of
spin-up, then ``n_frames`` frames every ``frame_dt`` = 0.5 R/U. Each frame is interpolated
(trilinearly; pressure with weights over fluid nodes only, velocity with u = 0 on solid nodes) onto
the 64^3 cell centres of the benchmark grid; cells inside the body are set to 0. Drag and lift
coefficients C = F / (1/2 rho U^2 pi R^2) (momentum exchange on the staircase body, nominal R) are
recorded at every frame.
"""

from __future__ import annotations

import math
import time as _time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..benchmarks.base import Benchmark, GeneratedData, check_preset, interleaved_sweep
from . import lbm

EXTENT = ((-8.0, 16.0), (-4.0, 4.0), (-4.0, 4.0))
SETTING_KEYS = ("resolution", "u_lattice", "spin_up", "n_frames", "frame_dt", "smagorinsky", "perturbation",
                "sponge", "sponge_strength", "walls", "half_width")
# sponge: length (R) of the absorbing layer added behind the output domain; sponge_strength: its peak
# relaxation rate per step toward the uniform inflow state.
DEFAULTS: dict[str, Any] = {"frame_dt": 0.5, "smagorinsky": 0.15, "perturbation": 0.05, "sponge": 4.0,
                            "sponge_strength": 0.05, "walls": True, "half_width": 4.0}
# walls=False drops the no-slip y walls (the y faces become periodic) and half_width widens the y-z
# cross-section: both only for validating the drag against unconfined correlations (force-only runs);
# the benchmark always has its walls at y = +-4R.

GENERATOR_VERSION = "1"
# Solver settings per preset: lattice nodes per R, lattice inflow speed, spin-up (R/U) before the first
# frame, frames; trajectory counts (n_train, n_test).
PRESET_SETTINGS: dict[str, dict[str, Any]] = {
    "paper": {"resolution": 8, "u_lattice": 0.05, "spin_up": 50.0, "n_frames": 100},
    "small": {"resolution": 2, "u_lattice": 0.1, "spin_up": 10.0, "n_frames": 10},
}
PRESET_COUNTS = {"paper": (90, 11), "small": (4, 2)}


def lattice_axes(resolution: int, extension: float = 0.0, half_width: float = 4.0
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Node coordinates (x, y, z) in units of R for ``resolution`` nodes per R (outlet at 16 + extension;
    y and z in [-half_width, half_width], 4 R in the benchmark)."""
    r = int(resolution)
    n = round(2 * half_width * r)
    x = -8.0 + np.arange(round((24 + extension) * r) + 1) / r
    y = -half_width + (np.arange(n + 2) - 0.5) / r
    z = -half_width + (np.arange(n) + 0.5) / r
    return x, y, z


def geometry(resolution: int, extension: float = 0.0, walls: bool = True, half_width: float = 4.0
             ) -> tuple[np.ndarray, np.ndarray]:
    """(solid, body) node masks of the lattice (``walls=False``: no y walls, i.e. y periodic; validation only)."""
    x, y, z = lattice_axes(resolution, extension, half_width)
    if not walls:  # the two wall rows are dropped, so y is periodic with period 2 half_width like z
        y = y[1:-1]
    body = x[:, None, None] ** 2 + y[None, :, None] ** 2 + z[None, None, :] ** 2 < 1.0
    solid = body.copy()
    if walls:
        solid[:, [0, -1], :] = True
    return solid, body


def interpolation_matrix(nodes: np.ndarray, targets: np.ndarray, period: float | None = None) -> np.ndarray:
    """Linear interpolation weights (n_targets, n_nodes) from uniform ``nodes`` to ``targets``.

    With ``period`` the node set is periodic (targets outside the node range wrap around)."""
    h = nodes[1] - nodes[0]
    s = (targets - nodes[0]) / h
    lo = np.floor(s).astype(int)
    t = s - lo
    n = nodes.size
    m = np.zeros((targets.size, n))
    for k, (i, a) in enumerate(zip(lo, t)):
        for j, wgt in ((i, 1.0 - a), (i + 1, a)):
            if period is not None:
                j %= n
            elif not 0 <= j < n:
                if wgt > 1e-12:
                    raise ValueError("interpolation target outside the lattice")
                continue
            m[k, j] += wgt
    return m


class Resampler:
    """Lattice fields -> the benchmark's 64^3 cell centres (u, v, w, p in U and U^2)."""

    def __init__(self, resolution: int, coords: tuple[np.ndarray, ...], cell_type: np.ndarray, solid: np.ndarray,
                 device: torch.device, u_lattice: float, extension: float = 0.0) -> None:
        x, y, z = lattice_axes(resolution, extension)
        period = 8.0
        mats = [
            interpolation_matrix(x, coords[0]),
            interpolation_matrix(y, coords[1]),
            interpolation_matrix(z, coords[2], period=period),
        ]
        self.mats = [torch.as_tensor(m, dtype=torch.float32, device=device) for m in mats]
        fluid = torch.as_tensor(~solid, dtype=torch.float32, device=device)
        self.fluid = fluid
        self.weight = self._apply(fluid[None])[0]
        self.inside = torch.as_tensor(cell_type == 2, device=device)
        self.u_lattice = float(u_lattice)

    def _apply(self, a: torch.Tensor) -> torch.Tensor:
        # a: (N, nx, ny, nz) -> (N, 64, 64, 64)
        a = torch.einsum("Xx,nxyz->nXyz", self.mats[0], a)
        a = torch.einsum("Yy,nXyz->nXYz", self.mats[1], a)
        return torch.einsum("Zz,nXYz->nXYZ", self.mats[2], a)

    def __call__(self, rho: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """rho (B, *lattice), u (B, 3, *lattice) in lattice units -> (B, 4, 64, 64, 64) float32."""
        b = rho.shape[0]
        vel = self._apply(u.reshape(b * 3, *u.shape[2:])).reshape(b, 3, *self.inside.shape) / self.u_lattice
        p = lbm.CS2 * (rho - 1.0) * self.fluid / self.u_lattice**2
        p = self._apply(p) / self.weight.clamp_min(1e-6)
        out = torch.cat([vel, p[:, None]], dim=1)
        return out.masked_fill(self.inside, 0.0)


def steps_per(duration: float, resolution: int, u_lattice: float) -> int:
    """Lattice steps in ``duration`` R/U; must be an integer (choose r, U_lattice accordingly)."""
    n = duration * resolution / u_lattice
    if abs(n - round(n)) > 1e-6 or round(n) < 1:
        raise ValueError(
            f"{duration} R/U is {n:g} lattice steps at resolution {resolution} and u_lattice {u_lattice}; "
            "choose them so that it is a positive integer"
        )
    return round(n)


def describe(settings: dict[str, Any]) -> dict[str, Any]:
    """Lattice shape, step counts and memory per case of ``settings`` (for the file's metadata)."""
    s = {**DEFAULTS, **settings}
    r, ul = int(s["resolution"]), float(s["u_lattice"])
    shape = geometry(r, float(s["sponge"]), bool(s["walls"]), float(s["half_width"]))[0].shape
    n_spin = steps_per(float(s["spin_up"]), r, ul)
    n_frame = steps_per(float(s["frame_dt"]), r, ul)
    return {
        "shape": list(shape),
        "steps": {"spin_up": n_spin, "per_frame": n_frame, "total": n_spin + n_frame * (int(s["n_frames"]) - 1)},
        "bytes_per_case_eager": lbm.bytes_per_case("D3Q19", shape),
        "bytes_per_case_compiled": lbm.bytes_per_case("D3Q19", shape, compiled=True),
        "mach": ul / math.sqrt(lbm.CS2),
    }


@dataclass(frozen=True)
class SweepPlan:
    """What every batch of one sphere sweep shares: the lattice and its geometry, the cases' viscosities,
    the initial state, the step counts and what is recorded."""

    resolution: int
    u_lattice: float
    solid: np.ndarray
    body: np.ndarray
    nu: np.ndarray  # lattice viscosity of every case of the sweep
    sponge: np.ndarray | None  # absorber strengths along x
    smagorinsky: float
    u0: np.ndarray  # (3, *shape) initial velocity
    n_spin: int
    n_frame: int
    n_frames: int
    force_every: int | None  # lattice steps between force samples, None for none
    area: float  # 1/2 rho U^2 pi R^2 in lattice units, the force coefficients' denominator
    resampler: Resampler | None  # None: no fields are recorded
    device: torch.device
    compile: bool

    @property
    def shape(self) -> tuple[int, ...]:
        """The lattice's nodes (nx, ny, nz)."""
        return self.solid.shape

    @property
    def total(self) -> int:
        """Lattice steps from the start to the last frame."""
        return self.n_spin + self.n_frame * (self.n_frames - 1)

    @property
    def frame_steps(self) -> dict[int, int]:
        """``{lattice step: frame index}``."""
        return {self.n_spin + k * self.n_frame: k for k in range(self.n_frames)}


def plan_sweep(
    re: np.ndarray,
    s: dict[str, Any],
    coords: tuple[np.ndarray, ...],
    cell_type: np.ndarray,
    device: torch.device,
    compile: bool,
    fields: bool,
    force_every: int | None,
) -> SweepPlan:
    """The :class:`SweepPlan` of the Reynolds numbers ``re`` with the full settings ``s``."""
    r, ul = int(s["resolution"]), float(s["u_lattice"])
    ext = float(s["sponge"])
    hw = float(s["half_width"])
    if fields and (hw != 4.0 or not s["walls"]):
        raise ValueError("half_width and walls may only be changed for force-only validation runs (fields=False)")
    solid, body = geometry(r, ext, bool(s["walls"]), hw)
    x, y, z = lattice_axes(r, ext, hw)
    if not s["walls"]:
        y = y[1:-1]
    # Absorbing layer beyond the output domain (x > 16 R): strength rising as ((x - 16) / ext)^2 to sponge_strength.
    sponge = None
    if ext > 0:
        sponge = float(s["sponge_strength"]) * np.clip((x - EXTENT[0][1]) / ext, 0.0, 1.0) ** 2
    return SweepPlan(
        resolution=r, u_lattice=ul, solid=solid, body=body, nu=ul * 2.0 * r / re, sponge=sponge,
        smagorinsky=float(s["smagorinsky"]), u0=initial_velocity(x, y, z, ul, float(s["perturbation"])),
        n_spin=steps_per(float(s["spin_up"]), r, ul), n_frame=steps_per(float(s["frame_dt"]), r, ul),
        n_frames=int(s["n_frames"]), force_every=int(force_every) if force_every else None,
        area=0.5 * ul**2 * math.pi * r**2,
        resampler=Resampler(r, coords, cell_type, solid, device, ul, ext) if fields else None,
        device=device, compile=bool(compile),
    )  # fmt: skip


def initial_velocity(x: np.ndarray, y: np.ndarray, z: np.ndarray, u_lattice: float, perturbation: float) -> np.ndarray:
    """(3, nx, ny, nz) float32: U in the fluid plus a bump in v behind the sphere (x ~ 1.5 R, slightly off-axis)."""
    bump = np.exp(-((x[:, None, None] - 1.5) ** 2 + y[None, :, None] ** 2 + (z[None, None, :] - 0.25) ** 2) / 0.5)
    u0 = np.zeros((3, x.size, y.size, z.size), np.float32)
    u0[0] = u_lattice
    u0[1] = perturbation * u_lattice * bump
    return u0


def batch_size(plan: SweepPlan, grid: tuple[int, ...], max_batch: int | None) -> tuple[int, int]:
    """``(cases per batch, bytes per case)``: what fits the device and, with fields, half the host's free memory
    for one batch of frames; at most ``max_batch``."""
    per_case = lbm.bytes_per_case("D3Q19", plan.shape, compiled=plan.compile)
    size = lbm.max_batch(per_case, plan.device)
    if plan.resampler is not None:
        size = min(size, lbm.max_batch(plan.n_frames * 4 * int(np.prod(grid)) * 4, "cpu", fraction=0.5))
    if max_batch is not None:
        size = min(size, int(max_batch))
    return size, per_case


def run_batches(
    re: np.ndarray,
    settings: dict[str, Any],
    *,
    coords: tuple[np.ndarray, ...],
    cell_type: np.ndarray,
    device: str | torch.device = "cpu",
    compile: bool | None = None,
    max_batch: int | None = None,
    progress: bool = False,
    fields: bool = True,
    force_every: int | None = None,
    info: dict[str, Any] | None = None,
) -> Iterator[tuple[slice, dict[str, np.ndarray]]]:
    """Run the sphere at every Reynolds number in ``re`` batch by batch; yield ``(slice, results)``.

    Per batch: ``fields`` (b, n_frames, 4, *grid) float32 (if ``fields``), ``drag``, ``lift`` (y, wall
    normal) and ``lift_z`` (b, n_frames) coefficients at the frames, and with ``force_every`` (lattice
    steps) ``force_coefficients`` (b, n_samples, 3) from the start of the run. Only one batch of frames
    is held in memory. ``info`` (a dict, filled in) receives the run's numbers (steps, batch size, time).
    """
    s = {**DEFAULTS, **settings}
    re = np.atleast_1d(np.asarray(re, dtype=np.float64))
    dev = torch.device(device)
    if compile is None:
        compile = dev.type == "cuda"
    plan = plan_sweep(re, s, coords, cell_type, dev, compile, fields, force_every)
    size, per_case = batch_size(plan, cell_type.shape, max_batch)
    n = re.size
    info = {} if info is None else info
    info.update(lattice_shape=plan.shape, batch_size=size, bytes_per_case=per_case, nu_lattice=plan.nu,
                steps={"spin_up": plan.n_spin, "per_frame": plan.n_frame, "total": plan.total},
                lattice_updates=float(n) * float(np.prod(plan.shape)) * plan.total)
    if plan.force_every:
        every = plan.force_every
        info["force_time"] = np.arange(plan.total // every + 1) * every * plan.u_lattice / plan.resolution

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=plan.total * n, desc=f"sphere LBM r={plan.resolution}", unit="case-step", unit_scale=True)
    t0 = _time.perf_counter()
    for part in lbm.chunks(n, size):
        yield part, run_batch(plan, part, re, cell_type.shape, bar)
    if bar is not None:
        bar.close()
    info["seconds"] = _time.perf_counter() - t0


def run_batch(
    plan: SweepPlan, part: slice, re: np.ndarray, grid: tuple[int, ...], bar: Any = None
) -> dict[str, np.ndarray]:
    """Run the cases ``part`` of the sweep together on one lattice; return their records (see :func:`run_batches`)."""
    b = part.stop - part.start
    res: dict[str, np.ndarray] = {k: np.zeros((b, plan.n_frames)) for k in ("drag", "lift", "lift_z")}
    if plan.resampler is not None:
        res["fields"] = np.zeros((b, plan.n_frames, 4, *grid), np.float32)
    if plan.force_every:
        res["force_coefficients"] = np.zeros((b, plan.total // plan.force_every + 1, 3))
    ul = plan.u_lattice
    sim = lbm.LBM("D3Q19", plan.shape, plan.nu[part], solid=plan.solid, body=plan.body, inlet_velocity=(ul, 0.0, 0.0),
                  outlet=True, absorber=plan.sponge, smagorinsky=plan.smagorinsky, device=plan.device,
                  compile=plan.compile)  # fmt: skip
    sim.initialize(plan.u0)
    frame_steps = plan.frame_steps
    for step in range(plan.total + 1):
        if step > 0:
            sim.step()
            if bar is not None:
                bar.update(b)
        if plan.force_every and step % plan.force_every == 0:
            res["force_coefficients"][:, step // plan.force_every] = (sim.body_force() / plan.area).cpu().numpy()
        if step in frame_steps:
            record_frame(sim, plan, res, frame_steps[step], re[part])
    return res


def record_frame(sim: lbm.LBM, plan: SweepPlan, res: dict[str, np.ndarray], k: int, re: np.ndarray) -> None:
    """Store frame ``k`` of the batch ``sim`` (Reynolds numbers ``re``) in ``res``: the force coefficients and,
    with a resampler, the fields; a diverged case stops the run."""
    bad = ~sim.is_finite().cpu().numpy()
    if bad.any():
        raise RuntimeError(
            f"the lattice Boltzmann run diverged at Re = {re[bad]} (resolution {plan.resolution}, "
            f"u_lattice {plan.u_lattice}); use a finer lattice or a lower u_lattice"
        )
    coef = (sim.body_force() / plan.area).cpu().numpy()
    res["drag"][:, k], res["lift"][:, k], res["lift_z"][:, k] = coef[:, 0], coef[:, 1], coef[:, 2]
    if plan.resampler is not None:
        rho, u = sim.macroscopic()
        res["fields"][:, k] = plan.resampler(rho, u).cpu().numpy()


def simulate(re: np.ndarray, settings: dict[str, Any], **kwargs: Any) -> dict[str, Any]:
    """:func:`run_batches` collected into whole arrays (n, ...) plus the run's ``info`` entries."""
    re = np.atleast_1d(np.asarray(re, dtype=np.float64))
    info: dict[str, Any] = {}
    out: dict[str, Any] = {}
    for part, res in run_batches(re, settings, info=info, **kwargs):
        for key, value in res.items():
            if key not in out:
                out[key] = np.zeros((re.size, *value.shape[1:]), value.dtype)
            out[key][part] = value
    out.update(info)
    return out


def generate_sphere(
    benchmark: Benchmark,
    preset: str = "paper",
    *,
    seed: int = 0,
    workdir: Path | None = None,
    progress: bool = True,
    device: str = "cpu",
    compile: bool | None = None,
    max_batch: int | None = None,
    **options: Any,
) -> GeneratedData:
    """Run the lattice Boltzmann sphere for the preset's Reynolds numbers ("paper": 90 / 11; "small": 4 / 2).

    The generator of :data:`dks_gym.benchmarks.sphere.SPHERE` (``SPHERE.generate(...)`` calls it with the
    benchmark). Re comes from :func:`interleaved_sweep` over [59.5, 990.5] with
    ``np.random.default_rng(seed)``. All runs of a split advance together as one batch on ``device``
    ("cpu", "cuda", "cuda:1" ...), split into batches that fit its memory (or at most ``max_batch``).
    ``compile`` (default: on for CUDA, off on the CPU) wraps the step in torch.compile. Solver settings
    can be overridden by keyword: resolution (nodes per R), u_lattice, spin_up (R/U), n_frames, frame_dt
    is fixed at 0.5 R/U, smagorinsky, perturbation, sponge (R), sponge_strength. ``time`` counts from the
    first frame (taken after ``spin_up``). Drag and lift coefficients at every frame are kept in the file
    as extras ``drag``, ``lift`` (y, wall-normal) and ``lift_z``. The runs happen when ``trajectories`` is
    iterated; ``workdir`` is unused (nothing is cached, so an interrupted generation starts again).
    """
    check_preset(preset)
    settings = generator_settings(preset, options, benchmark.dt)
    n_train, n_test = PRESET_COUNTS[preset]
    low, high = benchmark.param_range
    re_train, re_test = interleaved_sweep(low, high, n_train, n_test, np.random.default_rng(seed))
    n_frames = int(settings["n_frames"])
    if n_frames < 2:
        raise ValueError(f"n_frames must be at least 2, got {n_frames}")
    time = benchmark.dt * np.arange(n_frames)
    coords, cell_type = benchmark.coords(), benchmark.cell_type()
    re_all = np.concatenate([re_train, re_test])
    extras: dict[str, dict[str, np.ndarray]] = {
        split: {k: np.zeros((n, n_frames)) for k in ("drag", "lift", "lift_z")}
        for split, n in (("train", n_train), ("test", n_test))
    }
    # A generator function: nothing runs until the dataset layer reads the trajectories.
    batches = run_batches(
        re_all, settings, coords=coords, cell_type=cell_type, device=device, compile=compile,
        max_batch=max_batch, progress=progress, info={},
    )  # fmt: skip
    return GeneratedData(
        time=time,
        params={"train": re_train, "test": re_test},
        trajectories=split_trajectories(batches, n_train, extras),
        generator=generator_metadata(preset, seed, settings, device),
        coords=coords,
        cell_type=cell_type,
        extras=extras,
    )


def generator_settings(preset: str, options: dict[str, Any], frame_dt: float) -> dict[str, Any]:
    """The solver settings of ``preset`` with the generator's keyword ``options`` applied (unknown ones are an
    error naming the known ones); ``frame_dt`` is the benchmark's."""
    allowed = set(SETTING_KEYS) - {"frame_dt", "walls", "half_width"}
    unknown = set(options) - allowed
    if unknown:
        raise ValueError(
            f"unknown option(s) for the sphere generator: {', '.join(sorted(unknown))}; it accepts preset, "
            f"seed, workdir, progress, device, compile, max_batch and the solver settings {', '.join(sorted(allowed))}"
        )
    return {**DEFAULTS, **PRESET_SETTINGS[preset], **options, "frame_dt": frame_dt}


def split_trajectories(
    batches: Iterator[tuple[slice, dict[str, np.ndarray]]], n_train: int, extras: dict[str, dict[str, np.ndarray]]
) -> Iterator[tuple[str, int, np.ndarray]]:
    """``(split, index, fields)`` of every case of the batches (train cases first), filling in ``extras``'
    force coefficients as they come."""
    for part, res in batches:
        for j, i in enumerate(range(part.start, part.stop)):
            split, index = ("train", i) if i < n_train else ("test", i - n_train)
            for key in ("drag", "lift", "lift_z"):
                extras[split][key][index] = res[key][j]
            yield split, index, res["fields"][j]


def generator_metadata(preset: str, seed: int, settings: dict[str, Any], device: str) -> dict[str, Any]:
    """The generator's record in the dataset file: preset, seed, solver, boundaries, settings, lattice, units."""
    return {
        # The generator's name since version 1, when it was a method of the benchmark; kept so that files
        # generated before and after the move are identical.
        "name": "dks_gym.benchmarks.sphere",
        "version": GENERATOR_VERSION,
        "preset": preset,
        "seed": int(seed),
        "solver": "batched lattice Boltzmann D3Q19, BGK + Smagorinsky, float32 (dks_gym.solvers.lbm)",
        "boundaries": "x=-8R velocity inlet (NEE), y=+-4R no-slip walls (half-way bounce-back), z periodic, "
        "pressure outlet (NEE) behind an absorbing layer in 16R < x < 16R + sponge; sphere by half-way bounce-back",
        "settings": {k: settings[k] for k in SETTING_KEYS},
        "device": str(device),
        "lattice": describe(settings),
        "units": "lengths R, velocity U, time R/U, p kinematic in U^2 relative to the outlet; Re = U 2R / nu",
        "time": "time counts from the first frame, taken after spin_up R/U from an impulsive start",
        "extras": "drag, lift (y), lift_z: force coefficients F / (0.5 U^2 pi R^2) at every frame",
    }
