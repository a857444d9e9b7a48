"""The Kuramoto-Sivashinsky solver (ETDRK4, pseudo-spectral) and its data generator.

Independent references: the exact solution of the linearised equation (a tiny single Fourier mode), the
closed forms of the ETDRK4 coefficients, fourth-order convergence in dt against a much finer run, a second
implementation (full complex FFT right-hand side integrated by scipy's DOP853), two laws of the equation
(conservation of the mean, Galilean invariance) and the published leading Lyapunov exponent at L = 22.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from dks_gym.solvers import kuramoto_sivashinsky as ks

L = 22.0


def attractor_state(nu: float, n_x: int, seed: int = 0) -> np.ndarray:
    """A state after 50 time units from a random start (strongly nonlinear, smooth in time)."""
    u0 = ks.initial_conditions(1, n_x, L, np.random.default_rng(seed))[0]
    return ks.simulate(u0, nu, L, 0.1, 500, save_every=500)[-1]


def final(u0: np.ndarray, nu: float, T: float, n_steps: int) -> np.ndarray:
    return ks.simulate(u0, nu, L, T / n_steps, n_steps, save_every=n_steps)[..., -1, :]


@pytest.mark.parametrize("nu", (1.0, 0.5))
@pytest.mark.parametrize("m", (1, 2, 4, 6))
def test_a_tiny_fourier_mode_grows_or_decays_at_the_linear_rate(nu: float, m: int) -> None:
    n_x, T, eps = 64, 2.0, 1e-10
    x = L * np.arange(n_x) / n_x
    k = 2 * math.pi * m / L
    u = final(eps * np.cos(k * x + 0.3), nu, T, 8)
    # The nonlinear term feeds mode m only at O(eps^3) (through mode 2m): relative 1e-20 here, below round-off.
    ratio = np.fft.rfft(u)[m] / np.fft.rfft(eps * np.cos(k * x + 0.3))[m]
    assert ratio == pytest.approx(math.exp((k**2 - nu * k**4) * T), rel=1e-12, abs=0)
    # Both signs occur: modes 1, 2 grow, mode 6 decays (and mode 4 grows only for nu = 0.5).
    assert (abs(ratio) > 1) == (k**2 > nu * k**4)


def test_etdrk4_coefficients_match_their_closed_forms() -> None:
    dt, nu = 0.25, 0.7
    s = ks.ETDRK4.build(nu, L, 64, dt)
    z = dt * (ks.wavenumbers(64, L) ** 2 - nu * ks.wavenumbers(64, L) ** 4)[1:]  # z = 0 (the mean) below
    ez = np.exp(z)
    closed = {  # Cox & Matthews (2002) eq. 26; cancellation-free for |z| > 1/2
        "Q": (np.exp(z / 2) - 1) / z,
        "f1": (-4 - z + ez * (4 - 3 * z + z**2)) / z**3,
        "f2": (2 + z + ez * (z - 2)) / z**3,
        "f3": (-4 - 3 * z - z**2 + ez * (4 - z)) / z**3,
    }
    far = np.abs(z) > 0.5
    assert far.sum() > 20 and z.min() < -1e3  # the stiff end is covered
    for name, value in closed.items():
        got = getattr(s, name) / dt
        np.testing.assert_allclose(got[1:][far], value[far], rtol=1e-12, err_msg=name)
    # z = 0 (the mean): the limits 1/2 and 1/6, where the closed forms are 0/0.
    np.testing.assert_allclose([s.Q[0] / dt, s.f1[0] / dt, s.f2[0] / dt, s.f3[0] / dt], [0.5, 1 / 6, 1 / 6, 1 / 6],
                               rtol=1e-14)


def test_fourth_order_convergence_in_dt() -> None:
    # Stiffness stretches the pre-asymptotic range (error ratios ~10 at dt ~ 0.1 on 64 points, see
    # docs/validation.md); on 32 points dt = 0.0125 .. 0.003 is in the asymptotic range.
    u0 = attractor_state(1.0, 32)
    T = 0.5
    ref = final(u0, 1.0, T, 1280)
    errors = [np.abs(final(u0, 1.0, T, n) - ref).max() for n in (40, 80, 160)]
    ratios = [errors[0] / errors[1], errors[1] / errors[2]]
    assert errors[-1] > 1e-12  # above round-off (and the reference's own error), so the ratios measure the scheme
    assert 14 < ratios[0] < 17 and 14 < ratios[1] < 17, (errors, ratios)


def test_agrees_with_dop853_on_the_fourier_ode() -> None:
    n_x, nu, T = 32, 1.0, 1.0
    u0 = 2 * ks.initial_conditions(1, n_x, L, np.random.default_rng(3))[0]
    # Full complex FFT, both signs of k (the solver uses real FFTs); odd derivative zero at Nyquist.
    k = 2 * math.pi / L * np.fft.fftfreq(n_x, 1 / n_x)
    k_odd = np.where(np.arange(n_x) == n_x // 2, 0.0, k)

    def rhs(_: float, v: np.ndarray) -> np.ndarray:
        u = np.fft.ifft(v).real
        return (k**2 - nu * k**4) * v - 0.5j * k_odd * np.fft.fft(u * u)

    sol = solve_ivp(rhs, (0.0, T), np.fft.fft(u0).astype(complex), method="DOP853", rtol=1e-12, atol=1e-12)
    reference = np.fft.ifft(sol.y[:, -1]).real
    assert np.abs(reference - u0).max() > 0.5  # the run is long enough to change u
    assert np.abs(final(u0, nu, T, 200) - reference).max() < 3e-8


def test_mean_is_conserved() -> None:
    u0 = ks.initial_conditions(2, 64, L, np.random.default_rng(1)) + np.array([[0.0], [0.7]])
    u = ks.simulate(u0, np.array([1.0, 0.6]), L, 0.1, 1000, save_every=100)
    assert np.abs(u[0, -1] - u0[0]).max() > 1  # the field does change
    assert np.abs(u.mean(axis=-1) - np.array([[0.0], [0.7]])).max() < 1e-13


def test_scaling_maps_nu_to_the_domain_length() -> None:
    # u'(x', t') = sqrt(nu) u(sqrt(nu) x', nu t') solves the nu = 1 equation on L / sqrt(nu) (module docstring).
    nu, n_x = 0.5, 64
    u0 = 2 * ks.initial_conditions(1, n_x, L, np.random.default_rng(2))[0]
    u = ks.simulate(u0, nu, L, 0.05, 100, save_every=100)[-1]
    u_scaled = ks.simulate(math.sqrt(nu) * u0, 1.0, L / math.sqrt(nu), 0.05 / nu, 100, save_every=100)[-1]
    assert np.abs(u - u0).max() > 0.5
    assert np.abs(u_scaled / math.sqrt(nu) - u).max() < 1e-11


def test_galilean_invariance() -> None:
    # If u(x, t) solves KS, so does u(x - c t, t) + c: checks the nonlinear term's form and factor 1/2.
    n_x, nu, T, c = 64, 1.0, 2.0, 0.8
    u0 = attractor_state(nu, n_x)
    u, w = final(np.stack([u0, u0 + c]), nu, T, 200)
    k = ks.wavenumbers(n_x, L)
    shifted = np.fft.irfft(np.fft.rfft(u) * np.exp(-1j * k * c * T), n=n_x) + c
    assert np.abs(w - u).max() > 0.5
    assert np.abs(w - shifted).max() < 2e-7  # the advection by c is explicit in ETDRK4: a dt^4 error (2.6e-8)


def test_leading_lyapunov_exponent_at_l22_matches_the_published_value() -> None:
    # Published: about 0.043-0.048 (Edson et al. 2019; Cvitanovic et al. 2010); 0.0488 +- 0.0008 from long runs
    # here. These 1500-time-unit runs give 0.048 +- 0.005 (mean +- std over 20 initial conditions, range
    # 0.038-0.061: validation/results/kuramoto_sivashinsky.json); a periodic window gives ~0, L_eff = 36 ~0.075.
    lam = ks.leading_lyapunov_exponent(1.0, 22.0, n_x=48, dt=0.25, t_total=1500.0, transient=100.0)
    assert 0.032 < lam < 0.066, lam


def test_trajectories_shapes_parameters_and_seed() -> None:
    d = ks.small_dataset(seed=4)
    assert d.u.shape == (4, 20, 64) and d.time.shape == (20,) and d.x.shape == (64,) and d.nu.shape == (4,)
    np.testing.assert_allclose(d.nu, np.linspace(*ks.NU_RANGE, 4))
    np.testing.assert_allclose(np.diff(d.time), 0.5)
    np.testing.assert_allclose(d.x, ks.LENGTH * np.arange(64) / 64)
    assert d.u.dtype == np.float64 and np.all(np.isfinite(d.u))
    assert d.generator["seed"] == 4 and d.generator["spectral_tail"] < ks.MAX_SPECTRAL_TAIL
    assert np.abs(d.u[:, -1] - d.u[:, 0]).max() > 1  # the frames move
    np.testing.assert_array_equal(ks.small_dataset(seed=4).u, d.u)
    rngs = [np.random.default_rng(seed) for seed in (4, 4, 5)]
    first, same, other = (ks.initial_conditions(4, 64, ks.LENGTH, rng) for rng in rngs)
    assert np.array_equal(first, same) and not np.allclose(first, other)
    # One trajectory on its own is the one in the batch: same initial condition, same viscosity. The batched
    # FFT rounds differently, and the chaos amplifies that to ~3e-10 over these 50 time units.
    alone = ks.trajectories(1, 20, 64, nu=d.nu[0], transient=40.0, dt=0.1, oversample=4, seed=4)
    np.testing.assert_allclose(alone.u[0], d.u[0], rtol=0, atol=1e-7)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"frame_dt": 0.25, "dt": 0.1}, "whole multiple of dt"),
        ({"oversample": 1}, "do not resolve"),
        ({"nu": -1.0}, "must be positive"),
        ({"n_t": 0}, "n_t must be a positive integer"),
        ({"L": 0.0}, "L \\(domain length\\)"),
    ],
)
def test_trajectories_refuse_bad_input(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        ks.trajectories(**{"n_traj": 2, "n_t": 3, "n_x": 64, "transient": 5.0, "dt": 0.1, **kwargs})


def test_simulate_refuses_bad_input() -> None:
    u0 = np.zeros((2, 32))
    with pytest.raises(ValueError, match="batch shape"):
        ks.simulate(u0, np.ones(3), L, 0.1, 10)
    with pytest.raises(ValueError, match="multiple of save_every"):
        ks.simulate(u0, 1.0, L, 0.1, 10, save_every=3)
