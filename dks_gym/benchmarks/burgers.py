"""The 1D viscous Burgers benchmark: u_t + u u_x = nu u_xx on the periodic interval [0, 2 pi).

Every trajectory starts from u0 = sin x + 0.5 cos 2x and differs only through the viscosity nu
(paper Section III.A, SPEC section 1). The reference data come from the paper's explicit
finite-difference scheme (:func:`solve`): first-order upwind advection of the non-conservative form
u u_x, second-order central diffusion, advective Courant number 0.1 and diffusive factor 0.45.
:func:`exact_solution` is the Cole-Hopf solution, evaluated independently of the scheme, against which
the scheme is verified (``validation/burgers_convergence.py``).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator

import numpy as np

from .base import Benchmark, GeneratedData, GenerationCost, check_preset, interleaved_sweep

if TYPE_CHECKING:
    import torch

GENERATOR_VERSION = "1"

NX = 1024
LENGTH = 2.0 * math.pi
COURANT = 0.1
DIFFUSIVE_FACTOR = 0.45
U0_FORMULA = "sin(x) + 0.5*cos(2x)"
# max |u0| = 1.5, attained at x = 3 pi / 2.
U0_MAX = 1.5
# Range of F(x) = 1 - cos x + 0.25 sin 2x is [-0.101, 2.101]; 2.5 is a safe upper bound of max F - min F.
F_SPREAD_BOUND = 2.5
# Trajectory counts per preset: (n_train, n_test).
PRESET_COUNTS = {"paper": (50, 10), "small": (6, 3)}


def initial_condition(x: np.ndarray) -> np.ndarray:
    """u0(x) = sin x + 0.5 cos 2x."""
    x = np.asarray(x, dtype=np.float64)
    return np.sin(x) + 0.5 * np.cos(2.0 * x)


def _antiderivative_u0(x: np.ndarray) -> np.ndarray:
    """F(x) = int_0^x u0 = 1 - cos x + 0.25 sin 2x; 2 pi-periodic because u0 has zero mean."""
    return 1.0 - np.cos(x) + 0.25 * np.sin(2.0 * x)


def _check_nu(nu: np.ndarray) -> np.ndarray:
    nu = np.atleast_1d(np.asarray(nu, dtype=np.float64))
    if nu.ndim != 1 or nu.size == 0:
        raise ValueError(f"nu must be a non-empty 1D array of viscosities, got shape {nu.shape}")
    if not np.all(np.isfinite(nu)) or np.any(nu <= 0):
        raise ValueError(f"every viscosity nu must be finite and > 0, got {nu}")
    return nu


def _check_times(times: np.ndarray) -> np.ndarray:
    times = np.atleast_1d(np.asarray(times, dtype=np.float64))
    if times.ndim != 1 or times.size == 0:
        raise ValueError(f"times must be a non-empty 1D array, got shape {times.shape}")
    if not np.all(np.isfinite(times)) or times[0] < 0 or np.any(np.diff(times) < 0):
        raise ValueError("times must be finite, >= 0 and non-decreasing (the run starts from u0 at t = 0)")
    return times


def solve(
    nu: np.ndarray,
    times: np.ndarray,
    nx: int = NX,
    progress: bool = False,
    *,
    courant: float = COURANT,
    diffusive_factor: float = DIFFUSIVE_FACTOR,
    device: str | torch.device = "cpu",
) -> np.ndarray:
    """Integrate Burgers from u0 for every viscosity in ``nu``; return u at ``times``, shape (n_nu, n_times, nx).

    Explicit Euler in time, first-order upwind for u u_x (upwinded by the sign of u_i), second-order
    central differences for nu u_xx, periodic grid x_i = 2 pi i / nx. Each trajectory uses its own step
    dt_limit = min(courant dx / max|u0|, diffusive_factor dx^2 / nu); every interval between requested
    times is cut into ceil(interval / dt_limit) equal substeps so frames land exactly on ``times``.
    All trajectories advance together (float64 on ``device``); the result is float64 on the CPU.
    """
    # torch is imported where it is used: `import dks_gym` (which imports the benchmarks to register the
    # envs) stays free of it.
    import torch

    nu = _check_nu(nu)
    times = _check_times(times)
    if isinstance(nx, bool) or not isinstance(nx, (int, np.integer)) or nx < 3:
        raise ValueError(f"nx must be an integer >= 3, got {nx!r}")
    if not (courant > 0 and diffusive_factor > 0 and courant + 2 * diffusive_factor <= 1 + 1e-12):
        raise ValueError(
            "need courant > 0, diffusive_factor > 0 and courant + 2 * diffusive_factor <= 1 for a stable, "
            f"monotone scheme; got courant={courant}, diffusive_factor={diffusive_factor}"
        )
    nx = int(nx)
    dx = LENGTH / nx
    x = dx * np.arange(nx)
    # Burgers obeys a maximum principle, so max|u(t)| <= max|u0| and the advective bound taken from u0
    # holds for the whole run. The discrete scheme keeps it too: with a|u| <= courant and b <= factor,
    # each update is a convex combination of u_{i-1}, u_i, u_{i+1} whenever courant + 2 factor <= 1
    # (0.1 + 0.9 here), so no step ever sees a larger |u| than the one the limit was computed for.
    u0 = initial_condition(x)
    dt_limit = np.minimum(courant * dx / np.abs(u0).max(), diffusive_factor * dx**2 / nu)

    # Slowest trajectories (smallest dt_limit, most substeps) first: at substep s the ones still
    # stepping are a leading slice, so no work is masked away.
    order = np.argsort(dt_limit, kind="stable")
    nu_sorted, limit_sorted = nu[order], dt_limit[order]
    n = nu.size
    dev = torch.device(device)
    f64 = dict(dtype=torch.float64, device=dev)

    # Ghost cells u[:, 0] = u[:, nx] and u[:, nx + 1] = u[:, 1] carry the periodicity.
    u = torch.empty((n, nx + 2), **f64)
    u[:, 1:-1] = torch.from_numpy(u0).to(**f64)
    u[:, 0], u[:, -1] = u[:, -2], u[:, 1]
    diff = torch.empty((n, nx + 1), **f64)
    lap = torch.empty((n, nx), **f64)
    work = torch.empty((n, nx), **f64)
    flux = torch.empty((n, nx), **f64)

    out = np.empty((n, times.size, nx), dtype=np.float64)
    t_now = 0.0
    frames = range(times.size)
    if progress:
        from tqdm.auto import tqdm

        frames = tqdm(frames, desc=f"burgers nx={nx}", unit="frame")
    for j in frames:
        interval = times[j] - t_now
        if interval > 0:
            n_sub = np.ceil(interval / limit_sorted).astype(np.int64)  # non-increasing along the sort
            dt = interval / n_sub
            a = torch.from_numpy(dt / dx).to(**f64)[:, None]
            b = torch.from_numpy(nu_sorted * dt / dx**2).to(**f64)[:, None]
            # active[s] = how many trajectories take substep s.
            active = np.searchsorted(-n_sub, -np.arange(n_sub[0]), side="left")
            for k in active.tolist():
                _upwind_step(u[:k], a[:k], b[:k], diff[:k], lap[:k], work[:k], flux[:k])
            t_now = float(times[j])
        out[order, j] = u[:, 1:-1].cpu().numpy()
    return out


def _upwind_step(
    u: torch.Tensor,
    a: torch.Tensor,
    b: torch.Tensor,
    diff: torch.Tensor,
    lap: torch.Tensor,
    work: torch.Tensor,
    flux: torch.Tensor,
) -> None:
    """One explicit step in place on ghosted ``u`` (k, nx + 2); a = dt/dx, b = nu dt/dx^2 per row.

    With d- = u_i - u_{i-1}, d+ = u_{i+1} - u_i and lap = d+ - d-, the upwind term
    max(u,0) d- + min(u,0) d+ equals u d+ - max(u,0) lap, so
    u_i <- u_i + (b + a max(u_i,0)) lap - a u_i d+, which needs no branch and few passes.
    """
    import torch

    torch.sub(u[:, 1:], u[:, :-1], out=diff)
    torch.sub(diff[:, 1:], diff[:, :-1], out=lap)
    c = u[:, 1:-1]
    torch.clamp(c, min=0.0, out=work)
    work.mul_(a).add_(b).mul_(lap)
    torch.mul(c, diff[:, 1:], out=flux)
    flux.mul_(a)
    work.sub_(flux)
    c.add_(work)
    u[:, 0] = u[:, -2]
    u[:, -1] = u[:, 1]


def pseudo_spectral_solution(nu: float, t: float, nx: int) -> tuple[np.ndarray, np.ndarray]:
    """(x, u(x, t)) from a second, unrelated solver, to check :func:`exact_solution`: Fourier collocation on
    ``nx`` points in x, 8th-order Runge-Kutta (DOP853, rtol 1e-12) in t. ``nx`` must resolve the front."""
    from scipy.integrate import solve_ivp

    x = 2.0 * math.pi * np.arange(nx) / nx
    k = np.fft.rfftfreq(nx, 1.0 / nx)

    def rhs(_: float, u: np.ndarray) -> np.ndarray:
        return np.fft.irfft(-0.5j * k * np.fft.rfft(u * u) - nu * k**2 * np.fft.rfft(u), nx)

    sol = solve_ivp(rhs, (0.0, float(t)), initial_condition(x), method="DOP853", rtol=1e-12, atol=1e-13)
    if not sol.success:
        raise RuntimeError(f"pseudo-spectral solve failed: {sol.message}")
    return x, sol.y[:, -1]


def exact_solution(x: np.ndarray, t: float, nu: float, *, refine: float = 1.0) -> np.ndarray:
    """Cole-Hopf solution u(x, t) of Burgers from u0 = sin x + 0.5 cos 2x, to near machine precision.

    u = -2 nu phi_x / phi with phi_t = nu phi_xx and phi0 = exp(-F / (2 nu)), F = int_0^x u0. Writing
    phi as the heat-kernel convolution over the real line (F extended periodically) gives
    u(x, t) = sum_y w(y) (x - y) / t / sum_y w(y),  w(y) = exp(-(x - y)^2 / (4 nu t) - F(y) / (2 nu)),
    which is summed in log space (the exponent is shifted by its maximum) because phi0 spans
    e^-110 .. e^5 at nu = 0.01 and a Fourier representation of phi would lose the shock region.
    The sum is the trapezoid rule with spacing h = min(sqrt(2 nu t), nu) / (20 refine), below both
    the kernel width and the scale of F / (2 nu); for this smooth, doubly exponentially decaying
    integrand it converges exponentially in 1/h. The window |x - y| <= L keeps every point whose weight
    can exceed e^-75 times the largest one. ``refine`` > 1 shrinks h (used to show convergence).
    """
    x = np.asarray(x, dtype=np.float64)
    t, nu = float(t), float(nu)
    if not (math.isfinite(t) and t >= 0):
        raise ValueError(f"t must be finite and >= 0, got {t}")
    if not (math.isfinite(nu) and nu > 0):
        raise ValueError(f"nu must be finite and > 0, got {nu}")
    if not refine >= 1:
        raise ValueError(f"refine must be >= 1, got {refine}")
    if t == 0:
        return initial_condition(x)

    four_nu_t = 4.0 * nu * t
    # For |x - y| > L: exponent <= -L^2/(4 nu t) - min F/(2 nu) <= (max exponent) - 75, because the
    # maximum is at least the value at y = x, -max F/(2 nu).
    half_width = math.sqrt(four_nu_t * 75.0 + 2.0 * t * F_SPREAD_BOUND)
    h = min(math.sqrt(2.0 * nu * t), nu) / (20.0 * refine)
    n_half = math.ceil(half_width / h)
    s = h * np.arange(-n_half, n_half + 1)  # s = x - y
    kernel = -(s**2) / four_nu_t

    flat = x.ravel()
    u = np.empty_like(flat)
    chunk = max(1, 2_000_000 // s.size)
    for start in range(0, flat.size, chunk):
        xc = flat[start : start + chunk, None]
        exponent = kernel - _antiderivative_u0(xc - s) / (2.0 * nu)
        exponent -= exponent.max(axis=1, keepdims=True)
        w = np.exp(exponent)
        u[start : start + chunk] = (w @ s) / w.sum(axis=1) / t
    return u.reshape(x.shape)


def generate_burgers(
    benchmark: Benchmark,
    preset: str = "paper",
    *,
    seed: int = 0,
    workdir: Path | None = None,
    progress: bool = True,
    device: str | torch.device = "cpu",
    **options: Any,
) -> GeneratedData:
    """Solve Burgers for the preset's viscosities ("paper": 50 train / 10 test; "small": 6 / 3).

    The generator of :data:`BURGERS` (``BURGERS.generate(...)`` calls it with the benchmark).
    Viscosities come from :func:`interleaved_sweep` with ``np.random.default_rng(seed)``; the grid
    and the 100 frames are the same for both presets. The solve (about 4 s for "paper" on one CPU
    core) runs when ``trajectories`` is first iterated. ``workdir`` is unused (nothing is cached).
    """
    check_preset(preset)
    if options:
        raise ValueError(
            f"unknown option(s) for the burgers generator: {', '.join(sorted(options))}; "
            "it accepts preset, seed, workdir, progress and device"
        )
    n_train, n_test = PRESET_COUNTS[preset]
    low, high = benchmark.param_range
    nu_train, nu_test = interleaved_sweep(low, high, n_train, n_test, np.random.default_rng(seed))
    time = benchmark.dt * np.arange(benchmark.n_frames)
    (nx,) = benchmark.grid

    # Solved on first use, so parameters and metadata are available without the (seconds-long) run.
    def trajectories() -> Iterator[tuple[str, int, np.ndarray]]:
        u = solve(np.concatenate([nu_train, nu_test]), time, nx=nx, progress=progress, device=device)
        fields = u[:, :, None, :].astype(np.float32)  # (n, n_t, C=1, nx)
        for i in range(n_train):
            yield "train", i, fields[i]
        for i in range(n_test):
            yield "test", i, fields[n_train + i]

    generator: dict[str, Any] = {
        "name": __name__,
        "version": GENERATOR_VERSION,
        "preset": preset,
        "seed": int(seed),
        "scheme": "explicit Euler; first-order upwind u*u_x (non-conservative, upwind by sign of u_i); "
        "second-order central nu*u_xx; periodic",
        "courant": COURANT,
        "diffusive_factor": DIFFUSIVE_FACTOR,
        "dt_rule": "dt_limit = min(courant*dx/max|u0|, diffusive_factor*dx^2/nu); "
        "n_sub = ceil(frame_dt/dt_limit) equal substeps per frame",
        "u0": U0_FORMULA,
        "nx": nx,
        "precision": "float64 solve, float32 storage",
    }
    return GeneratedData(
        time=time,
        params={"train": nu_train, "test": nu_test},
        trajectories=trajectories(),
        generator=generator,
        coords=benchmark.coords(),
        cell_type=None,
    )


class BurgersBenchmark(Benchmark):
    """1D viscous Burgers, 1024 periodic points, nu in [0.01, 1], 100 frames spaced 0.005 from t = 0."""

    def coords(self) -> tuple[np.ndarray, ...]:
        """(x,) with x_i = 2 pi i / 1024 on the periodic interval [0, 2 pi)."""
        (nx,) = self.grid
        return (LENGTH * np.arange(nx) / nx,)

    def paper_layout(self, m: int = 16) -> np.ndarray:
        """``m`` equidistant sensors, symmetric about x = pi: index round((k + 1/2) nx / m), k < m.

        For m = 16 these are 32 + 64 k. Rounding is half-up; indices are returned sorted.
        """
        (nx,) = self.grid
        if isinstance(m, bool) or not isinstance(m, (int, np.integer)):
            raise ValueError(f"m (number of sensors) must be an integer, got {m!r} of type {type(m).__name__}")
        if not 1 <= m <= nx:
            raise ValueError(f"m (number of sensors) must be between 1 and {nx} (the grid size), got {m}")
        # Spacing nx/m >= 1, so the rounded positions are distinct; only m = nx rounds the last one up
        # to nx, which is grid point 0 on the periodic grid.
        return np.sort(np.floor((np.arange(m) + 0.5) * nx / m + 0.5).astype(np.int64) % nx)


BURGERS = BurgersBenchmark(
    name="burgers",
    env_id="DKS/Burgers-v0",
    grid=(NX,),
    channels=("u",),
    observed_channel="u",
    scored_channels=("u",),
    param_name="nu",
    param_range=(0.01, 1.0),
    dt=0.005,
    n_frames=100,
    n_train=50,
    n_test=10,
    generator_entry_point="dks_gym.benchmarks.burgers:generate_burgers",
    generation_costs={
        "small": GenerationCost("about 15 s on one CPU core"),
        "paper": GenerationCost("about 5 s on one CPU core"),
    },
)
