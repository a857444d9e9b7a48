"""SensingEnv and the four registered ids: Gymnasium compliance, seeding, the noise model, select mode, rendering."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import h5py
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import dks_gym  # noqa: F401  (registers the ids)
from dks_gym.benchmarks import BENCHMARKS, get_benchmark
from dks_gym.dataset import DataError, DatasetMissing, SchemaError

from .damage import damage_chunk, put_nonfinite


def _episode(env, seed=None, options=None, actions=None):
    obs, info = env.reset(seed=seed, options=options)
    out, infos = [obs], [info]
    for k in range(env.unwrapped.dataset.n_frames - 1):
        action = None if actions is None else actions[k]
        obs, reward, terminated, truncated, info = env.step(action)
        assert reward == 0.0 and not terminated
        out.append(obs)
        infos.append(info)
    assert truncated
    return np.stack(out), infos


def test_burgers_env_passes_check_env(burgers_small: Path) -> None:
    env = gym.make("DKS/Burgers-v0", preset="small")
    check_env(env.unwrapped, skip_render_check=False)
    check_env(gym.make("DKS/Burgers-v0", preset="small", sensor_mode="select").unwrapped)


def test_fresh_data_home_generate_then_default_make_passes_check_env(tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """The issue's path on a fresh machine: `dks-gym data generate burgers`, then the default gym.make."""
    from click.testing import CliRunner

    from dks_gym.cli import main

    monkeypatch.setenv("DKS_GYM_HOME", str(tmp_path))
    result = CliRunner().invoke(main, ["data", "generate", "burgers"])
    assert result.exit_code == 0, result.output
    env = gym.make("DKS/Burgers-v0")
    assert env.unwrapped.dataset.path == tmp_path / "data" / "burgers-paper.h5"
    assert env.unwrapped.dataset.n_trajectories("train") == 50 and env.unwrapped.dataset.n_trajectories("test") == 10
    check_env(env.unwrapped)


def test_episode_walks_every_frame_and_truncates(burgers_small: Path) -> None:
    env = gym.make("DKS/Burgers-v0", preset="small")
    obs, infos = _episode(env, seed=0)
    ds = env.unwrapped.dataset
    assert obs.shape == (ds.n_frames, 16) and obs.dtype == np.float32
    assert [i["time_index"] for i in infos] == list(range(ds.n_frames))
    np.testing.assert_allclose([i["time"] for i in infos], ds.time)
    assert infos[0]["param_name"] == "nu" and infos[0]["split"] == "test"
    np.testing.assert_array_equal(infos[0]["sensors"], get_benchmark("burgers").paper_layout(16))
    with pytest.raises(RuntimeError, match="reset"):
        env.step(None)


def test_same_seed_same_observations(burgers_small: Path) -> None:
    env = gym.make("DKS/Burgers-v0", preset="small")
    a, ia = _episode(env, seed=7)
    b, ib = _episode(env, seed=7)
    c, ic = _episode(env, seed=8, options={"trajectory": ia[0]["trajectory"]})
    np.testing.assert_array_equal(a, b)
    assert ia[0]["trajectory"] == ib[0]["trajectory"]
    assert not np.allclose(a, c)  # new seed, new noise on the same trajectory
    # An unseeded reset after a seeded one continues deterministically.
    env.reset(seed=3)
    x = env.reset()[0]
    env.reset(seed=3)
    np.testing.assert_array_equal(x, env.reset()[0])


def test_true_state_and_noise_statistics(burgers_small: Path) -> None:
    env = gym.make("DKS/Burgers-v0", preset="small", n_sensors=64)
    base = env.unwrapped
    with h5py.File(burgers_small) as f:
        truth = f["test/fields"][()]
    residuals, sigmas = [], []
    for traj in range(truth.shape[0]):
        obs, infos = _episode(env, seed=11 + traj, options={"trajectory": traj})
        clean = truth[traj, :, 0][:, infos[0]["sensors"]]
        # Definition (SPEC 2): sigma = 0.2 * max |u| over every cell and frame of the trajectory.
        sigma = 0.2 * np.abs(truth[traj, :, 0]).max()
        assert infos[0]["sigma"] == pytest.approx(sigma, rel=1e-6)
        residuals.append((obs - clean) / sigma)
        sigmas.append(sigma)
    np.testing.assert_allclose(base.true_state, truth[-1, -1], rtol=0, atol=0)
    z = np.concatenate([r.ravel() for r in residuals])
    n = z.size  # 3 trajectories x 100 frames x 64 sensors
    assert abs(z.mean()) < 4 / np.sqrt(n)
    assert abs(z.std() - 1.0) < 4 * np.sqrt(0.5 / n)


def test_noise_does_not_depend_on_the_layout(burgers_small: Path) -> None:
    """A cell reads the same noise whatever the rest of the layout is, so layouts compare fairly."""
    env_a = gym.make("DKS/Burgers-v0", preset="small", sensors=[5, 100, 700])
    env_b = gym.make("DKS/Burgers-v0", preset="small", sensors=[700, 3, 4, 5])
    a, _ = _episode(env_a, seed=1, options={"trajectory": 0})
    b, _ = _episode(env_b, seed=1, options={"trajectory": 0})
    np.testing.assert_array_equal(a[:, [0, 2]], b[:, [3, 0]])


def test_noise_level_zero_reads_the_truth(burgers_small: Path) -> None:
    env = gym.make("DKS/Burgers-v0", preset="small", noise_level=0.0)
    obs, info = env.reset(seed=0)
    np.testing.assert_array_equal(obs, env.unwrapped.true_state[0, info["sensors"]])


def test_select_mode_reads_the_chosen_cells(burgers_small: Path) -> None:
    candidates = np.arange(0, 1024, 8)
    env = gym.make("DKS/Burgers-v0", preset="small", sensor_mode="select", candidates=candidates,
                   n_sensors=4, noise_level=0.0)
    assert env.action_space == gym.spaces.MultiDiscrete([128] * 4)
    env.reset(seed=0)
    action = np.array([0, 5, 5, 127])
    obs, _, _, _, info = env.step(action)
    np.testing.assert_array_equal(info["sensors"], candidates[action])
    np.testing.assert_array_equal(obs, env.unwrapped.true_state[0, candidates[action]])
    for bad in (np.array([0, 1, 2]), np.array([0, 1, 2, 128]), np.array([0, 1, 2, -1]), np.array([0.0, 1, 2, 3])):
        with pytest.raises(ValueError, match="sensor_mode='select'|must lie in"):
            env.step(bad)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"split": "validation"}, "unknown split"),
        ({"noise_level": -0.1}, "noise_level"),
        ({"sensor_mode": "adaptive"}, "sensor_mode"),
        ({"n_sensors": 2000}, "only 1024"),
        ({"sensor_mode": "select", "candidates": [1, 2, 3], "n_sensors": 4}, "only 3 candidate"),
        ({"sensors": [0, 1024]}, r"\[0, 1024\)"),
        ({"sensors": [[1, 2]]}, "flat grid indices"),
        ({"candidates": [1, 1, 2]}, "repeated"),
        ({"n_sensors": 0}, "positive integer"),
        ({"preset": "huge"}, "unknown preset"),
    ],
)
def test_bad_construction_arguments(burgers_small: Path, kwargs: dict, match: str) -> None:
    kwargs.setdefault("preset", "small")
    with pytest.raises(ValueError, match=match):
        gym.make("DKS/Burgers-v0", **kwargs)


def test_bad_reset_and_step_arguments(burgers_small: Path) -> None:
    # Gymnasium's passive checker cannot continue after a step that raised, so it is off here.
    env = gym.make("DKS/Burgers-v0", preset="small", disable_env_checker=True)
    with pytest.raises(ValueError, match="trajectory"):
        env.reset(options={"trajectory": 99})
    with pytest.raises(ValueError, match="unknown reset options"):
        env.reset(options={"trajectroy": 0})
    with pytest.raises(ValueError, match="16"):
        env.reset(options={"sensors": [1, 2, 3]})
    env.reset(seed=0)
    with pytest.raises(ValueError, match="fixed"):
        env.step(np.array([1, 2]))
    for bad in (0.7, "a", 1, True):  # a float, a string, a wrong index, a bool: none is the no-op action 0
        with pytest.raises(ValueError, match="fixed"):
            env.step(bad)
    obs, *_ = env.step(0)
    assert obs.shape == (16,)
    obs, *_ = env.step(np.int64(0))
    assert obs.shape == (16,)


def test_sensors_by_reset_option_or_grid_coordinates_and_info(burgers_small: Path) -> None:
    """A layout given at reset or as (m, ndim) coordinates reads those cells; info carries the trajectory's mu."""
    env = dks_gym.SensingEnv("burgers", preset="small", n_sensors=3, noise_level=np.float32(0.0))
    cells = np.array([5, 100, 900])
    obs, info = env.reset(seed=1, options={"sensors": cells, "trajectory": 2})
    assert info["sensors"].tolist() == cells.tolist() and obs.shape == (3,)
    np.testing.assert_array_equal(obs, env.unwrapped.true_state[0, cells])  # noise_level 0: exact readings
    assert info["mu"] == float(env.dataset.params("test")[2]) and info["trajectory"] == 2
    env.dataset.params("test")[2] = -1.0  # the dataset hands out copies: a caller cannot change the env's mu
    assert env.step(0)[4]["mu"] == info["mu"] == float(env.dataset.params("test")[2])
    assert env.reset(options={"trajectory": 0})[1]["mu"] == float(env.dataset.params("test")[0])
    by_coords = dks_gym.SensingEnv("burgers", preset="small", sensors=cells[:, None])
    assert by_coords.reset(seed=1)[1]["sensors"].tolist() == cells.tolist()


def test_unsupported_render_mode(burgers_small: Path) -> None:
    with pytest.raises(ValueError, match="render_mode"):
        dks_gym.SensingEnv("burgers", preset="small", render_mode="ansi")


def test_unknown_benchmark() -> None:
    with pytest.raises(ValueError, match="unknown benchmark"):
        dks_gym.SensingEnv("pendulum")


def test_missing_data_says_how_to_get_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("DKS_GYM_HOME", str(tmp_path))
    for name, bench in BENCHMARKS.items():
        assert bench.generator_available
        with pytest.raises(DatasetMissing, match=f"dks-gym data generate {name}"):
            gym.make(bench.env_id)


def test_wrong_benchmark_file_is_refused(burgers_small: Path) -> None:
    with pytest.raises(SchemaError, match="holds the burgers benchmark"):
        gym.make("DKS/Cylinder-v0", data_path=str(burgers_small))


@pytest.mark.parametrize("name", ["cylinder", "dambreak", "sphere"])
def test_cfd_shaped_envs_with_a_schema_file(make_synthetic, name: str) -> None:
    """Every id works on any file in the schema; solids are never sensors, renders have the right shape."""
    bench = get_benchmark(name)
    path = make_synthetic(name, n_t=3)
    env = gym.make(bench.env_id, data_path=str(path), render_mode="rgb_array")
    check_env(env.unwrapped, skip_render_check=True)
    obs, info = env.reset(seed=0)
    assert obs.shape == (16,)
    assert env.unwrapped.true_state.shape == (len(bench.channels), *bench.grid)
    frame = env.render()
    assert frame.ndim == 3 and frame.shape[2] == 3 and frame.dtype == np.uint8 and frame.shape[0] > 100
    solid = ~bench.fluid_mask().ravel()
    assert not solid[info["sensors"]].any()
    if solid.any():
        with pytest.raises(ValueError, match="solid body"):
            gym.make(bench.env_id, data_path=str(path), sensors=np.flatnonzero(solid)[:1])
    sel = gym.make(bench.env_id, data_path=str(path), sensor_mode="select")
    assert sel.action_space.nvec[0] == int((~solid).sum())


def test_burgers_render(burgers_small: Path) -> None:
    env = gym.make("DKS/Burgers-v0", preset="small", render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame.ndim == 3 and frame.shape[2] == 3 and frame.dtype == np.uint8
    assert frame.std() > 0  # something was drawn


def test_vector_env(burgers_small: Path) -> None:
    envs = gym.make_vec("DKS/Burgers-v0", num_envs=3, vectorization_mode="sync", preset="small")
    obs, info = envs.reset(seed=[0, 1, 2])
    assert obs.shape == (3, 16)
    obs, *_ = envs.step(np.zeros(3, dtype=np.int64))
    assert obs.shape == (3, 16)


@pytest.fixture(params=["whole", "by-frame"])
def read_mode(request, monkeypatch: pytest.MonkeyPatch) -> str:
    """Small trajectories are read whole, large ones (the sphere) frame by frame: both paths check the data."""
    if request.param == "by-frame":
        monkeypatch.setattr("dks_gym.envs.sensing._WHOLE_TRAJECTORY_BYTES", 0)
    return request.param


@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_nonfinite_data_is_refused_at_reset_naming_file_split_trajectory_and_channel(
    make_synthetic, read_mode: str, value: float
) -> None:
    path = make_synthetic("burgers", n_test=3)
    put_nonfinite(path, "test", 1, frame=2, channel=0, value=value)
    env = gym.make("DKS/Burgers-v0", data_path=str(path))
    obs, info = env.reset(seed=0, options={"trajectory": 0})  # the other trajectories are fine
    assert np.all(np.isfinite(obs)) and np.isfinite(info["sigma"])
    with pytest.raises(DataError) as err:
        env.reset(seed=0, options={"trajectory": 1})
    message = str(err.value)
    for part in (str(path), "split 'test'", "trajectory 1", "channel 'u'", "NaN or inf", "frame 2", "writer"):
        assert part in message, message
    assert isinstance(err.value, SchemaError)
    with pytest.raises(RuntimeError, match="call reset"):  # no half-opened episode to step on
        env.step(None)
    env.reset(seed=0, options={"trajectory": 2})
    env.step(None)


def test_nonfinite_value_in_an_unobserved_channel_is_refused_too(make_synthetic) -> None:
    """The true state feeds the filters' rewards: a NaN in u poisons them though only p is read by sensors."""
    path = make_synthetic("cylinder", n_test=1)
    put_nonfinite(path, "test", 0, frame=1, channel=0)
    env = gym.make("DKS/Cylinder-v0", data_path=str(path))
    with pytest.raises(DataError, match="trajectory 0, channel 'u'"):
        env.reset(seed=0)


def test_damaged_data_block_is_refused_at_reset_naming_the_file(make_synthetic, read_mode: str) -> None:
    path = make_synthetic("burgers", n_test=2)
    damage_chunk(path, "test", 1)
    env = gym.make("DKS/Burgers-v0", data_path=str(path))  # the header is intact: the file opens
    env.reset(seed=0, options={"trajectory": 0})
    with pytest.raises(DataError) as err:
        env.reset(seed=0, options={"trajectory": 1})
    message = str(err.value)
    for part in (str(path), "is damaged", "trajectory 1", "split 'test'", "delete it"):
        assert part in message, message
    assert isinstance(err.value.__cause__, OSError)


# Sensor faults ----------------------------------------------------------------------------------------
def _faulty_episode(faults, seed=3, n_sensors=16):
    env = dks_gym.SensingEnv("burgers", preset="small", n_sensors=n_sensors, faults=faults)
    obs, infos = _episode(env, seed=seed, options={"trajectory": 1})
    return obs, np.stack([i["mask"] for i in infos]), env


def test_no_faults_gives_the_plain_readings_and_a_full_mask(burgers_small: Path) -> None:
    plain, mask, _ = _faulty_episode(None)
    off, _, _ = _faulty_episode({"dropout": 0.0})
    np.testing.assert_array_equal(plain, off)
    assert mask.all()


def test_faults_are_reproducible_from_the_seed_and_leave_the_truth_alone(burgers_small: Path) -> None:
    faults = dks_gym.envs.SensorFaults(dropout=0.2, failure_rate=0.02, drift=0.01, quantization=0.05)
    a, mask_a, env = _faulty_episode(faults)
    b, mask_b, _ = _faulty_episode(faults)
    np.testing.assert_array_equal(a, b)  # NaNs in the same places
    np.testing.assert_array_equal(mask_a, mask_b)
    np.testing.assert_array_equal(np.isnan(a), ~mask_a)  # the mask says which readings are missing
    c, mask_c, _ = _faulty_episode(faults, seed=4)
    assert not np.array_equal(mask_a, mask_c)
    np.testing.assert_array_equal(env.true_state, env.dataset.trajectory("test", 1)[-1])


def test_each_fault_model(burgers_small: Path) -> None:
    clean, _, _ = _faulty_episode(None)
    n_t = len(clean)
    # Dropout: each reading lost independently with probability p.
    _, mask, _ = _faulty_episode({"dropout": 0.3}, n_sensors=64)
    assert abs((~mask).mean() - 0.3) < 4 * np.sqrt(0.3 * 0.7 / mask.size)
    # Failure: a failed slot stays failed; at rate 1 every slot fails at the first step.
    _, mask, _ = _faulty_episode({"failure_rate": 0.01}, n_sensors=64)  # 0.99^99: about 37 % survive
    assert np.all(np.diff(mask.astype(int), axis=0) <= 0) and 0 < (~mask[-1]).sum() < 64
    _, mask, _ = _faulty_episode({"failure_rate": 1.0})
    assert mask[0].all() and not mask[1:].any()
    # Bias drift: a random walk from 0 whose steps have the given standard deviation.
    drifted, _, _ = _faulty_episode({"drift": 0.02}, n_sensors=64)
    clean64, _, _ = _faulty_episode(None, n_sensors=64)
    bias = drifted.astype(np.float64) - clean64
    np.testing.assert_allclose(bias[0], 0.0, atol=1e-6)
    assert abs(np.diff(bias, axis=0).std() - 0.02) < 0.002
    # Saturation: readings clipped to the range.
    low, high = np.quantile(clean, [0.2, 0.8])
    saturated, _, _ = _faulty_episode({"saturation": (low, high)})
    np.testing.assert_allclose(saturated, np.clip(clean, low, high), rtol=1e-6)
    # Quantization: multiples of the resolution, within half of it.
    quantized, _, _ = _faulty_episode({"quantization": 0.1})
    np.testing.assert_allclose(quantized / 0.1, np.round(quantized / 0.1), atol=1e-4)
    assert np.abs(quantized - clean).max() <= 0.05 + 1e-6
    # Latency: the reading of d frames earlier; nothing before the first d frames.
    late, mask, _ = _faulty_episode({"latency": 2})
    assert not mask[:2].any() and mask[2:].all()
    np.testing.assert_array_equal(late[2:], clean[: n_t - 2])
    # Slow sensors: the named slots read every k-th frame only.
    slow, mask, _ = _faulty_episode({"slow_sensors": (0, 5), "slow_every": 3})
    frames = np.arange(n_t)
    np.testing.assert_array_equal(mask[:, 0], frames % 3 == 0)
    np.testing.assert_array_equal(mask[:, 5], frames % 3 == 0)
    assert mask[:, [1, 2, 3, 4, 6]].all()
    np.testing.assert_array_equal(slow[mask], clean[mask])


@pytest.mark.parametrize("faults, match", [
    ({"dropuot": 0.1}, "unknown sensor faults"),
    ({"dropout": 1.5}, "dropout must be"),
    ({"saturation": (1.0, 0.0)}, "low < high"),
    ({"latency": -1}, "latency must be"),
    ({"slow_sensors": (16,), "slow_every": 2}, "beyond"),
    ("dropout", "faults must be"),
])
def test_bad_faults_are_refused_clearly(burgers_small: Path, faults, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        dks_gym.SensingEnv("burgers", preset="small", n_sensors=16, faults=faults)


def test_a_cells_faults_do_not_depend_on_the_rest_of_the_layout(burgers_small: Path) -> None:
    """Like its noise, a cell's faults are keyed by the cell: two layouts sharing it see the same faulty readings."""
    faults = {"dropout": 0.3, "failure_rate": 0.02, "drift": 0.05}
    out = []
    for layout in ([100, 500, 900], [700, 100, 300]):
        env = dks_gym.SensingEnv("burgers", preset="small", sensors=np.array(layout), faults=faults)
        obs, infos = _episode(env, seed=7, options={"trajectory": 0})
        column = layout.index(100)
        out.append((obs[:, column], np.array([i["mask"][column] for i in infos])))
    np.testing.assert_array_equal(out[0][0], out[1][0])
    np.testing.assert_array_equal(out[0][1], out[1][1])
    assert not out[0][1].all()  # some readings of the shared cell are missing
