"""The 1D Kuramoto-Sivashinsky equation u_t + u u_x + u_xx + nu u_xxxx = 0 on the periodic interval [0, L).

Method: Fourier pseudo-spectral in space (``n_x`` collocation points, real FFTs, the product u^2 formed on the
grid, no dealiasing: the solutions are analytic and their spectrum falls exponentially, so aliasing stays at
round-off level on a resolved grid; :func:`trajectories` checks this) and the fourth-order exponential time
differencing Runge-Kutta scheme ETDRK4 of Cox & Matthews (J. Comput. Phys. 176 (2002) 430), with its
coefficients phi_i(h L) evaluated by the contour integral of Kassam & Trefethen, "Fourth-order time-stepping
for stiff PDEs", SIAM J. Sci. Comput. 26 (2005) 1214 (their Fig. 2.1 code, which also solves this equation).
In Fourier space the equation reads d v_k / dt = (k^2 - nu k^4) v_k - (i k / 2) FFT(u^2)_k: the linear part
is integrated exactly, so the step size is set by the nonlinear dynamics only, not by the stiff nu k^4.
Everything is float64 numpy; a batch of initial conditions with one viscosity each advances at once.

Scaling: x' = x / sqrt(nu), t' = t / nu, u' = sqrt(nu) u turns the equation into the nu = 1 form on a domain
of length L / sqrt(nu). So varying nu on a fixed domain is varying the effective domain length
``L_eff = L / sqrt(nu)`` (the only dynamical parameter) together with the time and amplitude scales.

Default parameters (:data:`LENGTH`, :data:`NU_RANGE`): L = 60 and nu in [0.5, 1], so L_eff runs from 60
to 84.9 (9 to 13 linearly unstable Fourier modes; 6.8 to 9.5 wavelengths of the fastest-growing mode).
Why there: on small domains KS is chaotic only between windows of steady, travelling-wave or periodic
attractors. The scan of the leading Lyapunov exponent over L_eff = 14, 15, ..., 86 in
validation/results/kuramoto_sivashinsky.json (3 random initial conditions each, 1500 time units) has runs
with an exponent below 0.02 at L_eff = 15-18, 21, 23-25, 27-29, 31-33, 37, 40-41 and 48-49, so a nu range
there would mix chaotic and non-chaotic trajectories; every run from L_eff = 50 to 86 is chaotic (exponents
0.052-0.10, and 0.076-0.10 from 57 on). L = 60 sits at the low end of that band, with a margin: the dynamics
stay as low-dimensional as robust chaos allows. The example data set (:mod:`dks_gym.dataset.kuramoto_sivashinsky`)
takes L = 22 on 64 points instead: the lite latent models learn it and did not learn L = 60. At L = 60 the
leading exponent runs from 0.087 (nu = 1) to 0.18 (nu = 0.5): a Lyapunov time of 11 to 5.5 time units, 23 to
11 frames 0.5 apart. A factor 2 in nu changes the time scale (x 2), the amplitude (x 1.4) and the number of
cells, so nu matters to a model. L_eff = 22, the smallest domain with sustained chaos in Cvitanovic, Davidchack
& Siminos (SIAM J. Appl. Dyn. Syst. 9 (2010) 1), lies between two windows (L_eff = 21 and 23). Its leading
Lyapunov exponent, published as about 0.043-0.048 (Edson, Bunder, Mattner & Roberts, ANZIAM J. 61 (2019) 270;
Cvitanovic et al. 2010), is the published number the solver is checked against: 0.0488 +- 0.0008 here
(8 runs of 10^4 time units). All numbers and the commands: docs/validation.md#kuramoto-sivashinsky
(``OMP_NUM_THREADS=1 python validation/kuramoto_sivashinsky.py``).
Defaults of :func:`trajectories`: 128 stored points (solved on 256), frames 0.5 apart, solver step 0.025.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

#: Domain length of the generated data.
LENGTH = 60.0
#: Range of the viscosity nu over the generated trajectories (L_eff = L / sqrt(nu) from 60 to 84.9).
NU_RANGE = (0.5, 1.0)
#: Points on the upper half of the contour of radius 1 around each h L_k (Kassam & Trefethen use 16; the real
#: part of the mean over the upper half equals the mean over the full circle, as h L_k is real).
N_CONTOUR = 32
#: Modes 1..N_IC_MODES carry the random initial conditions.
N_IC_MODES = 4
#: Largest allowed max |v_k| over the top third of the wavenumbers, relative to max |v_k| (resolution check): a
#: tail of 4e-6 came with a grid error of 8e-9 after 5 time units, below the float32 precision of stored data.
MAX_SPECTRAL_TAIL = 1e-6


def wavenumbers(n_x: int, L: float) -> np.ndarray:
    """The ``n_x // 2 + 1`` non-negative wavenumbers k = 2 pi n / L of the real FFT of ``n_x`` points."""
    return 2.0 * math.pi / L * np.arange(n_x // 2 + 1)


def _check_grid(n_x: int, L: float) -> None:
    if isinstance(n_x, bool) or not isinstance(n_x, (int, np.integer)) or n_x < 4:
        raise ValueError(f"n_x (number of grid points) must be an integer >= 4, got {n_x!r}")
    if not (isinstance(L, (int, float, np.floating)) and math.isfinite(L) and L > 0):
        raise ValueError(f"L (domain length) must be a positive finite number, got {L!r}")


def _check_nu(nu: float | np.ndarray) -> np.ndarray:
    nu = np.asarray(nu, dtype=np.float64)
    if not (np.all(np.isfinite(nu)) and np.all(nu > 0)):
        raise ValueError(f"nu (the fourth-order coefficient) must be positive and finite, got {nu}")
    return nu


@dataclass(frozen=True)
class ETDRK4:
    """One ETDRK4 step of size ``dt`` for the Fourier coefficients ``v = rfft(u)`` (shape ``(*batch, n_x//2+1)``).

    Build it with :meth:`build`; ``E, E2`` are exp(h L), exp(h L / 2) and ``Q, f1, f2, f3`` the Cox-Matthews
    coefficients (Kassam & Trefethen eq. 2.5 with their contour averages), all of shape ``(*nu.shape, n_k)``.
    """

    n_x: int
    dt: float
    g: np.ndarray  # -i k / 2, zero at the Nyquist wavenumber (the derivative of a real grid function)
    E: np.ndarray
    E2: np.ndarray
    Q: np.ndarray
    f1: np.ndarray
    f2: np.ndarray
    f3: np.ndarray

    @classmethod
    def build(cls, nu: float | np.ndarray, L: float, n_x: int, dt: float, n_contour: int = N_CONTOUR) -> ETDRK4:
        """Coefficients for viscosity ``nu`` (a float, or one per batch entry) on ``n_x`` points of [0, L)."""
        _check_grid(n_x, L)
        nu = _check_nu(nu)
        if not (math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt (time step) must be positive and finite, got {dt!r}")
        k = wavenumbers(n_x, L)
        g = -0.5j * k
        if n_x % 2 == 0:
            g[-1] = 0.0
        hL = dt * (k**2 - nu[..., None] * k**4)
        r = np.exp(1j * math.pi * (np.arange(1, n_contour + 1) - 0.5) / n_contour)
        z = hL[..., None] + r  # contour points around each h L_k

        def mean(values: np.ndarray) -> np.ndarray:
            return dt * np.real(values.mean(axis=-1))

        ez = np.exp(z)
        return cls(
            n_x=int(n_x),
            dt=float(dt),
            g=g,
            E=np.exp(hL),
            E2=np.exp(hL / 2),
            Q=mean((np.exp(z / 2) - 1) / z),
            f1=mean((-4 - z + ez * (4 - 3 * z + z**2)) / z**3),
            f2=mean((2 + z + ez * (z - 2)) / z**3),
            f3=mean((-4 - 3 * z - z**2 + ez * (4 - z)) / z**3),
        )

    def nonlinear(self, v: np.ndarray) -> np.ndarray:
        """Fourier coefficients of -u u_x = -(u^2 / 2)_x for u = irfft(v)."""
        u = np.fft.irfft(v, n=self.n_x, axis=-1)
        return self.g * np.fft.rfft(u * u, axis=-1)

    def step(self, v: np.ndarray) -> np.ndarray:
        """``v`` advanced by one step (Kassam & Trefethen's Fig. 2.1 loop body)."""
        Nv = self.nonlinear(v)
        a = self.E2 * v + self.Q * Nv
        Na = self.nonlinear(a)
        b = self.E2 * v + self.Q * Na
        Nb = self.nonlinear(b)
        c = self.E2 * a + self.Q * (2 * Nb - Nv)
        Nc = self.nonlinear(c)
        return self.E * v + Nv * self.f1 + 2 * (Na + Nb) * self.f2 + Nc * self.f3


def simulate(
    u0: np.ndarray, nu: float | np.ndarray, L: float, dt: float, n_steps: int, save_every: int = 1
) -> np.ndarray:
    """Solve from ``u0`` (shape ``(*batch, n_x)``, grid x_j = j L / n_x) for ``n_steps`` steps of ``dt``.

    ``nu`` is a float or an array of the batch shape (one viscosity per initial condition). Returns u at
    t = 0, save_every dt, ..., n_steps dt: shape ``(*batch, n_steps // save_every + 1, n_x)``, float64.
    """
    u0 = np.asarray(u0, dtype=np.float64)
    if u0.ndim < 1 or not np.all(np.isfinite(u0)):
        raise ValueError(f"u0 must be a finite array of shape (*batch, n_x), got shape {u0.shape}")
    nu = _check_nu(nu)
    if nu.shape not in ((), u0.shape[:-1]):
        raise ValueError(f"nu must be a float or have the batch shape {u0.shape[:-1]} of u0, got shape {nu.shape}")
    for name, value in (("n_steps", n_steps), ("save_every", save_every)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    if n_steps % save_every:
        raise ValueError(f"n_steps ({n_steps}) must be a multiple of save_every ({save_every})")
    stepper = ETDRK4.build(nu, L, u0.shape[-1], dt)
    v = np.fft.rfft(u0, axis=-1)
    out = np.empty((n_steps // save_every + 1, *u0.shape), dtype=np.float64)
    out[0] = u0
    with np.errstate(over="ignore", invalid="ignore"):  # a blow-up is reported below, with what to change
        for i in range(1, n_steps + 1):
            v = stepper.step(v)
            if i % save_every == 0:
                out[i // save_every] = np.fft.irfft(v, n=u0.shape[-1], axis=-1)
    if not np.all(np.isfinite(out)):
        raise FloatingPointError(f"the solution blew up (nu={nu}, L={L}, dt={dt}): reduce dt or increase n_x")
    return np.moveaxis(out, 0, -2)


def initial_conditions(n: int, n_x: int, L: float, rng: np.random.Generator, n_modes: int = N_IC_MODES) -> np.ndarray:
    """``n`` smooth random zero-mean fields on ``n_x`` points of [0, L), each of RMS 1, shape ``(n, n_x)``.

    u0(x) = sum_{m=1}^{n_modes} a_m cos(2 pi m x / L) + b_m sin(2 pi m x / L), a_m, b_m ~ N(0, 1), rescaled to
    RMS 1. The mean is zero because it is conserved and a nonzero mean only adds a Galilean drift.
    """
    _check_grid(n_x, L)
    if not 1 <= n_modes < n_x // 2:
        raise ValueError(f"n_modes must be between 1 and {n_x // 2 - 1} for n_x = {n_x}, got {n_modes}")
    coef = rng.standard_normal((n, 2, n_modes))
    phase = 2 * math.pi * np.outer(np.arange(1, n_modes + 1), np.arange(n_x) / n_x)  # (n_modes, n_x)
    u0 = coef[:, 0] @ np.cos(phase) + coef[:, 1] @ np.sin(phase)
    return u0 / np.sqrt(np.mean(u0**2, axis=-1, keepdims=True))


def spectral_tail(u: np.ndarray) -> float:
    """max |v_k| over the top third of the resolved wavenumbers divided by max |v_k| (a resolution measure)."""
    v = np.abs(np.fft.rfft(u, axis=-1))
    cut = (2 * v.shape[-1]) // 3
    return float(v[..., cut:].max() / v[..., 1:].max())


@dataclass(frozen=True)
class Trajectories:
    """Generated KS data: ``u`` (n_traj, n_t, n_x) at times ``time`` (n_t,) on ``x`` (n_x,), with ``nu`` (n_traj,).

    ``time`` starts at 0 after the discarded transient. ``generator`` records everything needed to rebuild
    the data (method, domain, steps, seed).
    """

    u: np.ndarray
    time: np.ndarray
    x: np.ndarray
    nu: np.ndarray
    L: float
    generator: dict[str, Any] = field(default_factory=dict)


def _positive(name: str, value: float) -> float:
    if not (isinstance(value, (int, float, np.floating)) and math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return float(value)


def trajectories(
    n_traj: int = 16,
    n_t: int = 100,
    n_x: int = 128,
    *,
    nu: float | np.ndarray | None = None,
    L: float = LENGTH,
    frame_dt: float = 0.5,
    dt: float = 0.025,
    transient: float = 200.0,
    oversample: int = 2,
    seed: int = 0,
) -> Trajectories:
    """``n_traj`` KS trajectories of ``n_t`` frames ``frame_dt`` apart on ``n_x`` points, after a ``transient``.

    Viscosities: ``nu`` (a float for all, or one per trajectory); by default ``n_traj`` values evenly spaced
    over :data:`NU_RANGE`. Initial conditions: :func:`initial_conditions` with ``np.random.default_rng(seed)``
    (the same functions whatever the grid). The solve runs on ``oversample * n_x`` points and keeps every
    ``oversample``-th one (the stored values are those of the finer, converged solution). ``frame_dt`` must be
    a whole number of solver steps ``dt``. Raises if the solver grid does not resolve the solutions
    (:func:`spectral_tail` above :data:`MAX_SPECTRAL_TAIL`). Defaults: 1.5 s of CPU time.

    Reproducible bit for bit from the arguments on one machine (numpy's FFT is single-threaded). The chaos
    amplifies round-off, so another batch size (the batched FFT rounds differently) or another CPU gives other,
    statistically equivalent, trajectories once the transient has run.
    """
    _check_grid(n_x, L)
    for name, value in (("n_traj", n_traj), ("n_t", n_t), ("oversample", oversample)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    frame_dt, dt, transient = _positive("frame_dt", frame_dt), _positive("dt", dt), _positive("transient", transient)
    save_every = round(frame_dt / dt)
    if save_every < 1 or not math.isclose(save_every * dt, frame_dt, rel_tol=1e-9):
        raise ValueError(f"frame_dt ({frame_dt}) must be a whole multiple of dt ({dt})")
    nus = np.linspace(*NU_RANGE, n_traj) if nu is None else _check_nu(np.broadcast_to(nu, (n_traj,)).copy())
    n_solve = n_x * oversample
    u0 = initial_conditions(n_traj, n_solve, L, np.random.default_rng(seed))
    n_transient = math.ceil(transient / dt)
    start = simulate(u0, nus, L, dt, n_transient, save_every=n_transient)[:, -1]
    u = simulate(start, nus, L, dt, (n_t - 1) * save_every, save_every=save_every)
    tail = spectral_tail(u)
    if tail > MAX_SPECTRAL_TAIL:
        raise ValueError(
            f"{n_solve} points (n_x = {n_x} x oversample = {oversample}) do not resolve KS with L = {L} and nu down "
            f"to {nus.min()}: the top third of the spectrum holds {tail:.1e} of its peak (limit "
            f"{MAX_SPECTRAL_TAIL:.0e}); increase oversample or n_x"
        )
    generator = {
        "equation": "u_t + u u_x + u_xx + nu u_xxxx = 0, periodic on [0, L)",
        "method": "Fourier pseudo-spectral + ETDRK4 (Kassam & Trefethen 2005 contour coefficients), float64",
        "L": float(L),
        "n_x": int(n_x),
        "solver_n_x": int(n_solve),
        "dt": dt,
        "frame_dt": frame_dt,
        "transient": n_transient * dt,
        "initial_condition": f"random modes 1..{N_IC_MODES}, N(0, 1) coefficients, zero mean, RMS 1",
        "seed": int(seed),
        "spectral_tail": tail,
    }
    return Trajectories(u=np.ascontiguousarray(u[..., ::oversample]), time=frame_dt * np.arange(n_t),
                        x=L * np.arange(n_x) / n_x, nu=nus, L=float(L), generator=generator)


def small_dataset(seed: int = 0) -> Trajectories:
    """A tiny data set for tests: 4 trajectories of 20 frames on 64 points, nu over :data:`NU_RANGE`.

    The defaults of :func:`trajectories` except a shorter transient (40), a coarser step (0.1) and a 4 times
    finer solver grid (the coarser stored grid needs it to stay resolved at nu = 0.5).
    """
    return trajectories(n_traj=4, n_t=20, n_x=64, transient=40.0, dt=0.1, oversample=4, seed=seed)


def leading_lyapunov_exponent(
    nu: float, L: float = LENGTH, *, n_x: int = 64, dt: float = 0.1, t_total: float = 2000.0,
    t_renorm: float = 1.0, transient: float = 200.0, seed: int = 0,
) -> float:
    """Leading Lyapunov exponent (per unit time) by Benettin's two-trajectory method.

    A reference trajectory and one displaced by 1e-8 (in the L2 norm) advance together; every ``t_renorm``
    the displacement is measured and rescaled back to 1e-8, and the exponent is the mean log growth rate over
    ``t_total`` after a ``transient``. In nu = 1 units it depends on L / sqrt(nu) only (the module's scaling).
    """
    _check_grid(n_x, L)
    steps = round(_positive("t_renorm", t_renorm) / _positive("dt", dt))
    n_renorm = math.ceil(_positive("t_total", t_total) / (steps * dt))
    stepper = ETDRK4.build(nu, L, n_x, dt)
    v = np.fft.rfft(initial_conditions(1, n_x, L, np.random.default_rng(seed))[0])
    for _ in range(math.ceil(_positive("transient", transient) / dt)):
        v = stepper.step(v)
    eps = 1e-8
    d = np.fft.rfft(np.random.default_rng(seed + 1).standard_normal(n_x))
    d[0] = 0.0  # the mean is conserved: a displaced mean would not grow
    pair = np.stack([v, v + eps * d / np.linalg.norm(np.fft.irfft(d, n=n_x))])
    log_growth = 0.0
    for _ in range(n_renorm):
        for _ in range(steps):
            pair = stepper.step(pair)
        dist = np.linalg.norm(np.fft.irfft(pair[1] - pair[0], n=n_x))
        log_growth += math.log(dist / eps)
        pair[1] = pair[0] + (pair[1] - pair[0]) * (eps / dist)
    return log_growth / (n_renorm * steps * dt)
