"""Placement policies and the evaluation harness (agents/): valid layouts everywhere, QR and CCQR against
PySensors (its layouts stored by tests/references/make_references.py: the package pivots itself), greedy
against the filter run independently, the monotone covariance objective, PPO smoke runs, the results file."""

from __future__ import annotations

import dataclasses
import json
import pickle
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

import dks_gym  # noqa: F401
from dks_gym_agents.baselines import (
    GreedyLayout,
    PaperLayout,
    QRLayout,
    RandomLayout,
    ccqr_pivots,
    observed_snapshots,
    pod_modes,
    qr_pivots,
)
from dks_gym_agents.policies import PlacementTask, candidate_lattice, check_layout, distinct_picks
from dks_gym_agents.scoring import LinearizedTrajectories, covariance_traces, run_layouts
from dks_gym.dataset import Dataset, write_dataset
from dks_gym.assimilation import AssimilationConfig
from dks_gym.models import build_model
from dks_gym.models.calibration import calibrate
from dks_gym.wrappers import LatentFilter

sys.path.insert(0, str(Path(__file__).parent))
from conftest import synthetic_data  # noqa: E402

from tests.pictures import ink  # noqa: E402
from tests.references.make_references import assert_same_input, load_references  # noqa: E402

CFD = ("cylinder", "dambreak", "sphere")


def _noisy_synthetic(benchmark: str, path: Path, solid_boost: float = 1.0, n_t: int = 6) -> Path:
    """The conftest's synthetic CFD file with seeded noise added, so its 2 n_t training snapshots hold 2 n_t - 1
    POD modes (the travelling waves alone hold a handful).

    ``solid_boost`` scales the noise in solid cells: a large value makes them the most variable cells, the
    ones an unconstrained QR would pick.
    """
    from dks_gym.benchmarks import get_benchmark

    bench = get_benchmark(benchmark)
    data = synthetic_data(benchmark, n_train=2, n_test=1, n_t=n_t)
    rng = np.random.default_rng(1)
    solid = ~bench.fluid_mask()
    scale = np.where(solid, solid_boost, 1.0).astype(np.float32)

    def noisy():
        for split, i, fields in data.trajectories:
            yield split, i, (fields + 0.3 * scale * rng.standard_normal(fields.shape)).astype(np.float32)

    write_dataset(dataclasses.replace(data, trajectories=noisy()), benchmark, path)
    return path


def _untrained(benchmark: str, ds: Dataset):
    """An untrained lite Koopman model (r=4) with the calibration training would store (for the default
    calibrated Q and P0), measured on two training trajectories."""
    model = build_model(benchmark, "koopman", r=4, preset="lite", dataset=ds, seed=0)
    model.calibration = calibrate(model, ds, [0, 1])
    return model


@pytest.fixture(scope="module")
def burgers_task(burgers_small: Path) -> PlacementTask:
    """Burgers `small` data with an untrained lite Koopman model (r=4): the plumbing does not depend on training."""
    ds = Dataset(burgers_small)
    return PlacementTask(ds, _untrained("burgers", ds))


@pytest.fixture(scope="module")
def cfd_tasks(tmp_path_factory: pytest.TempPathFactory) -> dict[str, PlacementTask]:
    folder = tmp_path_factory.mktemp("agents_cfd")
    tasks = {}
    for bench in CFD:
        ds = Dataset(_noisy_synthetic(bench, folder / f"{bench}.h5"))
        tasks[bench] = PlacementTask(ds, _untrained(bench, ds), AssimilationConfig(n_sensors=4))
    return tasks


def _task(name: str, burgers_task: PlacementTask, cfd_tasks: dict[str, PlacementTask]) -> PlacementTask:
    return burgers_task if name == "burgers" else cfd_tasks[name]


@pytest.mark.parametrize("bench", ["burgers", *CFD])
def test_every_policy_gives_valid_layouts(bench: str, burgers_task, cfd_tasks) -> None:
    """m distinct fluid cells from every policy on every benchmark (static ones once, adaptive ones every step)."""
    from stable_baselines3 import PPO

    from dks_gym_agents.adaptive import PPOAdaptive, make_adaptive_env
    from dks_gym_agents.evaluate import evaluate_policy
    from dks_gym_agents.sequential import LayoutScorer, SequentialLayout, SequentialPlacementVecEnv

    task = _task(bench, burgers_task, cfd_tasks)
    task = dataclasses.replace(task, config=AssimilationConfig(n_sensors=4))
    m = task.n_sensors
    fluid = task.fluid_mask.ravel()
    lattice = candidate_lattice(task, 3 * m)
    static = [PaperLayout(), RandomLayout(0), RandomLayout(1), QRLayout(),
              GreedyLayout("trace", candidates=lattice, n_trajectories=2),
              GreedyLayout("information", candidates=lattice, n_trajectories=2),
              GreedyLayout("error", candidates=lattice[: m + 1], n_trajectories=1)]
    seq_env = SequentialPlacementVecEnv(LayoutScorer(task), lattice, n_envs=2)
    static.append(SequentialLayout(agent=PPO("MlpPolicy", seq_env, n_steps=m, batch_size=2 * m, seed=0, device="cpu"),
                                   candidates=lattice))
    layouts = {}
    for policy in static:
        layout = policy.fit(task).layout
        check_layout(task, layout)  # raises on repeats, solid cells, wrong length
        assert layout.shape == (m,) and len(set(layout.tolist())) == m and fluid[layout].all(), policy.name
        layouts[policy.name] = layout
    assert set(layouts["sequential"]) <= set(lattice) and set(layouts["greedy"]) <= set(lattice)
    assert not np.array_equal(np.sort(layouts["random-0"]), np.sort(layouts["random-1"]))
    np.testing.assert_array_equal(RandomLayout(0).fit(task).layout, layouts["random-0"])  # seeded

    agent = PPO("MlpPolicy", make_adaptive_env(task, lattice, n_envs=1), n_steps=8, batch_size=8, seed=0,
                device="cpu")
    run = evaluate_policy(task, PPOAdaptive(agent=agent, candidates=lattice), trajectories=[0])
    steps = run.layouts.reshape(-1, m)
    assert steps.shape[0] == task.dataset.n_frames - 1
    for row in steps:
        assert len(set(row.tolist())) == m and fluid[row].all() and set(row.tolist()) <= set(lattice.tolist())


def _burgers_snapshots(ds: Dataset) -> np.ndarray:
    """All training frames of the Burgers data as a mean-subtracted float64 snapshot matrix (N, 1024)."""
    fields = np.asarray(ds.fields("train")[:, :, 0], dtype=np.float64)  # (n, n_t, 1024)
    X = fields.reshape(-1, fields.shape[-1])
    return X - X.mean(axis=0)


# PySensors (python-sensors) is a dev-only cross-check that no extra installs: the layouts it picks on the
# inputs below are stored by tests/references/make_references.py, which builds those inputs with these helpers.
def test_qr_equals_pysensors_on_an_independent_svd_basis(burgers_task: PlacementTask) -> None:
    """Our POD (Gram eigendecomposition) + scipy's pivoted QR gives the sensors PySensors picks with its own
    SVD basis and its QR optimizer (SSPOR, 16 arpack SVD modes, 16 sensors)."""
    refs = load_references()
    assert_same_input(refs, "qr_burgers.input", _burgers_snapshots(burgers_task.dataset))
    qr = QRLayout().fit(burgers_task)
    expected = refs["qr_burgers.sensors"]
    np.testing.assert_array_equal(qr.layout, expected)
    assert not qr.used_ccqr  # Burgers has no solid cells: plain QR
    # The check can fail: fewer modes rank other cells.
    assert not np.array_equal(QRLayout(n_modes=17).fit(burgers_task).layout, expected)


def test_ccqr_keeps_qr_out_of_the_body(tmp_path: Path) -> None:
    """Cylinder data whose body cells vary most: plain QR picks body cells, the cost map (CCQR) never does,
    and the layout equals PySensors' CCQR with that cost map on an independent SVD basis."""
    refs = load_references()
    ds = Dataset(_noisy_synthetic("cylinder", tmp_path / "cylinder.h5", solid_boost=30.0))
    task = PlacementTask(ds, _untrained("cylinder", ds), AssimilationConfig(n_sensors=8))
    solid = ~task.fluid_mask.ravel()
    X = observed_snapshots(ds).astype(np.float64)
    X -= X.mean(axis=0)
    assert_same_input(refs, "ccqr_cylinder.input", X)
    unconstrained = refs["ccqr_cylinder.unconstrained"]  # PySensors' SSPOR with no cost map
    assert solid[unconstrained].any()
    np.testing.assert_array_equal(qr_pivots(pod_modes(X, 8)[0], 8), unconstrained)  # and ours, the same
    policy = QRLayout().fit(task)
    assert policy.used_ccqr and not solid[policy.layout].any()
    np.testing.assert_array_equal(policy.layout, refs["ccqr_cylinder.sensors"])


PIVOT_CASES = ("dense", "negative-costs", "forbidden", "exhausted", "preferred-zero-rows")


def _pivot_case(case: str) -> tuple[np.ndarray, np.ndarray]:
    """A random orthonormal basis (300, 12) and a cost map (300,) for one case of the pivoting cross-check."""
    rng = np.random.default_rng(1)
    n, r = 300, 12
    basis = np.linalg.qr(rng.standard_normal((n, r)))[0]
    costs = np.zeros(n)
    if case == "negative-costs":
        costs = rng.uniform(-0.05, 0.1, n)  # comparable to the row norms (~0.2): they reorder the picks
    elif case == "forbidden":
        costs[rng.choice(n, 250, replace=False)] = 1e6
    elif case == "exhausted":
        allowed = rng.choice(n, 20, replace=False)
        basis[allowed[5:]] = 0.0  # only 5 allowed cells carry the basis
        costs[:] = 1e6
        costs[allowed] = 0.0
    elif case == "preferred-zero-rows":
        zero = rng.choice(n, 3, replace=False)
        basis[zero] = 0.0
        costs[zero] = -0.5  # preferred cells that carry nothing: they are picked with a zero residual
    return basis, costs


@pytest.mark.parametrize("case", PIVOT_CASES)
def test_pivots_equal_pysensors_optimizers_on_random_bases(case: str) -> None:
    """qr_pivots and ccqr_pivots rank every cell PySensors' QR and CCQR optimizers rank, in the same order,
    on random orthonormal bases: no costs, mixed-sign costs, forbidden cells, a basis whose allowed cells
    run out (rows exactly zero) before the last pivot, and zero rows that negative costs make pivots (the
    one case where PySensors' zero-pivot reflector, reproduced as is, changes the later picks)."""
    refs = load_references()
    basis, costs = _pivot_case(case)
    n, r = basis.shape
    assert_same_input(refs, f"pivots.{case}.basis", basis)
    assert_same_input(refs, f"pivots.{case}.costs", costs)
    expected = refs[f"pivots.{case}.ccqr"]  # PySensors' CCQR(sensor_costs=costs), the first r pivots
    ours = ccqr_pivots(basis, costs, r)
    np.testing.assert_array_equal(ours, expected)
    for k in (1, 5, r):  # the greedy prefix does not depend on where it stops
        np.testing.assert_array_equal(ccqr_pivots(basis, costs, k), expected[:k])
    if case == "dense":
        np.testing.assert_array_equal(ours, refs[f"pivots.{case}.qr"])  # no cost: PySensors' plain QR
        np.testing.assert_array_equal(qr_pivots(basis, r), refs[f"pivots.{case}.qr"])
    if case == "forbidden":
        assert (costs[ours] == 0).all()
        assert not np.array_equal(ours, qr_pivots(basis, r))  # the costs matter: this check can fail
    if case == "negative-costs":
        assert not np.array_equal(ours, ccqr_pivots(basis, np.zeros(n), r))
    with pytest.raises(ValueError, match="n_pivots"):
        ccqr_pivots(basis, costs, r + 1)
    with pytest.raises(ValueError, match="costs"):
        ccqr_pivots(basis, costs[:-1], r)


def test_greedy_trace_falls_monotonically_and_matches_a_numpy_riccati(burgers_task: PlacementTask) -> None:
    """The covariance objective only falls as sensors are added (Loewner order of the Riccati map), and its
    value equals a plain numpy EKF covariance recursion with the same Jacobians."""
    task = dataclasses.replace(burgers_task, config=AssimilationConfig(n_sensors=6))
    lattice = candidate_lattice(task, 24)
    greedy = GreedyLayout("trace", candidates=lattice, n_trajectories=2).fit(task)
    history = np.array(greedy.history)
    assert np.all(np.diff(history) <= 1e-12 * history[0]) and history[-1] < history[0]

    lin = LinearizedTrajectories(task.model, task.dataset, greedy.used_trajectories, lattice, task.config)
    cfg = task.config
    layout = greedy.layout
    ours = covariance_traces(lin, layout[None], cfg)[0]  # (T, n_t - 1)
    pos = np.searchsorted(lin.cells, layout)
    P0 = np.asarray(cfg.filter.initial_covariance(task.model), dtype=np.float64)  # the calibrated (r, r) ones
    Q = np.asarray(cfg.filter.process_noise(task.model), dtype=np.float64)
    assert P0.shape == Q.shape == (task.model.r, task.model.r)
    for t in range(len(lin.trajectories)):
        P = P0.copy()
        R = float(lin.sigma[t]) ** 2 * np.eye(len(layout))
        for k in range(1, lin.J.shape[1]):
            F, J, M = lin.F[t, k - 1].numpy(), lin.J[t, k][pos].numpy(), lin.M[t, k].numpy()
            P = F @ P @ F.T + Q
            K = P @ J.T @ np.linalg.inv(J @ P @ J.T + R)
            P = (np.eye(task.model.r) - K @ J) @ P
            assert ours[t, k - 1] == pytest.approx(np.trace(M @ P), rel=1e-6)
    assert greedy.history[-1] == pytest.approx(ours.mean(), rel=1e-9)


def _tiny_linearization(seed: int = 0, n_traj: int = 2, n_t: int = 6, n_cells: int = 7, r: int = 3):
    """A stand-in for LinearizedTrajectories: random F_k, J_k over a few cells, per-trajectory sigma."""
    from types import SimpleNamespace

    rng = np.random.default_rng(seed)
    F = torch.as_tensor(rng.standard_normal((n_traj, n_t - 1, r, r)) * 0.6 + np.eye(r))
    J = torch.as_tensor(rng.standard_normal((n_traj, n_t, n_cells, r)))
    return SimpleNamespace(F=F, J=J, sigma=torch.tensor([0.5, 0.8][:n_traj], dtype=torch.float64),
                           cells=np.arange(n_cells) * 10, trajectories=np.arange(n_traj))


def test_episode_information_is_what_the_filter_learns_about_the_initial_state() -> None:
    """With no process noise the EKF's final covariance is Phi_N I^{-1} Phi_N^T (I the information about z_0),
    so log det I = 2 log |det Phi_N| - log det P_N: the filters' own recursion checks episode_information."""
    from dks_gym.filters import GaussianState, LatentDynamics, ekf_forecast, ekf_update
    from dks_gym_agents.scoring import episode_information, information_logdets

    lin = _tiny_linearization()
    prior = torch.diag(torch.tensor([0.5, 2.0, 1.0], dtype=torch.float64))
    layout = np.array([10, 40, 60])
    ours = information_logdets(lin, episode_information(lin), layout[None], prior)[0]
    for t in range(2):
        state = GaussianState(torch.zeros(1, 3, dtype=torch.float64), torch.linalg.inv(prior)[None])
        phi = torch.eye(3, dtype=torch.float64)
        for k in range(1, lin.J.shape[1]):
            dyn = LatentDynamics(lambda z: z, lambda z: torch.zeros(1, 3, dtype=torch.float64),
                                 forecast_jacobian=lin.F[t, k - 1][None],
                                 observe_jacobian=lin.J[t, k][layout // 10][None])
            state, _ = ekf_forecast(state, dyn, 0.0)
            state, _ = ekf_update(state, torch.zeros(1, 3, dtype=torch.float64), dyn, float(lin.sigma[t]) ** 2)
            phi = lin.F[t, k - 1] @ phi
        expected = 2 * torch.linalg.slogdet(phi)[1] - torch.linalg.slogdet(state.cov[0])[1]
        assert ours[t] == pytest.approx(float(expected), rel=1e-9)


def test_d_optimal_greedy_against_a_brute_force_search() -> None:
    """On a tiny case every 3-of-7 layout is scored: the greedy layout's gain over the prior is within the
    (1 - 1/e) bound of the best one's (log det is monotone submodular), and equals it here."""
    import itertools

    from dks_gym_agents.baselines import greedy_layout
    from dks_gym_agents.scoring import episode_information, information_logdets

    lin = _tiny_linearization(seed=1)
    info, prior = episode_information(lin), torch.eye(3, dtype=torch.float64)

    def score(layouts: np.ndarray) -> np.ndarray:
        return -information_logdets(lin, info, layouts, prior).mean(axis=1)

    chosen, history, _ = greedy_layout(score, lin.cells, 3)
    every = np.array(list(itertools.combinations(lin.cells, 3)))
    values = score(every)
    best = -values.min()  # the prior's log det is 0
    assert -history[-1] >= (1 - 1 / np.e) * best
    assert -history[-1] == pytest.approx(best, rel=1e-12)
    assert sorted(chosen.tolist()) == sorted(every[values.argmin()].tolist())
    assert np.all(np.diff(history) < 0)  # every sensor adds information


def test_greedy_error_scores_are_the_filter_error_of_latent_filter_runs(burgers_task: PlacementTask) -> None:
    """The greedy 'error' objective of its final layout equals the time-averaged MSE of LatentFilter episodes
    on the same training trajectories and noise (a second, unbatched implementation of the same runs)."""
    task = dataclasses.replace(burgers_task, config=AssimilationConfig(n_sensors=3, noise_seed=5))
    greedy = GreedyLayout("error", candidates=np.arange(8, 1024, 128), n_trajectories=2).fit(task)
    assert len(greedy.scores[0]) == 8 and len(greedy.scores[-1]) == 6
    errors = []
    for t in greedy.used_trajectories:
        env = LatentFilter(gym.make("DKS/Burgers-v0", data_path=str(task.dataset.path), split="train",
                                    sensors=greedy.layout), model=task.model, filter="ekf")
        env.reset(options={"trajectory": int(t), "noise_seed": 5})
        done, mse = False, []
        while not done:
            _, _, terminated, truncated, info = env.step(None)
            mse.append(info["mse"])
            done = terminated or truncated
        errors.append(np.mean(mse))
    assert greedy.history[-1] == pytest.approx(np.mean(errors), rel=2e-4)


def test_run_layouts_is_the_filter_per_layout(burgers_task: PlacementTask) -> None:
    """Two layouts batched on the same trajectory (sharing cells) give each what a lone run of that layout gives."""
    # The paper's P0 and Q: an untrained model's calibrated ones are so small that no layout moves it.
    cfg = AssimilationConfig(n_sensors=4, noise_seed=3).replace(Q="paper", P0="paper")
    a, b = np.array([10, 300, 600, 900]), np.array([10, 310, 620, 900])
    both = run_layouts(burgers_task.model, burgers_task.dataset, np.stack([a, b]), [1, 1], cfg)
    for row, layout in enumerate((a, b)):
        alone = run_layouts(burgers_task.model, burgers_task.dataset, layout[None], [1], cfg)
        np.testing.assert_allclose(both.step_mse[row], alone.step_mse[0], rtol=1e-4, atol=1e-9)
    assert not np.allclose(both.step_mse[0], both.step_mse[1])


def test_distinct_picks_moves_repeats_to_the_nearest_free_index() -> None:
    picks = np.array([[3, 3, 3, 0, 9], [0, 1, 2, 3, 4], [9, 9, 9, 9, 9]])
    out = distinct_picks(picks, 10)
    np.testing.assert_array_equal(out[0], [3, 2, 4, 0, 9])  # lower neighbour first, then the upper one
    np.testing.assert_array_equal(out[1], picks[1])
    np.testing.assert_array_equal(out[2], [9, 8, 7, 6, 5])
    with pytest.raises(ValueError, match="distinct"):
        distinct_picks(np.zeros((1, 4), dtype=int), 3)


def test_ppo_smoke_sequential_and_adaptive_with_checkpoints(burgers_task: PlacementTask, tmp_path: Path) -> None:
    """A few hundred PPO steps of each learner run, save checkpoint, metadata and learning curve, and reload
    to the same decisions; a checkpoint refuses a task with another sensor count."""
    from dks_gym_agents.adaptive import PPOAdaptive, train_adaptive
    from dks_gym_agents.sequential import SequentialLayout, train_sequential

    task = dataclasses.replace(burgers_task, config=AssimilationConfig(n_sensors=4))
    agent, meta = train_sequential(task, timesteps=64, n_envs=4, n_candidates=16, seed=0, out=tmp_path,
                                   ppo_kwargs={"batch_size": 16})
    assert meta["timesteps"] == 64 and meta["filter_runs"] > 0 and meta["learning_curve"]["timesteps"]
    assert (tmp_path / "sequential.zip").exists() and (tmp_path / "sequential_curve.png").exists()
    stored = json.loads((tmp_path / "sequential.json").read_text())["identity"]["dataset"]
    assert stored["path"] == Path(task.dataset.path).name  # the file's name, no machine path
    fitted = SequentialLayout(agent=agent, candidates=np.array(meta["candidates"])).fit(task)
    trained = fitted.layout
    np.testing.assert_array_equal(SequentialLayout(tmp_path / "sequential.zip").fit(task).layout, trained)
    # pickled (to a worker of dks_gym.parallel and back) the agent travels as its checkpoint, its env left behind
    np.testing.assert_array_equal(pickle.loads(pickle.dumps(fitted)).choose(task), trained)

    agent, meta = train_adaptive(task, timesteps=256, n_envs=2, n_candidates=16, seed=0, out=tmp_path,
                                 ppo_kwargs={"n_steps": 64, "batch_size": 64})
    assert meta["timesteps"] >= 256 and (tmp_path / "adaptive_curve.png").exists()
    belief = np.random.default_rng(0).standard_normal((3, 2 * task.model.r)).astype(np.float32)
    live = PPOAdaptive(agent=agent, candidates=np.array(meta["candidates"])).fit(task)
    loaded = PPOAdaptive(tmp_path / "adaptive.zip").fit(task)
    np.testing.assert_array_equal(loaded.decide(belief), live.decide(belief))
    np.testing.assert_array_equal(pickle.loads(pickle.dumps(live)).decide(belief), live.decide(belief))
    other = dataclasses.replace(task, config=AssimilationConfig(n_sensors=5))
    with pytest.raises(ValueError, match="n_sensors"):
        PPOAdaptive(tmp_path / "adaptive.zip").fit(other)


def test_evaluate_placement_writes_a_ranked_valid_results_file(burgers_task, tmp_path: Path, monkeypatch) -> None:
    """The CLI command ranks the policies by time-averaged MSE, stores a schema-valid JSON whose paper record
    equals a LatentFilter run, and draws the layout figure."""
    from click.testing import CliRunner

    from dks_gym_agents.cli import evaluate_placement_command
    from dks_gym_agents.policies import PlacementTask as Task
    from dks_gym.evaluation.results import load_results

    captured = {}

    def fake_load(cls, benchmark, model="koopman", **kwargs):
        captured.update(kwargs)
        return dataclasses.replace(burgers_task, config=AssimilationConfig().replace(**{
            k: kwargs[k] for k in ("kind", "n_sensors", "noise_level", "noise_seed")}))

    monkeypatch.setattr(Task, "load", classmethod(fake_load))
    result = CliRunner().invoke(evaluate_placement_command, [
        "burgers", "--policies", "paper,random,qr", "--random-seeds", "2", "--noise-seed", "7", "--noise-seeds", "2",
        "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert captured["noise_seed"] == 7 and captured["kind"] == "ekf"
    doc = load_results(tmp_path / "placement.json.gz")
    recs = {r["policy"]: r for r in doc["records"]}
    assert set(recs) == {"paper", "random-0", "random-1", "qr", "forward"}
    assert recs["qr"]["batch"] == 6 and recs["qr"]["noise_seeds"] == [7, 7, 7, 8, 8, 8]
    assert recs["qr"]["trajectories"] == [0, 1, 2, 0, 1, 2]
    table = (tmp_path / "placement.md").read_text()
    ranked = [line.split("|")[2].strip() for line in table.splitlines()[2:] if line.startswith("| ") and
              line.split("|")[1].strip().isdigit()]
    assert ranked == sorted(ranked, key=lambda p: recs[p]["time_mean_mse_mean"])
    assert ink(tmp_path / "placement_layouts.png") > 0.02  # drawn, not a blank page
    assert recs["qr"]["paired_vs_random"]["n_episodes"] == 6 and recs["random-0"]["paired_vs_random"]["n_random"] == 1
    assert "log(MSE / random mean)" in table

    env = LatentFilter(gym.make("DKS/Burgers-v0", data_path=str(burgers_task.dataset.path)), model=burgers_task.model)
    env.reset(options={"trajectory": 2, "noise_seed": 7})
    done = False
    while not done:
        _, _, terminated, truncated, info = env.step(None)
        done = terminated or truncated
    assert recs["paper"]["sensors"] == PaperLayout().fit(burgers_task).layout.tolist()
    assert recs["paper"]["per_trajectory_final_mse"][2] == pytest.approx(info["mse"], rel=2e-4)


@pytest.mark.filterwarnings("ignore:.*not within the observation space:UserWarning")  # NaN readings, by design
def test_budgets_and_faults_through_the_command(burgers_task, tmp_path: Path, monkeypatch) -> None:
    """--budgets runs one ranking per sensor count and writes the error-vs-budget table and figure; --faults puts
    the faults in every test episode (and in the results' config) while the policies are fitted without them;
    the paper record under faults equals a LatentFilter run of the same faulty env."""
    from click.testing import CliRunner

    from dks_gym_agents.cli import evaluate_placement_command
    from dks_gym_agents.policies import PlacementTask as Task
    from dks_gym.evaluation.results import load_results

    def fake_load(cls, benchmark, model="koopman", **kwargs):
        return dataclasses.replace(burgers_task, config=AssimilationConfig().replace(**{
            k: kwargs[k] for k in ("kind", "n_sensors", "noise_level", "noise_seed")}))

    monkeypatch.setattr(Task, "load", classmethod(fake_load))
    result = CliRunner().invoke(evaluate_placement_command, [
        "burgers", "--policies", "paper,random,d-optimal", "--random-seeds", "2", "--budgets", "2,4",
        "--faults", '{"dropout": 0.3, "failure_rate": 0.02}', "--greedy-candidates", "12",
        "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    table = (tmp_path / "budgets.md").read_text()
    assert "| d-optimal |" in table and "m = 2" in table and "m = 4" in table and "dropout 0.3" in table
    assert ink(tmp_path / "budgets.png") > 0.02  # drawn, not a blank page
    docs = {m: load_results(tmp_path / f"m{m}" / "placement.json.gz") for m in (2, 4)}
    for m, doc in docs.items():
        recs = {r["policy"]: r for r in doc["records"]}
        assert len(recs["d-optimal"]["sensors"]) == m
        assert doc["config"]["faults"]["dropout"] == 0.3
    paper = {r["policy"]: r for r in docs[4]["records"]}["paper"]
    env = LatentFilter(gym.make("DKS/Burgers-v0", data_path=str(burgers_task.dataset.path), n_sensors=4,
                                faults={"dropout": 0.3, "failure_rate": 0.02}), model=burgers_task.model)
    env.reset(options={"trajectory": 1, "noise_seed": 0})
    done = False
    while not done:
        _, _, terminated, truncated, info = env.step(None)
        done = terminated or truncated
    assert paper["per_trajectory_final_mse"][1] == pytest.approx(info["mse"], rel=2e-4)
    bad = CliRunner().invoke(evaluate_placement_command, ["burgers", "--faults", '{"dropuot": 1}', "--out",
                                                          str(tmp_path / "bad")])
    assert bad.exit_code != 0 and "unknown sensor faults" in bad.output
    bad = CliRunner().invoke(evaluate_placement_command, ["burgers", "--budgets", "4,x", "--out", str(tmp_path / "b")])
    assert bad.exit_code != 0 and "--budgets must be" in bad.output
    bad = CliRunner().invoke(evaluate_placement_command, ["burgers", "--resume", "--out", str(tmp_path / "r")])
    assert bad.exit_code != 0 and "give --budgets" in bad.output


@pytest.mark.parametrize("bench", CFD)
def test_constraints_keep_every_static_policy_inside_the_allowed_cells(bench: str, cfd_tasks) -> None:
    """'surface' allows the fluid cells touching a solid body, 'wall' those and the domain's wall cells; a keep-out
    mask forbids its cells; every static policy (the paper layout moved to the nearest allowed cells) chooses inside
    them."""
    from dks_gym_agents.policies import constraint_candidates, default_candidate_count

    task = cfd_tasks[bench]
    fluid = task.fluid_mask
    surface = constraint_candidates(task.dataset, "surface")
    for cell in surface:  # each one is fluid with a solid face-neighbour inside the grid
        index = np.unravel_index(cell, fluid.shape)
        neighbours = [tuple(np.add(index, step)) for axis in range(fluid.ndim) for step in
                      (np.eye(fluid.ndim, dtype=int)[axis], -np.eye(fluid.ndim, dtype=int)[axis])]
        assert fluid[index] and any(all(0 <= i < n for i, n in zip(nb, fluid.shape)) and not fluid[nb]
                                    for nb in neighbours)
    wall = constraint_candidates(task.dataset, "wall")  # the body surface and the domain's walls
    code = task.benchmark.cell_type_codes["wall"]
    typed_wall = set(np.flatnonzero(fluid.ravel() & (task.dataset.cell_type.ravel() == code)).tolist())
    added = set(wall.tolist()) - set(surface.tolist())
    assert set(surface.tolist()) <= set(wall.tolist()) and fluid.ravel()[wall].all()
    assert typed_wall <= set(wall.tolist()) and added and added <= typed_wall
    for cell in added:  # a wall cell that is not on the body lies on the grid's edge
        assert any(i in (0, n - 1) for i, n in zip(np.unravel_index(cell, fluid.shape), fluid.shape))
    keep_out = np.zeros(fluid.shape, dtype=bool)
    keep_out[tuple(slice(0, n // 2) for n in fluid.shape)] = True  # the lower corner block
    outside = constraint_candidates(task.dataset, keep_out)
    assert not keep_out.ravel()[outside].any() and fluid.ravel()[outside].all()
    for allowed in (surface, wall, outside):
        constrained = dataclasses.replace(task, candidates=allowed)
        spread = candidate_lattice(constrained)  # the default size; the surface is too thin for a lattice
        assert set(spread.tolist()) <= set(allowed.tolist()) and len(set(spread.tolist())) == len(spread)
        assert 2 * len(spread) >= min(default_candidate_count(task.n_sensors), len(allowed))
        lattice = candidate_lattice(constrained, 3 * task.n_sensors)
        for policy in (PaperLayout(), RandomLayout(0), QRLayout(), GreedyLayout("information", candidates=lattice,
                                                                                n_trajectories=1)):
            layout = check_layout(constrained, policy.fit(constrained).layout)
            assert set(layout.tolist()) <= set(allowed.tolist()), policy.name
    with pytest.raises(ValueError, match="unknown constraint"):
        constraint_candidates(task.dataset, "walls")
    with pytest.raises(ValueError, match="grid's shape"):
        constraint_candidates(task.dataset, np.zeros(3, dtype=bool))


def test_burgers_has_no_surface(burgers_task: PlacementTask) -> None:
    from dks_gym_agents.policies import constraint_candidates

    with pytest.raises(ValueError, match="no solid body"):
        constraint_candidates(burgers_task.dataset, "surface")
    with pytest.raises(ValueError, match="no solid body or wall"):
        constraint_candidates(burgers_task.dataset, "wall")


def test_a_policy_that_cannot_be_fitted_at_a_budget_is_skipped_not_fatal(burgers_task, tmp_path: Path) -> None:
    """evaluate_budgets leaves out a policy whose fit fails at one budget (QR with more sensors than POD modes)
    and says so in the table; a single ranking still stops on it."""
    from dks_gym_agents import StaticPolicy
    from dks_gym_agents.budgets import evaluate_budgets
    from dks_gym_agents.evaluate import evaluate_placement

    class TooGreedy(StaticPolicy):
        name = "too-greedy"

        def choose(self, task):
            raise ValueError("the training snapshots hold only 3 POD modes")

    docs = evaluate_budgets(burgers_task, [4], policies=["paper", TooGreedy()], out=tmp_path, log=lambda _: None)
    table = (tmp_path / "budgets.md").read_text()
    assert "| too-greedy | skipped |" in table and "only 3 POD modes" in table
    assert docs[4]["config"]["skipped_policies"] == {"too-greedy": "the training snapshots hold only 3 POD modes"}
    with pytest.raises(ValueError, match="only 3 POD modes"):
        evaluate_placement(burgers_task, ["paper", TooGreedy()], log=lambda _: None)


def test_a_placement_document_names_its_protocol(burgers_task) -> None:
    """The harness stamps the benchmark's protocol: the small data is the run's one deviation, and no record
    leaves it (the policy's layout is what a placement run compares, not a deviation)."""
    from dks_gym_agents.evaluate import evaluate_placement

    doc, _ = evaluate_placement(burgers_task, ["paper", "random"], log=lambda _: None)
    assert (doc["protocol"]["name"], doc["protocol"]["version"]) == ("dks-v1", 1)
    assert doc["protocol"]["deviations"] == {"data_preset": "small"}
    assert not any("protocol_deviations" in r for r in doc["records"])


def test_a_resumed_sweep_keeps_finished_budgets_and_refuses_other_settings(burgers_task, tmp_path: Path) -> None:
    """resume=True keeps a budget an earlier sweep finished (its file untouched), runs the others, tables every
    budget of the folder; a folder made with other settings is refused before anything runs."""
    from dks_gym.evaluation.results import load_results, save_results
    from dks_gym_agents.budgets import evaluate_budgets
    from dks_gym_agents.scenario import Scenario

    evaluate_budgets(burgers_task, [2], policies="paper", out=tmp_path, log=lambda _: None)
    first = (tmp_path / "m2" / "placement.json.gz").read_bytes()
    said: list[str] = []
    docs = evaluate_budgets(burgers_task, [4], policies="paper", out=tmp_path, resume=True, log=said.append)
    assert (tmp_path / "m2" / "placement.json.gz").read_bytes() == first
    assert sorted(docs) == [2, 4] and "m = 2" in (tmp_path / "budgets.md").read_text()
    assert not any("budget m = 2" == line for line in said) and "budget m = 4" in said
    docs = evaluate_budgets(burgers_task, [2, 4], policies="paper", out=tmp_path, resume=True,
                            log=said.append)
    assert [line for line in said if line.startswith("budget m")][-2:] == [
        f"budget m = {m}: kept {tmp_path / f'm{m}' / 'placement.json.gz'}" for m in (2, 4)]
    with pytest.raises(ValueError, match="faults differ"):
        evaluate_budgets(burgers_task, [8], Scenario(faults="default"), "paper", out=tmp_path, resume=True)
    assert not (tmp_path / "m8").exists()
    # with faults too: the budget run here and the one read back compare equal (tuples in one, lists in the other)
    evaluate_budgets(burgers_task, [2], Scenario(faults="default"), "paper", out=tmp_path / "f",
                     log=lambda _: None)
    docs = evaluate_budgets(burgers_task, [2, 4], Scenario(faults="default"), "paper", out=tmp_path / "f",
                            resume=True, log=lambda _: None)
    assert sorted(docs) == [2, 4] and "m = 4" in (tmp_path / "f" / "budgets.md").read_text()
    stale = load_results(tmp_path / "m4" / "placement.json.gz")
    stale["config"]["noise_level"] = 0.5
    save_results(stale, tmp_path / "m4" / "placement.json.gz")
    with pytest.raises(ValueError, match="noise_level differ"):
        evaluate_budgets(burgers_task, [8], policies="paper", out=tmp_path, resume=True)


def test_bad_input_is_refused(burgers_task: PlacementTask, cfd_tasks) -> None:
    from dks_gym_agents.registry import make_policies

    cyl = cfd_tasks["cylinder"]
    body = np.flatnonzero(~cyl.fluid_mask.ravel())[:3]
    with pytest.raises(ValueError, match="solid"):
        PlacementTask(cyl.dataset, cyl.model, cyl.config, candidates=np.concatenate([body, np.arange(10)]))
    with pytest.raises(ValueError, match="solid"):
        check_layout(cyl, np.concatenate([body[:2], [0, 1]]))
    with pytest.raises(ValueError, match="repeats"):
        check_layout(burgers_task, np.zeros(16, dtype=int))
    with pytest.raises(ValueError, match="n_modes"):
        QRLayout(n_modes=4).fit(burgers_task)
    with pytest.raises(ValueError, match="unknown policies"):
        make_policies("paper,oracle")
    with pytest.raises(ValueError, match="model is for"):
        PlacementTask(burgers_task.dataset, cyl.model)
    with pytest.raises(RuntimeError, match="not fitted"):
        PaperLayout().episode_layouts(np.zeros(2))


@pytest.mark.parametrize("kind", ["sequential", "adaptive"])
def test_trainer_command_lines_write_checkpoint_and_curve(kind: str, burgers_task, tmp_path: Path, monkeypatch,
                                                          capsys) -> None:
    """`python -m dks_gym_agents.sequential|adaptive BENCHMARK --out DIR` trains and writes the checkpoint, its metadata
    and the learning-curve figure, with the options passed through to the task."""
    import importlib

    from dks_gym_agents.policies import PlacementTask as Task

    captured = {}

    def fake_load(cls, benchmark, model="koopman", **kwargs):
        captured.update(kwargs, benchmark=benchmark, model=model)
        return dataclasses.replace(burgers_task, config=AssimilationConfig(n_sensors=kwargs["n_sensors"]))

    monkeypatch.setattr(Task, "load", classmethod(fake_load))
    module = importlib.import_module(f"dks_gym_agents.{kind}")
    steps = ["--timesteps", "64", "--n-envs", "16"] if kind == "sequential" else ["--timesteps", "256", "--n-envs", "2"]
    with pytest.raises(SystemExit) as exit_info:
        module.main(["burgers", "--n-sensors", "4", "--n-candidates", "16", "--seed", "3", *steps,
                     "--out", str(tmp_path)])
    assert exit_info.value.code == 0
    assert captured["n_sensors"] == 4 and captured["seed"] == 3 and captured["model_preset"] == "lite"
    assert captured["train_if_missing"] is False
    for suffix in (".zip", ".json", "_curve.png"):
        assert (tmp_path / f"{kind}{suffix}").exists()
    assert f"wrote {tmp_path}" in capsys.readouterr().out


def test_custom_policy_objects_are_ranked_beside_named_ones(burgers_task, tmp_path: Path) -> None:
    """evaluate_placement takes the user's own StaticPolicy next to the built-in names and runs its layout;
    duplicate names and unknown names are refused."""
    from dks_gym_agents import StaticPolicy
    from dks_gym_agents.evaluate import evaluate_placement
    from dks_gym_agents.registry import make_policies

    class Clustered(StaticPolicy):
        name = "clustered"

        def choose(self, task):
            return task.fluid_cells[:task.n_sensors]

    task = dataclasses.replace(burgers_task, config=AssimilationConfig(n_sensors=4))
    _, results = evaluate_placement(task, ["paper", Clustered()], log=lambda _: None)
    by_name = {r.name: r for r in results}
    np.testing.assert_array_equal(by_name["clustered"].layouts[0], task.fluid_cells[:4])
    assert set(by_name) == {"paper", "clustered"}
    with pytest.raises(ValueError, match="distinct name"):
        make_policies([Clustered(), Clustered()])
    with pytest.raises(ValueError, match="unknown policies"):
        make_policies("paper,best")


def test_evaluate_placement_on_a_dask_cluster_writes_what_the_serial_run_writes(burgers_task, dask_client,
                                                                               tmp_path: Path) -> None:
    """The policies fitted and run, and a SHRED baseline trained, on a two-worker LocalCluster: the same
    document but for the measured times, the same table once those are masked, the same figure."""
    import re

    from dks_gym.evaluation.results import load_results
    from dks_gym.models.shred import ShredConfig
    from dks_gym_agents.evaluate import evaluate_placement
    from dks_gym_agents.scenario import Scenario
    from tests.conftest import without_times

    task = dataclasses.replace(burgers_task, config=AssimilationConfig(n_sensors=4))
    scenario = Scenario(shred=["qr"], shred_config=ShredConfig(epochs=2, noise_seeds=1, rank=4))
    for name, executor in (("serial", None), ("dask", dask_client.get_executor(pure=False))):
        _, results = evaluate_placement(task, "paper,qr", scenario, out=tmp_path / name, log=lambda _: None,
                                        executor=executor)
    assert [pr.name for pr in results] == ["paper", "qr"] and results[1].policy.layout is not None
    serial, spread = (load_results(tmp_path / name / "placement.json.gz") for name in ("serial", "dask"))
    assert [r["policy"] for r in serial["records"]] == ["paper", "qr", "forward", "shred-qr"]
    assert without_times(spread) == without_times(serial)
    timeless = [re.sub(r"[0-9.e+-]+ m?s \|", "t |", (tmp_path / name / "placement.md").read_text())
                for name in ("serial", "dask")]
    assert timeless[0] == timeless[1] and "| t | t |" in timeless[0]
    assert (tmp_path / "dask" / "placement_layouts.png").read_bytes() == \
        (tmp_path / "serial" / "placement_layouts.png").read_bytes()


def test_paired_vs_random_from_a_results_document(tmp_path: Path) -> None:
    """The paired comparison with the random layouts: per-episode log ratio to the random mean (the other
    seeds' for a random row), its standard error, the geometric variant and the wins, from JSON alone."""
    from dks_gym_agents.paired import paired_vs_random
    from dks_gym_agents.tables import ranked_table

    def rec(policy, values, trajectories=(0, 1, 0, 1)):
        return {"experiment": f"placement/{policy}", "policy": policy, "per_trajectory_time_mean_mse": list(values),
                "trajectories": list(trajectories), "time_mean_mse_mean": float(np.mean(values)),
                "time_mean_mse_std": float(np.std(values, ddof=1)), "final_mse_mean": 1.0, "final_mse_std": 0.0}

    r0, r1, qr = [1.0, 2.0, 1.0, 4.0], [3.0, 2.0, 1.0, 2.0], [1.0, 1.0, 2.0, 1.0]
    doc = {"benchmark": "burgers", "records": [rec("random-0", r0), rec("random-1", r1), rec("qr", qr)],
           "config": {"model": "koopman", "model_preset": "lite", "r": 4, "filter": "ekf", "n_sensors": 4,
                      "noise_level": 0.2, "n_episodes": 4, "n_test": 2, "noise_seeds": [0, 1], "n_frames": 5}}
    paired = paired_vs_random(doc)
    q = np.log(np.array(qr) / ((np.array(r0) + np.array(r1)) / 2))
    assert paired["qr"]["log_ratio_mean"] == pytest.approx(q.mean())
    assert paired["qr"]["log_ratio_se"] == pytest.approx(q.std(ddof=1) / 2)
    assert paired["qr"]["wins"] == int(np.sum(q < 0)) == 3 and paired["qr"]["n_random"] == 2
    per_traj = [q[[0, 2]].mean(), q[[1, 3]].mean()]
    assert paired["qr"]["log_ratio_se_trajectories"] == pytest.approx(np.std(per_traj, ddof=1) / np.sqrt(2))
    g = np.log(qr) - (np.log(r0) + np.log(r1)) / 2
    assert paired["qr"]["log_ratio_geometric_mean"] == pytest.approx(g.mean())
    assert paired["random-0"]["log_ratio_mean"] == pytest.approx(np.log(np.array(r0) / r1).mean())  # leave-one-out
    assert paired["random-0"]["n_random"] == 1
    assert f"{q.mean():+.3f}" in ranked_table(doc) and "3/4" in ranked_table(doc)
    doc["records"] = doc["records"][1:]
    assert paired_vs_random(doc) == {}  # one random layout is no reference


@pytest.fixture(scope="module")
def cfd_tasks_m16(tmp_path_factory: pytest.TempPathFactory) -> dict[str, PlacementTask]:
    """The synthetic CFD files with 2 x 10 training snapshots (19 POD modes, enough for QR with m = 16)."""
    folder = tmp_path_factory.mktemp("agents_cfd_m16")
    tasks = {}
    for bench in CFD:
        ds = Dataset(_noisy_synthetic(bench, folder / f"{bench}.h5", n_t=10))
        tasks[bench] = PlacementTask(ds, _untrained(bench, ds), AssimilationConfig(n_sensors=16))
    return tasks


@pytest.mark.parametrize("bench", CFD)
def test_m16_layouts_on_cfd_geometries_and_their_figure(bench: str, cfd_tasks_m16, tmp_path: Path) -> None:
    """The paper's m = 16 on the cylinder, dambreak and sphere grids: every static baseline gives 16 distinct
    fluid cells (never the cylinder, obstacle or sphere), the harness ranks them, and the 2D/3D layout
    figure (3D: mid-plane) is drawn."""
    from dks_gym_agents.evaluate import evaluate_placement

    task = cfd_tasks_m16[bench]
    fluid = task.fluid_mask.ravel()
    assert (~fluid).any()  # each geometry has cells a sensor must never take
    lattice = candidate_lattice(task, 32)
    # The greedy's 3D path is checked at m = 2 (test_every_policy_gives_valid_layouts[sphere]); at m = 16 on the
    # 64^3 grid it alone took 40 s.
    greedy = [] if bench == "sphere" else [GreedyLayout("trace", candidates=lattice, n_trajectories=1)]
    policies = [PaperLayout(), RandomLayout(0), RandomLayout(1), QRLayout(), *greedy]
    for policy in policies:
        layout = policy.fit(task).layout
        check_layout(task, layout)
        assert layout.shape == (16,) and len(set(layout.tolist())) == 16 and fluid[layout].all(), policy.name
    doc, results = evaluate_placement(task, policies, out=tmp_path, log=lambda _: None)
    assert {r.name for r in results} == {"paper", "random-0", "random-1", "qr", *(p.name for p in greedy)}
    assert all(len(r["sensors"]) == 16 for r in doc["records"] if r["policy"] != "forward")
    qr = next(r for r in doc["records"] if r["policy"] == "qr")
    assert qr["paired_vs_random"]["n_random"] == 2
    assert ink(tmp_path / "placement_layouts.png") > 0.02  # drawn, not a blank page
    assert "log(MSE / random mean)" in (tmp_path / "placement.md").read_text()


def test_shred_ranks_beside_the_filters(burgers_task: PlacementTask, tmp_path: Path) -> None:
    """evaluate_placement(shred=[...]) trains SHRED on a static policy's layout and scores it on the same
    episodes: a shred-<policy> record that the results schema accepts, in the table and the budget table; a
    policy not in the run is skipped with its reason."""
    from dks_gym.evaluation.results import load_results
    from dks_gym.models.shred import ShredConfig
    from functools import partial

    from dks_gym_agents.budgets import evaluate_budgets
    from dks_gym_agents.registry import POLICIES, random_layouts
    from dks_gym_agents.scenario import Scenario
    from dks_gym_agents.summary import fault_pairs, write_summary

    quick = dict(registry={**POLICIES, "random": partial(random_layouts, 2)}, log=lambda _: None)
    shred = dict(shred=["paper", "qr"], shred_config=ShredConfig(epochs=2, noise_seeds=1, rank=4))
    docs = evaluate_budgets(burgers_task, [4], Scenario(**shred), "paper,random", out=tmp_path / "burgers" / "none",
                            **quick)
    faulty = evaluate_budgets(burgers_task, [4], Scenario(faults="default", **shred), "paper,random",
                              out=tmp_path / "burgers" / "default", **quick)
    page = write_summary(tmp_path, tmp_path / "benchmark.md").read_text()
    assert "![burgers, none: error vs budget](./burgers/none/budgets.png)" in page  # the figure beside its table
    cost = faulty[4]["records"][0]["time_mean_mse_mean"] / docs[4]["records"][0]["time_mean_mse_mean"]
    assert f"| paper | {cost:.2f} |" in page  # the faults' cost, default over none
    assert fault_pairs(["none", "default", "wall-none", "wall-default", "surface-default", "greedy-none"]) == [
        ("default", "none"), ("wall-default", "wall-none")]  # a constrained pair too; no partner, no table
    tmp_path = tmp_path / "burgers" / "none"
    doc = load_results(tmp_path / "m4" / "placement.json.gz")
    rec = next(r for r in doc["records"] if r["policy"] == "shred-paper")
    paper = next(r for r in doc["records"] if r["policy"] == "paper")
    assert rec["model"] == "shred" and rec["filter"] == "none" and rec["sensors"] == paper["sensors"]
    assert rec["trajectories"] == paper["trajectories"] and rec["noise_seeds"] == paper["noise_seeds"]
    assert len(rec["per_trajectory_time_mean_mse"]) == paper["batch"] and "paired_vs_random" in rec
    assert 0 <= rec["pod_floor_time_mean_mse"] <= rec["time_mean_mse_mean"]
    assert "| shred-paper |" in (tmp_path / "m4" / "placement.md").read_text().replace(" (adaptive)", "")
    assert "| shred-paper |" in (tmp_path / "budgets.md").read_text()
    assert docs[4]["config"]["skipped_policies"] == {"shred-qr": "'qr' is not in this run"}


def test_your_own_policy_ranks_at_every_budget(burgers_task: PlacementTask, tmp_path: Path) -> None:
    """An unfitted policy object is fitted afresh at each budget (a copy); a fitted one is refused."""
    from dks_gym_agents import StaticPolicy
    from dks_gym_agents.budgets import evaluate_budgets

    class Leftmost(StaticPolicy):
        name = "leftmost"

        def choose(self, task):
            return task.allowed_cells[: task.n_sensors]

    mine = Leftmost()
    docs = evaluate_budgets(burgers_task, [2, 3], policies=["paper", mine], out=tmp_path, log=lambda _: None)
    for m in (2, 3):
        rec = next(r for r in docs[m]["records"] if r["policy"] == "leftmost")
        assert rec["sensors"] == burgers_task.allowed_cells[:m].tolist()
    assert mine.task is None  # the caller's object is left as it was
    mine.fit(burgers_task)
    with pytest.raises(ValueError, match="fitted policy object"):
        evaluate_budgets(burgers_task, [2, 3], policies=[mine], out=tmp_path, log=lambda _: None)


def test_the_linearization_is_reused_only_for_the_same_inputs(burgers_task: PlacementTask) -> None:
    from dks_gym_agents.scoring import LinearizedTrajectories, linearized

    ds, model, config = burgers_task.dataset, burgers_task.model, burgers_task.config
    cells = np.arange(0, 64, 8)
    first = linearized(model, ds, np.array([0, 1]), cells, config)
    assert linearized(model, ds, np.array([0, 1]), cells, config.replace(n_sensors=3)) is first
    noisier = linearized(model, ds, np.array([0, 1]), cells, config.replace(noise_level=0.3))
    assert noisier is not first and not torch.equal(noisier.sigma, first.sigma)
    assert linearized(model, ds, np.array([0]), cells, config) is not first
    fresh = LinearizedTrajectories(model, ds, np.array([0, 1]), cells, config)
    again = linearized(model, ds, np.array([0, 1]), cells, config)
    assert torch.equal(again.J, fresh.J) and torch.equal(again.F, fresh.F)
