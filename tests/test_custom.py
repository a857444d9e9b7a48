"""Your own flow as a benchmark: a schema file on a grid none of the four has, its env, the four models trained by
`dks-gym train --data`, and the EKF around them; the sizing rule of the encoders and decoders."""

from __future__ import annotations

import dataclasses

import json
from pathlib import Path

import gymnasium as gym
import h5py
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from dks_gym.benchmarks import BENCHMARKS, CustomBenchmark, GeneratedData
from dks_gym.benchmarks.layout import lattice_counts, lattice_layout
from dks_gym.dataset import SchemaError, load_benchmark, write_dataset

GRID = (20, 36)  # not a multiple of 2**3 along either axis: the backbones pad it to 24 x 40
SOLID = (slice(6, 10), slice(8, 13))  # a 4 x 5 block of solid cells


def _heat(kappa: float, time: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(n_t, 2, *GRID): a decaying temperature mode and its x-derivative, an analytic "simulation"."""
    mode = np.sin(np.pi * x)[:, None] * np.cos(0.5 * np.pi * y)[None, :]
    temperature = np.exp(-kappa * np.pi**2 * time)[:, None, None] * mode
    return np.stack([temperature, np.gradient(temperature, x, axis=1)], axis=1)


@pytest.fixture(scope="module")
def heat_file(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, CustomBenchmark]:
    """A custom benchmark's schema file, written as docs/envs.md says: a CustomBenchmark and write_dataset."""
    cell_type = np.zeros(GRID, dtype=np.int8)
    cell_type[SOLID] = 1
    bench = CustomBenchmark(
        name="heat_plate", grid=GRID, channels=("T", "dTdx"), observed_channel="T", scored_channels=("T", "dTdx"),
        param_name="kappa", param_range=(0.05, 0.5), dt=0.1, n_frames=5, n_train=5, n_test=2,
        cell_types=cell_type, cell_type_codes={"plate": 0, "hole": 1}, solid_codes=(1,),
    )
    x, y = np.linspace(0.0, 1.0, GRID[0]), np.linspace(0.0, 2.0, GRID[1])
    time = bench.dt * np.arange(bench.n_frames)
    params = {"train": np.array([0.05, 0.14, 0.25, 0.36, 0.5]), "test": np.array([0.1, 0.3])}
    data = GeneratedData(time=time, params=params, generator={"name": "analytic heat modes"}, coords=(x, y),
                         cell_type=cell_type, trajectories=((split, i, _heat(k, time, x, y))
                                                            for split, values in params.items()
                                                            for i, k in enumerate(values)))
    path = tmp_path_factory.mktemp("custom") / "heat.h5"
    write_dataset(data, bench, path)
    return path, bench


# The benchmark from its file -------------------------------------------------------------------------------
def test_the_file_describes_its_benchmark(heat_file) -> None:
    path, written = heat_file
    bench = load_benchmark(path)
    assert bench == written and isinstance(bench, CustomBenchmark)
    assert (bench.grid, bench.n_frames, bench.n_train, bench.n_test, bench.env_id) == (GRID, 5, 5, 2, "DKS/Custom-v0")
    np.testing.assert_array_equal(bench.coords()[1], np.linspace(0.0, 2.0, GRID[1]))
    assert bench.fluid_mask().sum() == GRID[0] * GRID[1] - 20
    assert load_benchmark(path).paper_layout(16).tolist() == bench.paper_layout(16).tolist()


def test_a_file_from_another_tool_needs_no_custom_attribute(tmp_path: Path) -> None:
    """Bare h5py, only the schema's required items: the parameter range is the file's, the codes their values."""
    path = tmp_path / "wave.h5"
    with h5py.File(path, "w") as f:
        f.attrs.update(benchmark="wave_1d", channels=json.dumps(["h"]), observed_channel="h", scored_channels=["h"],
                       param_name="c", dt=0.5, generator=json.dumps({"name": "elsewhere"}), schema_version=1,
                       created="2026-01-01")
        f["time"] = 0.5 * np.arange(3)
        f["coords/x"] = np.arange(100.0)
        f["cell_type"] = np.r_[np.full(50, 7), np.full(50, 3)].astype(np.int8)
        for split, params in (("train", [1.0, 2.0]), ("test", [1.5])):
            f[f"{split}/fields"] = np.ones((len(params), 3, 1, 100), np.float32)
            f[f"{split}/params"] = np.asarray(params)
        f["stats/mean"], f["stats/std"] = np.zeros(1), np.ones(1)
    bench = load_benchmark(path)
    assert (bench.grid, bench.param_range, bench.cell_type_codes) == ((100,), (1.0, 2.0), {"3": 3, "7": 7})
    with h5py.File(path, "a") as f:
        f["test/params"][0] = 1.0
        f["train/params"][1] = 1.0  # one value: no range to scale the parameter to
    with pytest.raises(SchemaError, match="param_range"):
        load_benchmark(path)
    with h5py.File(path, "a") as f:
        f.attrs["param_range"] = [0.5, 3.0]
        f.attrs["benchmark"] = "wave-1d"
    with pytest.raises(SchemaError, match="lower-case letters"):
        load_benchmark(path)


def test_lattice_layout_is_equidistant_and_avoids_solid_cells() -> None:
    assert lattice_counts((64, 64), 16) == (4, 4) and lattice_counts((24, 40), 16) == (4, 4)
    assert lattice_counts((64, 64, 64), 16) == (4, 2, 2) and lattice_counts((100,), 7) == (7,)
    # 1D: 16 bins of 6.25 cells, each sensor on the cell nearest its bin centre, mirror-symmetric.
    line = lattice_layout(np.ones(100, bool), 16)
    assert np.all(np.abs(line - (np.arange(16) + 0.5) * 6.25 + 0.5) <= 0.5) and np.all(line + line[::-1] == 99)
    # 2D: a 4 x 4 lattice of the rows and columns nearest 8 and 24 bin centres; a solid block moves its sensor.
    plate = np.ones((64, 64), bool)
    rows, cols = np.unravel_index(lattice_layout(plate, 16), plate.shape)
    assert sorted(set(rows)) == sorted(set(cols)) == [7, 23, 40, 56]
    plate[20:26, 20:26] = False
    moved = lattice_layout(plate, 16)
    assert plate.ravel()[moved].all() and len(set(moved.tolist())) == 16
    assert np.ravel_multi_index((23, 23), plate.shape) not in moved
    with pytest.raises(ValueError, match="fluid cells"):
        lattice_layout(np.zeros(10, bool), 1)


# The sizing rule ----------------------------------------------------------------------------------------------
def test_sizing_rule_gives_the_paper_stage_counts_and_tables_where_they_coincide() -> None:
    from dks_gym.models.presets import BACKBONES, backbone_spec, benchmark_shape, sized_backbone, stride_stages

    for name, bench in BENCHMARKS.items():
        assert stride_stages(bench.grid) == len(BACKBONES["paper"][name].conv_channels) == \
            len(BACKBONES["lite"][name].conv_channels)
        for preset in ("paper", "lite"):  # the four keep their tables, whatever the rule says
            assert backbone_spec(name, preset) is BACKBONES[preset][name]
    burgers, cylinder = benchmark_shape("burgers"), benchmark_shape("cylinder")
    assert sized_backbone(burgers, "paper") == BACKBONES["paper"]["burgers"]  # 8-16-32, k3, FC 512-256
    # lite: at least 8 channels first, so Burgers' shape gets 8-16-32, wider than its lite table's 2-4-8
    lite_8 = dataclasses.replace(BACKBONES["lite"]["burgers"], conv_channels=(8, 16, 32))
    assert sized_backbone(burgers, "lite") == lite_8
    assert sized_backbone(cylinder, "lite") == BACKBONES["lite"]["cylinder"]  # 8-16-32, k5, FC 128-64
    assert stride_stages((2048,)) == 4 and stride_stages((20, 36)) == 3 and stride_stages((96, 96)) == 4


def test_padded_grid_decodes_to_the_grid_and_its_sensor_jacobian_is_the_derivative() -> None:
    """100 cells pad to 104 (3 stages, 13 bottleneck cells); the filters' sensor-window Jacobian must still be the
    derivative of the whole (cropped) decode, at the last real cell too."""
    from dks_gym.models import build_model

    bench = CustomBenchmark(name="line", grid=(100,), channels=("u",), observed_channel="u", scored_channels=("u",),
                            param_name="a", param_range=(1.0, 2.0), dt=0.1, n_frames=4, n_train=2, n_test=1)
    model = build_model(bench, "mlp", r=4, preset="lite", seed=0).double()
    assert model.decoder.bottleneck == (32, 13) and model.decoder.window() == (5,)  # lite 8-16-32
    mu = torch.tensor([1.0, 1.5, 2.0], dtype=torch.float64)
    z = torch.randn(3, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    assert model.decode(z, mu).shape == (3, 1, 100) and model.encode(model.decode(z, mu), mu).shape == (3, 4)
    sensors = np.array([[0, 1, 50, 95, 98, 99]] * 3)
    values, jacobian = model.filter_observe_jacobian(mu, lambda n: sensors.repeat(n // 3, axis=0), "u")(z)
    with torch.no_grad():
        torch.testing.assert_close(values, model.decode(z, mu)[:, 0, sensors[0]], rtol=1e-12, atol=1e-12)
        for i in range(4):
            dz = torch.zeros_like(z)
            dz[:, i] = 1e-6
            fd = (model.decode(z + dz, mu) - model.decode(z - dz, mu))[:, 0, sensors[0]] / 2e-6
            torch.testing.assert_close(jacobian[..., i], fd, rtol=1e-6, atol=1e-9)
    # The predictive variance's exact rule crops as the decoder does: diag(G G^T) from the whole Jacobian.
    full = torch.autograd.functional.jacobian(lambda v: model.decode(v, mu).sum(0), z)  # (1, 100, 3, 4)
    expected = (full.permute(2, 0, 1, 3) ** 2).sum(-1)  # (3, 1, 100)
    eye = torch.eye(4, dtype=torch.float64).expand(3, 4, 4)
    torch.testing.assert_close(model.decoder_variance(z, mu, eye), expected, rtol=1e-9, atol=1e-12)


# The env, training and the filter ------------------------------------------------------------------------------
def test_padded_2d_grid_reads_its_sensors_from_their_windows_as_the_whole_decode() -> None:
    """84 x 84 pads to 88 x 88 (11 x 11 bottleneck cells, a 7 x 7 window): the members' sensor readings from their
    windows must be the whole (cropped) decode's at the same flat indices of the 84 x 84 grid, far corner too."""
    from dks_gym.models import build_model

    bench = CustomBenchmark(name="plate", grid=(84, 84), channels=("u",), observed_channel="u",
                            scored_channels=("u",), param_name="a", param_range=(1.0, 2.0), dt=0.1, n_frames=4,
                            n_train=2, n_test=1)
    model = build_model(bench, "mlp", r=4, preset="lite", seed=0).double().eval()
    assert model.decoder.crop is not None and model.decoder.window() == (7, 7)
    mu = torch.tensor([1.0, 1.5], dtype=torch.float64)
    z = torch.randn(2, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    sensors = np.array([0, 85, 84 * 40 + 83, 84 * 83 + 7, 84 * 84 - 1])
    with torch.no_grad():
        whole = model.decode(z, mu).flatten(2)[:, 0, sensors]
        torch.testing.assert_close(model.observe(z, mu, sensors, "u"), whole, rtol=1e-10, atol=1e-12)
        per_row = np.stack([sensors, sensors[::-1]])  # one layout per row: the windows path without the cache
        torch.testing.assert_close(model.observe(z, mu, per_row, "u"),
                                   model.decode(z, mu).flatten(2)[:, 0].gather(1, torch.as_tensor(per_row)))


def test_custom_env_steps_with_noise_faults_select_mode_and_render(heat_file) -> None:
    path, bench = heat_file
    env = gym.make("DKS/Custom-v0", data_path=str(path), sensor_mode="select", noise_level=0.1,
                   faults={"dropout": 0.25}, render_mode="rgb_array")
    obs, info = env.reset(seed=3, options={"trajectory": 1})
    base = env.unwrapped
    assert base.benchmark == bench and info["param_name"] == "kappa" and info["mu"] == 0.3
    assert env.action_space.nvec.tolist() == [GRID[0] * GRID[1] - 20] * 16  # every fluid cell a candidate
    assert info["sensors"].tolist() == bench.paper_layout(16).tolist()
    truth = _heat(0.3, bench.dt * np.arange(5), np.linspace(0, 1, GRID[0]), np.linspace(0, 2, GRID[1]))
    for k in range(1, 4):
        obs, reward, terminated, truncated, info = env.step(np.arange(16) * 7)
        assert info["sensors"].tolist() == base.candidates[np.arange(16) * 7].tolist()
        present = info["mask"]
        assert np.isnan(obs[~present]).all() and np.isfinite(obs[present]).all()
        np.testing.assert_allclose(base.true_state, truth[k], rtol=1e-6, atol=1e-7)
        error = obs[present] - truth[k, 0].ravel()[info["sensors"][present]]
        assert np.all(np.abs(error) < 6 * info["sigma"])  # Gaussian noise of the stated sigma, not more
    assert info["sigma"] == pytest.approx(0.1 * np.abs(truth[:, 0][:, bench.fluid_mask()]).max(), rel=1e-6)
    frame = env.render()
    assert frame.ndim == 3 and frame.shape[2] == 3 and frame.dtype == np.uint8 and frame.std() > 0
    with pytest.raises(ValueError, match="data_path"):
        gym.make("DKS/Custom-v0")


def test_dks_gym_train_on_the_file_then_the_ekf_filters_the_custom_env(heat_file, tmp_path, monkeypatch) -> None:
    from dks_gym import LatentFilter, ModelSpec
    from dks_gym.cli import main
    from dks_gym.models import model_from_checkpoint

    path, bench = heat_file
    monkeypatch.setenv("DKS_GYM_HOME", str(tmp_path))
    # The loss-curve figure costs 1-2 s a model here (matplotlib's layout) and is tested with Burgers
    # (test_training.py); its call is recorded instead.
    figures = []
    monkeypatch.setattr("dks_gym.models.training.write_loss_curves", lambda *args: figures.append(Path(args[2])))
    args = ["train", "--data", str(path), "--r", "4", "--steps", "2", "--batch-size", "4", "--no-progress",
            "--no-eval"]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    for kind in ("koopman", "mlp", "xlstm"):
        checkpoint = tmp_path / "models" / f"heat_plate-{kind}-lite-r4-T1-data-custom.safetensors"
        assert checkpoint.with_name(checkpoint.stem + ".loss.png") in figures
        model = model_from_checkpoint(checkpoint)  # rebuilt from the checkpoint alone: no registry entry, no data
        assert (model.benchmark, model.grid, model.decoder.bottleneck[1:]) == ("heat_plate", GRID, (3, 5))
    assert "pdmd: POD + parametric DMD fitted" in result.output
    assert CliRunner().invoke(main, ["train", "--model", "mlp"]).exit_code == 2  # no benchmark, no file

    env = LatentFilter(gym.make("DKS/Custom-v0", data_path=str(path)), model=ModelSpec("koopman", r=4), filter="ekf")
    obs, info = env.reset(seed=0)
    assert obs.shape == (8,) and info["estimate"].shape == (2, *GRID)
    for _ in range(3):
        obs, reward, terminated, truncated, info = env.step(0)
        assert np.isfinite(reward) and reward == pytest.approx(-info["mse"])
        assert info["estimate_std"].shape == (2, *GRID) and np.all(info["estimate_std"] > 0)
