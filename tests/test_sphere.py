"""The batched lattice Boltzmann solver and the sphere benchmark built on it (CPU, eager torch).

Exactness checks: Poiseuille flow against the parabolic profile (second-order convergence), mass and
momentum conservation in a periodic box, a batch equals its cases run one by one, a chunked sweep
equals an unchunked one. Physics check: drag on the sphere at Re = 20 on a coarse lattice. End to end:
the `small` preset generated through the dataset layer and `check_env` on DKS/Sphere-v0.
"""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

import dks_gym  # noqa: F401  (registers the ids)
from dks_gym.benchmarks import get_benchmark
from dks_gym.solvers import lbm, sphere_case


def _channel(h: int, nu: float, steps: int) -> float:
    """Max relative error of the D2Q9 force-driven channel (walls half-way, h fluid nodes) vs the parabola."""
    g = 1e-6
    shape = (4, h + 2)
    solid = np.zeros(shape, bool)
    solid[:, [0, -1]] = True
    sim = lbm.LBM("D2Q9", shape, [nu], solid=solid, acceleration=(g, 0.0), smagorinsky=0.0)
    sim.step(steps)
    _, u = sim.macroscopic()
    y = np.arange(1, h + 1) - 0.5  # walls at y = 0 and y = h
    exact = lbm.poiseuille_profile(h, y, g, nu)
    return float(np.abs(u[0, 0, 1, 1:-1].double().numpy() - exact).max() / exact.max())


def test_lattices_are_consistent() -> None:
    for lat in lbm.LATTICES.values():
        assert np.isclose(lat.w.sum(), 1.0)
        assert np.allclose(lat.w @ lat.c, 0.0)
        assert np.allclose((lat.w[:, None, None] * lat.c[:, :, None] * lat.c[:, None, :]).sum(0), np.eye(lat.d) / 3)
        assert (lat.c[lat.opp] == -lat.c).all()


def test_poiseuille_profile_converges_at_second_order() -> None:
    nu = 0.1
    coarse = _channel(8, nu, int(3 * 8**2 / nu))
    fine = _channel(16, nu, int(3 * 16**2 / nu))
    assert coarse < 0.02 and fine < 0.005
    assert coarse / fine > 3.5  # second order: 4 when halving the spacing


@pytest.mark.parametrize("lattice, shape", [("D2Q9", (12, 10)), ("D3Q19", (8, 6, 6))])
def test_periodic_box_conserves_mass_and_momentum(lattice: str, shape: tuple[int, ...]) -> None:
    d = len(shape)
    rng = np.random.default_rng(0)
    sim = lbm.LBM(lattice, shape, [0.01, 0.1], smagorinsky=0.15)
    sim.initialize(0.05 * rng.standard_normal((2, d, *shape)))
    mass0 = sim.mass().double()
    mom0 = (sim.f.double().flatten(2).sum(-1) @ sim.c.double())
    sim.step(200)
    assert torch.allclose(sim.mass().double(), mass0, rtol=1e-5)
    mom = sim.f.double().flatten(2).sum(-1) @ sim.c.double()
    assert torch.allclose(mom, mom0, atol=1e-4)
    assert sim.is_finite().all()


def test_batch_equals_separate_runs() -> None:
    shape = (30, 14)
    solid = np.zeros(shape, bool)
    solid[:, [0, -1]] = True
    x, y = np.meshgrid(np.arange(30), np.arange(14), indexing="ij")
    body = (x - 8) ** 2 + (y - 6.5) ** 2 < 9
    solid |= body
    kw = {"solid": solid, "body": body, "inlet_velocity": (0.05, 0.0), "outlet": True}
    nus = [0.01, 0.05, 0.2]
    batch = lbm.LBM("D2Q9", shape, nus, **kw)
    batch.step(60)
    for i, nu in enumerate(nus):
        one = lbm.LBM("D2Q9", shape, [nu], **kw)
        one.step(60)
        torch.testing.assert_close(batch.f[i : i + 1], one.f, rtol=1e-5, atol=1e-7)
        torch.testing.assert_close(batch.body_force()[i : i + 1], one.body_force(), rtol=1e-4, atol=1e-7)


def test_velocity_inlet_keeps_the_mass_flux() -> None:
    """Channel with a parabolic NEE velocity inlet and the pressure outlet: steady, the mass flux is the same
    through every section (mass conservation) and the volume flux equals the inlet's to within the weak
    compressibility (Delta rho ~ 1 % over the channel), and the profile stays parabolic."""
    shape = (40, 12)
    solid = np.zeros(shape, bool)
    solid[:, [0, -1]] = True
    y = np.arange(12) - 0.5  # walls at y = 0 and y = 10
    profile = np.where((y > 0) & (y < 10), 0.075 * 4 * y * (10 - y) / 100, 0.0)
    inlet = np.stack([profile, np.zeros_like(profile)])
    sim = lbm.LBM("D2Q9", shape, [0.02], solid=solid, inlet_velocity=inlet, outlet=True, smagorinsky=0.0)
    sim.step(8000)
    rho, u = sim.macroscopic()
    mass_flux = (rho[0] * u[0, 0]).sum(1).numpy()[1:-1]  # per interior x section
    volume_flux = u[0, 0].sum(1).numpy()
    np.testing.assert_allclose(mass_flux, mass_flux.mean(), rtol=2e-4)
    assert volume_flux[1] == pytest.approx(profile.sum(), rel=0.005)  # what enters is what the inlet imposes
    np.testing.assert_allclose(volume_flux, profile.sum(), rtol=0.015)  # u grows as rho drops downstream
    np.testing.assert_allclose(u[0, 0, 20].numpy(), profile, atol=0.01 * profile.max())
    assert float(rho[0, -1].mean()) == pytest.approx(1.0, abs=2e-3)  # the outlet holds p = 0


def test_interpolation_reproduces_linear_functions() -> None:
    nodes = np.linspace(-1.0, 3.0, 9)
    targets = np.array([-1.0, -0.3, 0.1, 2.99, 3.0])
    m = sphere_case.interpolation_matrix(nodes, targets)
    np.testing.assert_allclose(m @ (2 * nodes + 1), 2 * targets + 1, atol=1e-12)
    periodic = np.arange(8) + 0.5  # period 8: 7.9 lies between nodes 7.5 and 8.5 = 0.5
    mp = sphere_case.interpolation_matrix(periodic, np.array([7.9, 0.1]), period=8.0)
    np.testing.assert_allclose(mp.sum(1), 1.0)
    assert mp[0, 7] == pytest.approx(0.6) and mp[0, 0] == pytest.approx(0.4)


def test_cylinder_drag_matches_schafer_turek_2d1() -> None:
    """Force check in 2D: the Schafer-Turek (1996) benchmark 2D-1 (cylinder D at (2D, 2D) in a channel of
    height 4.1 D, parabolic inflow, Re = U_mean D / nu = 20), reference Cd = 5.5795, Cl = 0.0106. With
    D = 10 lattice nodes the staircase cylinder gives Cd about 10 % high (5.88 at D = 20: first order)."""
    d = 10
    h, length = 41, 220
    shape = (length + 1, h + 2)
    x = np.arange(shape[0])[:, None]
    y = np.arange(shape[1])[None, :] - 0.5  # walls at y = 0 and y = h
    body = (x - 2 * d) ** 2 + (y - 2 * d) ** 2 < (d / 2) ** 2
    solid = body.copy()
    solid[:, [0, -1]] = True
    u_mean = 0.05
    yy = y[0]
    profile = np.where((yy > 0) & (yy < h), 6 * u_mean * yy * (h - yy) / h**2, 0.0)
    sim = lbm.LBM("D2Q9", shape, [u_mean * d / 20], solid=solid, body=body, outlet=True, smagorinsky=0.0,
                  inlet_velocity=np.stack([profile, 0 * profile]))
    sim.initialize(np.stack([np.broadcast_to(profile, shape), np.zeros(shape)]))
    sim.step(6000)
    cd, cl = (sim.body_force()[0].numpy() / (0.5 * u_mean**2 * d)).tolist()
    assert 1.0 < cd / 5.5795 < 1.12, cd
    assert 0.0 < cl < 0.03, cl


def test_sphere_drag_at_low_reynolds_number() -> None:
    """Re = 20, 3 nodes per R, y walls replaced by periodic faces (a square array of spheres 8R apart):
    steady, symmetric, Cd above Schiller-Naumann (2.61) by the array's confinement and the coarse
    staircase (see docs/sphere.md for the resolution study); measured 3.45 = 1.32 Cd_SN when this test was
    written. With the benchmark's no-slip walls it is about twice Schiller-Naumann (5.5: the walls'
    boundary layers speed up the core flow at this low Re)."""
    bench = get_benchmark("sphere")
    out = sphere_case.simulate(
        [20.0],
        {"resolution": 3, "u_lattice": 0.1, "spin_up": 12.0, "n_frames": 3, "perturbation": 0.0, "walls": False},
        coords=bench.coords(), cell_type=bench.cell_type(), fields=False,
    )
    cd = out["drag"][0, -1]
    sn = 24 / 20 * (1 + 0.15 * 20**0.687)
    assert 1.0 < cd / sn < 1.6, cd
    assert abs(out["drag"][0, -1] - out["drag"][0, 0]) < 0.03 * cd  # nearly steady after 12 R/U
    assert abs(out["lift"][0, -1]) < 0.01 * cd and abs(out["lift_z"][0, -1]) < 0.01 * cd


def test_chunked_sweep_equals_unchunked() -> None:
    bench = get_benchmark("sphere")
    settings = {"resolution": 2, "u_lattice": 0.1, "spin_up": 1.0, "n_frames": 2}
    kw = {"coords": bench.coords(), "cell_type": bench.cell_type()}
    whole = sphere_case.simulate([80.0, 400.0, 900.0], settings, max_batch=3, **kw)
    parts = sphere_case.simulate([80.0, 400.0, 900.0], settings, max_batch=1, **kw)
    assert whole["batch_size"] == 3 and parts["batch_size"] == 1
    np.testing.assert_allclose(parts["fields"], whole["fields"], rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(parts["drag"], whole["drag"], rtol=1e-4, atol=1e-6)


def test_memory_estimate_and_chunks() -> None:
    per = lbm.bytes_per_case("D3Q19", (193, 66, 64))
    assert per > 19 * 193 * 66 * 64 * 4
    assert [(s.start, s.stop) for s in lbm.chunks(7, 3)] == [(0, 3), (3, 6), (6, 7)]
    assert lbm.max_batch(10**30, "cpu") == 1


def test_unknown_option_is_rejected() -> None:
    with pytest.raises(ValueError, match="unknown option"):
        get_benchmark("sphere").generate("small", workers=2)
    with pytest.raises(ValueError, match="integer"):
        get_benchmark("sphere").generate("small", resolution=3, u_lattice=0.07)


@pytest.fixture(scope="module")
def sphere_small(data_home: Path) -> Path:
    from dks_gym.dataset import generate_dataset

    return generate_dataset("sphere", "small", progress=False)


def test_small_preset_file_and_env(sphere_small: Path) -> None:
    from dks_gym.dataset import Dataset

    bench = get_benchmark("sphere")
    with Dataset(sphere_small) as ds:
        assert ds.grid == (64, 64, 64) and ds.n_frames == 10
        assert ds.n_trajectories("train") == 4 and ds.n_trajectories("test") == 2
        extras = ds.extras("train")
        assert set(extras) == {"drag", "lift", "lift_z"} and extras["drag"].shape == (4, 10)
        traj = ds.trajectory("train", 0)
        inside = bench.cell_type() == 2
        assert np.all(traj[:, :, inside] == 0)
        u = traj[:, 0][:, ~inside]
        assert 0.3 < u.mean() < 1.5  # velocity in units of U
        assert np.isfinite(traj).all()
        assert np.all(np.diff(ds.params("train")) > 0)
    env = gym.make("DKS/Sphere-v0", data_path=str(sphere_small), disable_env_checker=True)
    check_env(env.unwrapped, skip_render_check=True)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (16,)


def test_reproduce_runs_the_sphere_small_preset_end_to_end(sphere_small: Path, tmp_path: Path) -> None:
    """The 3D path through `dks-gym reproduce sphere --preset lite` (the paper data need a GPU): two
    neural lite models trained a few steps on the small preset (its 10 frames are too few for pDMD at r = 32,
    which needs r + 1), then the operator-norm experiment (forward run and EKF of each) writes its results,
    tables and figures; the Koopman operator stays a contraction.

    Long (about 30 s on one core) because it is the one end-to-end check of the 3D path through the command
    line: two trainings and four filter runs that decode 4 x 64^3 fields at every step."""
    from click.testing import CliRunner

    from dks_gym.dataset import Dataset
    from dks_gym.evaluation.commands import reproduce_command
    from dks_gym.evaluation.results import load_results
    from dks_gym.models import train_model, training_schedule

    ds = Dataset(sphere_small)
    neural = ("koopman", "mlp")  # the explicit and the autodiff Jacobian; xLSTM's adds time, not a path
    for kind in neural:
        train_model("sphere", kind, 32, "lite", 1, dataset=ds, schedule=training_schedule("sphere", "lite", steps=2),
                    progress=False)
    out = tmp_path / "sphere"
    result = CliRunner().invoke(reproduce_command, ["sphere", "--preset", "lite", "--data-preset", "small",
                                                    "--only", "operator_norm", "--out", str(out), "--no-train",
                                                    *[a for m in neural for a in ("--model", m)]])
    assert result.exit_code == 0, result.output + repr(result.exception)
    doc = load_results(out / "results.json.gz")
    assert {(r["model"], r["filter"]) for r in doc["records"]} == {(m, f) for m in neural for f in ("forward", "ekf")}
    assert all(r["batch"] == 2 and r["final_mse_mean"] is not None for r in doc["records"])
    koopman = [r for r in doc["records"] if r["model"] == "koopman"]
    assert max(v for r in koopman for v in r["max_forecast_norm"]) <= 1 + 1e-5
    assert "Table IX" in (out / "tables.md").read_text()
    assert set(doc["records"][0]["final_channel_nmse_mean"]) == set(ds.scored_channels)
