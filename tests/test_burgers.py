"""The Burgers benchmark: Cole-Hopf exact solution, the paper's finite-difference scheme, the generator.

Independent references: the exact solution is checked against u0, against itself at a finer quadrature,
against the PDE (finite-difference residual), against conservation of the mean and against a separate
pseudo-spectral solver; the scheme is checked against the exact solution (first-order convergence).
"""

from __future__ import annotations

import numpy as np
import pytest

from dks_gym.benchmarks.burgers import BURGERS, exact_solution, initial_condition, pseudo_spectral_solution, solve

NUS = (0.01, 0.1, 1.0)


def grid(nx: int) -> np.ndarray:
    return 2 * np.pi * np.arange(nx) / nx


# Exact solution -------------------------------------------------------------------------------------


@pytest.mark.parametrize("nu", NUS)
def test_exact_solution_starts_from_u0(nu: float) -> None:
    x = grid(256)
    u0 = np.sin(x) + 0.5 * np.cos(2 * x)
    np.testing.assert_array_equal(exact_solution(x, 0.0, nu), u0)
    # |u_t| <= |u u_x| + nu |u_xx| < 6, so u(1e-8) is within 6e-8 of u0.
    assert np.abs(exact_solution(x, 1e-8, nu) - u0).max() < 1e-6


@pytest.mark.parametrize("nu", NUS)
@pytest.mark.parametrize("t", (0.05, 0.495))
def test_exact_solution_quadrature_is_converged_to_machine_precision(nu: float, t: float) -> None:
    x = grid(512)
    u = exact_solution(x, t, nu)
    assert np.abs(exact_solution(x, t, nu, refine=2.0) - u).max() < 1e-12


def _pde_residual(nu: float, t: float, h: float, x: np.ndarray) -> tuple[float, float]:
    """Centred space-time residual of u_t + u u_x - nu u_xx, relative to max |u_t|."""

    def u(xx: np.ndarray, tt: float) -> np.ndarray:
        return exact_solution(xx, tt, nu)

    uc, up, um = u(x, t), u(x + h, t), u(x - h, t)
    u_t = (u(x, t + h) - u(x, t - h)) / (2 * h)
    r = u_t + uc * (up - um) / (2 * h) - nu * (up - 2 * uc + um) / h**2
    return float(np.abs(r).max() / np.abs(u_t).max()), float(np.abs(u_t).max())


@pytest.mark.parametrize("nu", NUS)
def test_exact_solution_satisfies_burgers(nu: float) -> None:
    x = grid(512)
    coarse, u_t_scale = _pde_residual(nu, 0.495, 2e-3, x)
    fine, _ = _pde_residual(nu, 0.495, 1e-3, x)
    assert u_t_scale > 0.5  # the solution does evolve, so a small residual means something
    assert fine < 1e-4
    # Only the O(h^2) truncation of the difference stencil remains.
    assert 3.5 < coarse / fine < 4.5


@pytest.mark.parametrize("nu", NUS)
def test_exact_solution_conserves_the_mean(nu: float) -> None:
    # The periodic trapezoid rule is spectrally accurate; 4096 points resolve the nu = 0.01 front.
    assert abs(exact_solution(grid(4096), 0.25, nu).mean()) < 1e-12


@pytest.mark.parametrize(("nu", "nx"), ((1.0, 64), (0.1, 512), (0.01, 2048)))
def test_exact_solution_matches_pseudo_spectral_solver(nu: float, nx: int) -> None:
    x, u = pseudo_spectral_solution(nu, 0.495, nx)
    assert np.abs(exact_solution(x, 0.495, nu) - u).max() < 1e-10


def test_exact_solution_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="nu"):
        exact_solution(grid(8), 0.1, 0.0)
    with pytest.raises(ValueError, match="t must be"):
        exact_solution(grid(8), -0.1, 0.1)


# Finite-difference scheme ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def refinement() -> dict[int, np.ndarray]:
    """Scheme at t = 0.25 for every nu in NUS on three grids: {nx: (n_nu, nx)}."""
    return {nx: solve(np.array(NUS), np.array([0.0, 0.25]), nx=nx)[:, -1] for nx in (128, 256, 512)}


@pytest.mark.parametrize("i_nu", range(len(NUS)))
def test_scheme_converges_at_first_order_to_the_exact_solution(refinement: dict, i_nu: int) -> None:
    nu = NUS[i_nu]
    errors = {}
    for nx, u in refinement.items():
        e = u[i_nu] - exact_solution(grid(nx), 0.25, nu)
        errors[nx] = (np.abs(e).max(), np.sqrt(np.mean(e**2)))
    for norm in (0, 1):
        for nx in (256, 512):
            order = np.log2(errors[nx // 2][norm] / errors[nx][norm])
            assert 0.8 < order < 1.2, f"nu={nu} nx={nx} norm={'max' if norm == 0 else 'rms'}: order {order:.2f}"


def _textbook_scheme(nu: float, n_frames: int, nx: int) -> np.ndarray:
    """The paper's scheme written out directly, one trajectory, np.roll for the periodic neighbours."""
    dx = 2 * np.pi / nx
    u = initial_condition(grid(nx))
    dt_limit = min(0.1 * dx / 1.5, 0.45 * dx**2 / nu)
    n_sub = int(np.ceil(0.005 / dt_limit))
    dt = 0.005 / n_sub
    frames = [u.copy()]
    for _ in range(n_frames - 1):
        for _ in range(n_sub):
            left, right = np.roll(u, 1), np.roll(u, -1)
            u_x = np.where(u > 0, (u - left) / dx, (right - u) / dx)  # upwind by the sign of u_i
            u = u + dt * (-u * u_x + nu * (right - 2 * u + left) / dx**2)
        frames.append(u.copy())
    return np.array(frames)


def test_solve_is_the_paper_scheme() -> None:
    nus = np.array([0.9, 0.01, 0.2])
    # nx = 1024 (the shipped grid): 13 to 266 substeps per frame, so both step limits are in play.
    fast = solve(nus, 0.005 * np.arange(6), nx=1024)
    for i, nu in enumerate(nus):
        np.testing.assert_allclose(fast[i], _textbook_scheme(nu, 6, 1024), rtol=0, atol=1e-13)


def test_batched_solve_equals_one_trajectory_at_a_time() -> None:
    # Trajectories with different substep counts share the batch; slicing must not couple them.
    nus, times = np.array([0.8, 0.02, 0.3]), np.array([0.0, 0.01, 0.03])
    together = solve(nus, times, nx=64)
    for i, nu in enumerate(nus):
        np.testing.assert_allclose(together[i], solve(np.array([nu]), times, nx=64)[0], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(together[:, 0], np.broadcast_to(initial_condition(grid(64)), (3, 64)))


def test_solve_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="nu"):
        solve(np.array([0.1, -1.0]), np.array([0.0, 0.1]), nx=32)
    with pytest.raises(ValueError, match="non-decreasing"):
        solve(np.array([0.1]), np.array([0.0, 0.2, 0.1]), nx=32)
    with pytest.raises(ValueError, match="nx"):
        solve(np.array([0.1]), np.array([0.0]), nx=2)
    with pytest.raises(ValueError, match="courant"):
        solve(np.array([0.1]), np.array([0.0]), nx=32, courant=0.5, diffusive_factor=0.45)


# Generator ---------------------------------------------------------------------------------------------


def _collect(data) -> dict[str, np.ndarray]:
    out: dict[str, dict[int, np.ndarray]] = {"train": {}, "test": {}}
    for split, i, fields in data.trajectories:
        assert i not in out[split], f"{split} trajectory {i} yielded twice"
        out[split][i] = fields
    return {split: np.stack([d[i] for i in range(len(d))]) for split, d in out.items()}


@pytest.fixture(scope="module")
def small():
    data = BURGERS.generate("small", seed=0, progress=False)
    return data, _collect(data)


def test_small_preset_shapes_dtypes_and_metadata(small) -> None:
    data, fields = small
    assert fields["train"].shape == (6, 100, 1, 1024) and fields["test"].shape == (3, 100, 1, 1024)
    assert fields["train"].dtype == np.float32
    assert data.params["train"].dtype == np.float64 and data.params["train"].shape == (6,)
    np.testing.assert_allclose(data.time, 0.005 * np.arange(100), rtol=0, atol=1e-15)
    np.testing.assert_array_equal(data.coords[0], grid(1024))
    assert data.cell_type is None
    assert data.generator["name"] == "dks_gym.benchmarks.burgers"
    assert data.generator["courant"] == 0.1 and data.generator["diffusive_factor"] == 0.45
    assert data.generator["seed"] == 0 and data.generator["preset"] == "small"
    # Maximum principle: |u| never exceeds max |u0| = 1.5.
    assert np.abs(fields["train"]).max() <= 1.5 + 1e-6


def test_frames_sit_at_their_times(small) -> None:
    data, fields = small
    x = grid(1024)
    u0 = initial_condition(x).astype(np.float32)
    np.testing.assert_array_equal(fields["test"][:, 0, 0], np.broadcast_to(u0, (3, 1024)))
    for nu, traj in zip(data.params["test"], fields["test"]):
        for k in (1, 50, 99):
            rms = {j: np.sqrt(np.mean((traj[k, 0] - exact_solution(x, 0.005 * j, nu)) ** 2)) for j in (k - 1, k, k + 1)}
            # The scheme's RMS error at nx = 1024 is below 5e-3 (validation/burgers_convergence.py);
            # the change over one frame is larger, so a frame at the wrong time fails.
            assert rms[k] < 5e-3 and rms[k] < rms[k - 1] and rms[k] < rms[k + 1], (nu, k, rms)


def test_same_seed_gives_identical_data(small) -> None:
    data, fields = small
    again = BURGERS.generate("small", seed=0, progress=False)
    np.testing.assert_array_equal(again.params["train"], data.params["train"])
    np.testing.assert_array_equal(_collect(again)["test"], fields["test"])


def test_viscosities_are_distinct_interleaved_and_in_range() -> None:
    for preset, (n_train, n_test) in (("paper", (50, 10)), ("small", (6, 3))):
        params = BURGERS.generate(preset, seed=3, progress=False).params  # lazy: nothing is solved yet
        train, test = params["train"], params["test"]
        assert train.shape == (n_train,) and test.shape == (n_test,)
        both = np.concatenate([train, test])
        assert np.unique(both).size == both.size
        assert both.min() >= 0.01 and both.max() <= 1.0
        # Every test value has training values on both sides and no two test values are neighbours.
        assert train.min() < test.min() and test.max() < train.max()
        is_test = np.isin(np.sort(both), test)
        assert not np.any(is_test[1:] & is_test[:-1])
    seed3 = BURGERS.generate("paper", seed=3, progress=False).params["train"]
    np.testing.assert_array_equal(BURGERS.generate("paper", seed=3, progress=False).params["train"], seed3)
    assert not np.any(BURGERS.generate("paper", seed=4, progress=False).params["train"] == seed3)


def test_generate_rejects_bad_arguments() -> None:
    with pytest.raises(ValueError, match="preset"):
        BURGERS.generate("huge", progress=False)
    with pytest.raises(ValueError, match="unknown option"):
        BURGERS.generate("small", progress=False, n_points=10)


# Static description -------------------------------------------------------------------------------------


def test_benchmark_description_matches_spec() -> None:
    assert (BURGERS.name, BURGERS.env_id, BURGERS.grid) == ("burgers", "DKS/Burgers-v0", (1024,))
    assert BURGERS.channels == ("u",) and BURGERS.observed_channel == "u" and BURGERS.scored_channels == ("u",)
    assert (BURGERS.param_name, BURGERS.param_range, BURGERS.dt) == ("nu", (0.01, 1.0), 0.005)
    assert (BURGERS.n_frames, BURGERS.n_train, BURGERS.n_test) == (100, 50, 10)
    assert BURGERS.cell_type() is None


def test_paper_layout_is_equidistant_and_symmetric() -> None:
    idx = BURGERS.paper_layout()
    np.testing.assert_array_equal(idx, 32 + 64 * np.arange(16))
    assert np.unique(idx).size == 16
    assert np.all(np.diff(idx) == 64) and (idx[0] + 1024 - idx[-1]) == 64  # equidistant around the circle
    np.testing.assert_array_equal(np.sort((1024 - idx) % 1024), idx)  # mirror image about x = pi
    for m in (1, 3, 7, 1024):
        layout = BURGERS.paper_layout(m)
        assert layout.size == m and np.unique(layout).size == m and layout.min() >= 0 and layout.max() < 1024


@pytest.mark.parametrize("m", (0, -4, 1025, 2.5, "16", True))
def test_paper_layout_rejects_bad_m(m) -> None:
    with pytest.raises(ValueError, match="m \\(number of sensors\\)"):
        BURGERS.paper_layout(m)
