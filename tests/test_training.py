"""Training (Eqs. 10-11), resumable checkpoints and load_model, on the Burgers `small` dataset with lite models."""

from __future__ import annotations

import dataclasses
import shutil

import h5py
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from dks_gym.cli import main
from dks_gym.dataset import Dataset
from dks_gym.models import (
    CheckpointMissing,
    WindowSampler,
    build_model,
    load_model,
    one_step_error,
    read_metadata,
    train_model,
    training_loss,
    training_schedule,
)

R = 8
STEPS = 150
NEURAL = ("koopman", "mlp", "xlstm")


@pytest.fixture(scope="module")
def ds(burgers_small) -> Dataset:
    return Dataset(burgers_small)


@pytest.fixture(scope="module")
def trained(ds, tmp_path_factory):
    """A short lite training of every model (pDMD: its fit), written to a private directory.

    The module's one long setup (about 20 s on one core): every test here reads these four checkpoints."""
    out = tmp_path_factory.mktemp("checkpoints")
    return {
        kind: train_model("burgers", kind, R, "lite", dataset=ds, progress=False, path=out / f"{kind}.safetensors",
                          schedule=training_schedule("burgers", "lite", steps=STEPS, batch_size=32))
        for kind in (*NEURAL, "pdmd")
    }


def _normalized(ds: Dataset, x: torch.Tensor) -> torch.Tensor:
    mean = torch.as_tensor(ds.stats_mean, dtype=x.dtype).view(-1, 1)
    std = torch.as_tensor(ds.stats_std, dtype=x.dtype).view(-1, 1)
    return (x - mean) / std


# Loss --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["koopman", "xlstm"])
@pytest.mark.parametrize("horizon", [1, 3])
def test_loss_is_eq_11_evaluated_sample_by_sample(ds, kind, horizon):
    model = build_model("burgers", kind, r=R, preset="lite", dataset=ds, seed=1)
    sampler = WindowSampler(ds, horizon, seed=2)
    x, mu = sampler.sample(3)
    loss, terms = training_loss(model, x, mu)
    # Second implementation: one sample and one step at a time, statistics taken from the file.
    rec, pred, lat = [], [], []
    with torch.no_grad():
        for b in range(3):
            m = mu[b: b + 1]
            z = model.encode(x[b, :1], m)
            rec.append(torch.mean((model.decode_normalized(z, m) - _normalized(ds, x[b, 0])) ** 2))
            for j in range(1, horizon + 1):
                z = model.forecast(z, m)
                pred.append(torch.mean((model.decode_normalized(z, m) - _normalized(ds, x[b, j])) ** 2))
                lat.append(torch.mean((z - model.encode(x[b, j: j + 1], m)) ** 2))
    expected = [torch.stack(t).mean() for t in (rec, pred, lat)]
    torch.testing.assert_close(terms[1:], torch.stack(expected), rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(loss.detach(), sum(expected), rtol=1e-5, atol=1e-7)


def test_sampler_windows_are_consecutive_frames_of_one_trajectory(ds):
    for in_memory in (True, False):
        sampler = WindowSampler(ds, 2, seed=5, in_memory=in_memory)
        traj, start = sampler.draw(4)
        x, mu = sampler.windows(traj, start)
        assert x.shape == (4, 3, 1, 1024)
        for b in range(4):
            i, k = int(traj[b]), int(start[b])
            assert 0 <= k <= ds.n_frames - 3
            np.testing.assert_array_equal(x[b].numpy(), ds.trajectory("train", i)[k: k + 3])
            assert float(mu[b]) == ds.params("train")[i]
    a, b = WindowSampler(ds, 1, seed=7), WindowSampler(ds, 1, seed=7, in_memory=False)
    assert all(torch.equal(u, v) for u, v in zip(a.sample(8), b.sample(8)))  # same seed, same batches


# Learning ----------------------------------------------------------------------------------------------
def test_loss_decreases(trained):
    losses = trained["koopman"].losses
    assert losses.shape == (STEPS, 4)
    np.testing.assert_allclose(losses[:, 0], losses[:, 1:].sum(axis=1), rtol=1e-5)
    assert losses[50:60, 0].mean() < 0.2 * losses[:10, 0].mean()
    assert losses[-10:, 0].mean() < 0.9 * losses[50:60, 0].mean()


@pytest.mark.parametrize("kind", NEURAL)
def test_short_training_learns_the_fields(ds, trained, kind):
    # Baseline independent of the model: predicting the train mean field has the train variance as error.
    # 150 lite steps get the one-step decoded error to ~3 % of it; an untrained model is above 100 %.
    fields = np.asarray(ds.fields("train"), dtype=np.float64)
    mean_field_error = float(((fields - fields.mean()) ** 2).mean())
    err = one_step_error(trained[kind].model, ds)
    assert err["pairs"] == ds.n_trajectories("train") * (ds.n_frames - 1)
    assert err["model_mse"] < 0.1 * mean_field_error
    # The reconstruction floor, recomputed from the raw train fields (frames 0..n_t-2 of every trajectory).
    model = trained[kind].model
    x = torch.as_tensor(fields[:, :-1], dtype=torch.float32).flatten(0, 1)
    mu = torch.as_tensor(np.repeat(np.asarray(ds.params("train")), ds.n_frames - 1, axis=0), dtype=torch.float32)
    with torch.no_grad():
        recon = model.decode(model.encode(x, mu), mu)
    assert err["reconstruction_mse"] == pytest.approx(float(((recon - x) ** 2).double().mean()), rel=1e-4)
    untrained = build_model("burgers", kind, r=R, preset="lite", dataset=ds).eval()
    assert one_step_error(untrained, ds)["model_mse"] > 0.5 * mean_field_error


def test_pdmd_trains_through_the_same_entry_point(ds, trained):
    result = trained["pdmd"]
    direct = build_model("burgers", "pdmd", r=R, dataset=ds).fit_dataset(ds, seed=0)
    assert torch.equal(result.model.basis, direct.basis)
    assert read_metadata(result.path)["model"] == "pdmd"
    # On its own training data the fitted pDMD beats predicting "no change" by orders of magnitude.
    err = one_step_error(result.model, ds)
    assert err["model_mse"] < 0.01 * err["persistence_mse"]


# Multi-step --------------------------------------------------------------------------------------------
def test_multistep_training_runs_and_is_recorded(ds, tmp_path):
    result = train_model("burgers", "mlp", R, "lite", T=2, dataset=ds, progress=False, path=tmp_path / "t2.safetensors",
                         schedule=training_schedule("burgers", "lite", steps=4, batch_size=4))
    assert result.losses.shape == (4, 4) and np.isfinite(result.losses).all()
    meta = read_metadata(result.path)
    assert (meta["T"], meta["steps_done"], meta["complete"]) == (2, 4, True)
    with pytest.raises(ValueError, match="T = 2, not 1"):
        load_model("burgers", "mlp", R, "lite", T=1, path=result.path)


# Resume ------------------------------------------------------------------------------------------------
def test_interrupted_training_resumes_to_bit_identical_weights(ds, tmp_path):
    kwargs = {"dataset": ds, "schedule": training_schedule("burgers", "lite", steps=6, batch_size=4),
              "checkpoint_every": 2, "progress": False}
    full = train_model("burgers", "koopman", R, "lite", path=tmp_path / "full.safetensors", **kwargs)

    def interrupt(step, terms):
        if step == 5:
            raise KeyboardInterrupt

    part = tmp_path / "part.safetensors"
    with pytest.raises(KeyboardInterrupt):
        train_model("burgers", "koopman", R, "lite", path=part, on_step=interrupt, **kwargs)
    meta = read_metadata(part)
    assert (meta["steps_done"], meta["complete"]) == (4, False)
    with pytest.raises(CheckpointMissing, match="stopped at step 4 of 6"):
        load_model("burgers", "koopman", R, "lite", dataset=ds, path=part)

    resumed = train_model("burgers", "koopman", R, "lite", path=part, **kwargs)
    assert resumed.new_steps == 2
    np.testing.assert_array_equal(resumed.losses, full.losses)
    a, b = full.model.state_dict(), resumed.model.state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)

    with pytest.raises(ValueError, match="seed"):
        train_model("burgers", "koopman", R, "lite", path=part, seed=1, **kwargs)
    restarted = train_model("burgers", "koopman", R, "lite", path=part, resume=False, **kwargs)
    assert restarted.new_steps == 6


def test_a_finished_constant_rate_run_continues_to_more_steps_bit_for_bit(ds, tmp_path):
    """Training in stages (validation/training_schedule.py): a finished 3-step run of a constant-rate schedule
    continued to 5 steps equals a 5-step run at once; a schedule whose learning rate depends on the step count
    (the lite preset's warm-up and cosine decay) refuses to continue, saying why."""
    def paper(steps):
        return {"dataset": ds, "schedule": training_schedule("burgers", "paper", steps=steps, batch_size=4),
                "progress": False}

    once = train_model("burgers", "mlp", R, "paper", path=tmp_path / "once.safetensors", **paper(5))
    staged = tmp_path / "staged.safetensors"
    train_model("burgers", "mlp", R, "paper", path=staged, **paper(3))
    continued = train_model("burgers", "mlp", R, "paper", path=staged, **paper(5))
    assert continued.new_steps == 2 and read_metadata(staged)["schedule"]["steps"] == 5
    np.testing.assert_array_equal(continued.losses, once.losses)
    a, b = once.model.state_dict(), continued.model.state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    with pytest.raises(ValueError, match="cannot be resumed"):  # fewer steps: not a continuation
        train_model("burgers", "mlp", R, "paper", path=staged, **paper(4))
    lite = tmp_path / "lite.safetensors"
    kwargs = {"dataset": ds, "progress": False}
    train_model("burgers", "mlp", R, "lite", path=lite,
                schedule=training_schedule("burgers", "lite", steps=3, batch_size=4), **kwargs)
    with pytest.raises(ValueError, match="constant learning rate"):
        train_model("burgers", "mlp", R, "lite", path=lite,
                    schedule=training_schedule("burgers", "lite", steps=5, batch_size=4), **kwargs)


# Checkpoints -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kind", (*NEURAL, "pdmd"))
def test_checkpoint_round_trip_is_bit_identical(ds, trained, kind):
    model = trained[kind].model
    loaded = load_model("burgers", kind, R, "lite", dataset=ds, path=trained[kind].path)
    assert type(loaded) is type(model) and not loaded.training
    x = torch.as_tensor(ds.trajectory("test", 0)[:5])
    mu = torch.full((5,), float(ds.params("test")[0]))

    def outputs(m):
        with torch.no_grad():
            z = m.encode(x, mu)
            return z, m.forecast(z, mu), m.decode(z, mu), m.forecast_jacobian(z, mu)

    assert all(torch.equal(u, v) for u, v in zip(outputs(model), outputs(loaded)))


def test_wrong_benchmark_r_model_or_dataset_is_refused(ds, trained, tmp_path):
    path = trained["koopman"].path
    with pytest.raises(ValueError, match="benchmark = 'burgers', not 'cylinder'"):
        load_model("cylinder", "koopman", R, "lite", path=path)
    with pytest.raises(ValueError, match="r = 8, not 32"):
        load_model("burgers", "koopman", 32, "lite", path=path)
    with pytest.raises(ValueError, match="model = 'koopman', not 'mlp'"):
        load_model("burgers", "mlp", R, "lite", path=path)
    # A byte-identical copy elsewhere is the same dataset; changing one parameter makes it another one.
    copy = tmp_path / "copy.h5"
    shutil.copy(ds.path, copy)
    load_model("burgers", "koopman", R, "lite", dataset=Dataset(copy), path=path)
    with h5py.File(copy, "r+") as f:
        f["train/params"][0] += 1e-3
    with pytest.raises(ValueError, match="trained on another dataset"):
        load_model("burgers", "koopman", R, "lite", dataset=Dataset(copy), path=path)


def test_load_model_missing_names_the_train_command(ds, tmp_path, monkeypatch):
    monkeypatch.setenv("DKS_GYM_HOME", str(tmp_path))
    with pytest.raises(FileNotFoundError, match="dks-gym train burgers --model koopman --preset lite --r 8 --T 1 "
                                                "--data-preset small"):
        load_model("burgers", "koopman", R, dataset=ds)
    # train_if_missing fits (pDMD: quickly) into the data home, and the next call only loads.
    first = load_model("burgers", "pdmd", R, dataset=ds, train_if_missing=True, progress=False)
    path = tmp_path / "models" / "burgers-pdmd-r8-data-small.safetensors"
    stamp = path.stat().st_mtime_ns
    second = load_model("burgers", "pdmd", R, dataset=ds)
    assert path.stat().st_mtime_ns == stamp and torch.equal(first.basis, second.basis)


def test_cli_train(ds, tmp_path, monkeypatch):
    monkeypatch.setenv("DKS_GYM_HOME", str(tmp_path))
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "burgers-small.h5").symlink_to(ds.path)
    args = ["train", "burgers", "--model", "mlp", "--r", "8", "--steps", "3", "--batch-size", "2",
            "--data-preset", "small", "--no-progress"]
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    assert "mlp" in result.output and " s" in result.output
    meta = read_metadata(tmp_path / "models" / "burgers-mlp-lite-r8-T1-data-small.safetensors")
    assert (meta["steps_done"], meta["batch_size"], meta["complete"]) == (3, 2, True)
    again = CliRunner().invoke(main, args)  # the default --resume finds the finished checkpoint
    assert again.exit_code == 0 and "already trained" in again.output
    bad = CliRunner().invoke(main, ["train", "burgers", "--model", "mlp", "--device", "cuda"] + args[4:])
    if not torch.cuda.is_available():
        assert bad.exit_code != 0 and "CUDA is not available" in bad.output


@pytest.mark.parametrize("in_memory", [True, False])
def test_training_on_a_damaged_file_names_the_file(make_synthetic, in_memory: bool) -> None:
    from dks_gym.dataset import DataError

    from .damage import damage_chunk

    path = make_synthetic("burgers", n_train=3, n_t=6)
    damage_chunk(path, "train", 1)
    with Dataset(path) as ds, pytest.raises(DataError, match="is damaged: trajectory 1 of split 'train'"):
        sampler = WindowSampler(ds, 1, seed=0, in_memory=in_memory)
        for _ in range(20):  # streamed: some batch draws trajectory 1
            sampler.sample(4)


# Schedule, validation, early stopping, calibration ---------------------------------------------------------
def test_learning_rate_warms_up_then_decays_along_a_cosine():
    from dks_gym.models.schedule import TrainingSchedule

    s = TrainingSchedule(1000, 32, 1e-3, warmup=0.1, final_lr=1e-5)
    assert s.warmup_steps == 100
    np.testing.assert_allclose([s.lr_at(0), s.lr_at(49), s.lr_at(99)], [1e-5, 5e-4, 1e-3])
    np.testing.assert_allclose(s.lr_at(100 + 450), 1e-5 + 0.5 * (1e-3 - 1e-5))  # half way down the cosine
    np.testing.assert_allclose(s.lr_at(1000), 1e-5)
    assert TrainingSchedule(10, 4, 1e-4).lr_at(7) == 1e-4  # the paper's: constant
    lite = TrainingSchedule(8000, 32, 1e-3, epochs=60)
    assert lite.resolve(495).steps == 929 and lite.resolve(4455).steps == 8000  # 60 epochs, at most 8000 steps


def test_adam_step_clips_the_gradients_global_norm():
    """With plain SGD at lr 1 the step is the clipped gradient itself: g * min(1, c / |g|), |g| over all tensors."""
    from dks_gym.models.training import adam_step

    torch.manual_seed(0)
    net = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.GELU(), torch.nn.Linear(4, 2))
    x = torch.randn(5, 3)
    grads = torch.autograd.grad(net(x).pow(2).sum(), list(net.parameters()))
    norm = np.sqrt(sum(float((g.double() ** 2).sum()) for g in grads))
    for clip, scale in ((None, 1.0), (10 * norm, 1.0), (0.25 * norm, 0.25)):
        before = [p.detach().clone() for p in net.parameters()]
        adam_step(net, torch.optim.SGD(net.parameters(), lr=1.0), net(x).pow(2).sum(), clip)
        for p, p0, g in zip(net.parameters(), before, grads):
            torch.testing.assert_close(p0 - p.detach(), scale * g, rtol=1e-5, atol=1e-7)
            p.data.copy_(p0)


def test_a_schedule_without_clipping_records_as_before_the_field_existed():
    """Checkpoints written before ``clip_norm`` (the shipped lite ones, paper-preset runs) keep reading as trained
    with their schedule, so they are neither retrained nor refused on resume; a clipping schedule records it."""
    from dks_gym.models.schedule import TrainingSchedule
    from dks_gym.models.shipped import find_shipped

    paper = training_schedule("burgers", "paper").record()
    assert "clip_norm" not in paper and TrainingSchedule(**paper).record() == paper
    for benchmark in ("cylinder", "dambreak"):  # lite presets without clipping: the shipped files' own schedules
        shipped = find_shipped(benchmark, "koopman").metadata
        assert shipped["schedule"] == TrainingSchedule(**shipped["schedule"]).record()
        assert shipped["preset_schedule"] == training_schedule(benchmark, "lite").record()
    clipped = training_schedule("burgers", "lite")
    assert clipped.record()["clip_norm"] == 0.1 and TrainingSchedule(**clipped.record()) == clipped
    with pytest.raises(ValueError, match="clip_norm must be positive"):
        TrainingSchedule(10, 4, 1e-3, clip_norm=0.0).check()


def test_validation_trajectories_are_held_out_and_the_best_weights_kept(ds, tmp_path, monkeypatch):
    from dks_gym.models.checkpoint import loss_curve_path
    from dks_gym.models.schedule import TrainingSchedule
    from dks_gym.models.validation import ValidationMonitor, validation_trajectories

    held_out = validation_trajectories(ds.n_trajectories("train"), 0.1, seed=3)
    assert held_out == validation_trajectories(6, 0.1, seed=3) and len(held_out) == 1
    seen = set()
    sampler = WindowSampler(ds, 1, seed=0, trajectories=[i for i in range(6) if i not in held_out])
    for _ in range(50):
        seen.update(sampler.draw(8)[0].tolist())
    assert not seen & set(held_out)

    # From step 40 on, Adam moves every weight by about 1 per step: the last weights are not the best ones,
    # whatever the round-off of the machine (a high learning rate's spikes alone depend on it).
    lr_at = TrainingSchedule.lr_at
    monkeypatch.setattr(TrainingSchedule, "lr_at", lambda self, step: lr_at(self, step) if step < 40 else 1.0)
    schedule = dataclasses.replace(training_schedule("burgers", "lite", steps=60, batch_size=8, lr=0.03),
                                   clip_norm=None)
    result = train_model("burgers", "mlp", R, "lite", dataset=ds, seed=3, progress=False,
                         path=tmp_path / "m.safetensors", schedule=schedule)
    meta = read_metadata(result.path)
    assert meta["validation_trajectories"] == held_out and meta["calibrated_on"] == "validation"
    assert loss_curve_path(result.path).stat().st_size > 10_000  # the figure beside the checkpoint
    from dks_gym.models.checkpoint import read_checkpoint

    history = read_checkpoint(result.path).training["validation"]
    assert history.shape[1] == 5 and len(history) >= 10
    best = int(torch.argmin(history[:, 1]))
    assert meta["best_step"] == int(history[best, 0]) <= 40
    # The weights stored (and returned) are the best ones: their validation loss is the history's minimum.
    monitor = ValidationMonitor(ds, held_out, 1, eval_every=1, patience=0, batch_size=8, seed=3)
    loaded = load_model("burgers", "mlp", R, "lite", path=result.path)
    assert float(monitor.loss(loaded)[0]) == pytest.approx(float(history[best, 1]), rel=1e-5)
    assert float(monitor.loss(result.model)[0]) == pytest.approx(float(history[best, 1]), rel=1e-5)


def test_early_stopping_ends_a_run_that_stopped_improving(ds, tmp_path, monkeypatch):
    from dks_gym.models import schedule

    # A learning rate too small to move the loss by 1 % between validations: patience 2 ends it at the third.
    frozen = schedule.TrainingSchedule(400, 8, 1e-9, validation_fraction=0.1, validations=40, patience=2)
    monkeypatch.setitem(schedule.TRAINING_SCHEDULES["lite"], "burgers", frozen)
    result = train_model("burgers", "koopman", R, "lite", dataset=ds, progress=False, path=tmp_path / "k.safetensors")
    meta = read_metadata(result.path)
    assert meta["stopped_early"] and meta["complete"] and result.steps_done == 30
    again = train_model("burgers", "koopman", R, "lite", dataset=ds, progress=False, path=tmp_path / "k.safetensors")
    assert again.loaded_only and again.steps_done == 30


def test_calibrated_q_is_the_true_process_noise_of_a_linear_gaussian_model():
    """z_{k+1} = A z_k + w_k, w ~ N(0, Q): with an exact model (identity encoder and decoder, forecast A z)
    the calibrated Q is the sample covariance of w, within its sampling error."""
    from dks_gym.models.latent_model import LatentModel
    from dks_gym.models.presets import benchmark_shape
    from dks_gym.models.calibration import calibrate

    r, n_traj, n_t = 4, 40, 101
    rng = np.random.default_rng(0)
    A = np.linalg.qr(rng.standard_normal((r, r)))[0] * 0.95
    L = np.tril(rng.standard_normal((r, r))) * 0.1
    Q_true = L @ L.T
    shape = benchmark_shape("burgers")

    class Linear(LatentModel):
        def encode(self, x, mu):
            return torch.as_tensor(x)[:, 0, :r].double()

        def decode(self, z, mu):
            out = torch.zeros(z.shape[0], 1, shape.grid[0], dtype=torch.float64)
            out[:, 0, :r] = z
            return out

        def forecast(self, z, mu):
            return z @ torch.as_tensor(A).T

    class Trajectories:
        def __init__(self) -> None:
            self.data = np.zeros((n_traj, n_t, 1, shape.grid[0]))
            for i in range(n_traj):
                z = rng.standard_normal(r)
                for k in range(n_t):
                    self.data[i, k, 0, :r] = z
                    z = A @ z + L @ rng.standard_normal(r)

        def params(self, split):
            return np.linspace(0.1, 0.9, n_traj)

        def read(self, split, i, *selection):
            return self.data[i][selection]

    model = Linear(shape, r)
    data = Trajectories()
    cal = calibrate(model, data, range(n_traj))
    n = n_traj * (n_t - 1)
    se = np.sqrt((Q_true ** 2 + np.outer(np.diag(Q_true), np.diag(Q_true))) / n)  # std error of each entry
    assert np.all(np.abs(cal["Q"].numpy() - Q_true) < 4 * se)
    assert float(cal["reconstruction_variance"][0, r:].abs().max()) == 0.0  # cells the decoder gets exactly
    # P0: the spread of the first states around their mean, plus Q (and a 1e-6 floor).
    z0 = data.data[:, 0, 0, :r]
    spread = (z0 - z0.mean(0)).T @ (z0 - z0.mean(0)) / n_traj + cal["Q"].numpy()
    np.testing.assert_allclose(cal["P0"].numpy(), spread, rtol=1e-5, atol=1e-6 * np.trace(spread) / r * 1.01)
