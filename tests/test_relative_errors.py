"""The relative L2 error ||x^ - x|| / ||x|| and the score 100 (1 - relative L2) beside Eq. 18's MSE: their
computation, the wrappers' infos, the records and the tables, each against a direct numpy computation."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from dks_gym.assimilation import AssimilationConfig, ctf_score, field_errors, relative_l2_errors, run_assimilation
from dks_gym.dataset import Dataset
from dks_gym.models import build_model
from dks_gym.models.calibration import calibrate


def _direct(estimate: np.ndarray, truth: np.ndarray, scored: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """numpy: the relative L2 error over the scored channels and every cell (B,), and per channel (B, n)."""
    diff = (estimate.astype(np.float64) - truth.astype(np.float64))[:, scored].reshape(len(truth), len(scored), -1)
    x = truth.astype(np.float64)[:, scored].reshape(len(truth), len(scored), -1)
    total = np.sqrt((diff**2).sum(axis=(1, 2)) / (x**2).sum(axis=(1, 2)))
    return total, np.sqrt((diff**2).sum(-1) / (x**2).sum(-1))


def test_relative_l2_against_numpy_and_the_mse() -> None:
    """Over the scored channels only, every cell; the square is the MSE over the mean square of the truth;
    a channel whose truth is 0 has NaN (no error relative to nothing); the score is 100 (1 - it)."""
    rng = np.random.default_rng(0)
    truth = rng.normal(size=(3, 4, 6, 5)).astype(np.float32)
    estimate = (truth + 0.1 * rng.normal(size=truth.shape)).astype(np.float32)
    estimate[:, 1] += 100.0  # an unscored channel: must not count
    scored = (0, 2, 3)
    total, per_channel = relative_l2_errors(torch.as_tensor(estimate), torch.as_tensor(truth), scored)
    expected = _direct(estimate, truth, list(scored))
    np.testing.assert_allclose(total, expected[0], rtol=1e-12)
    np.testing.assert_allclose(per_channel, expected[1], rtol=1e-12)
    mse = field_errors(torch.as_tensor(estimate).double(), torch.as_tensor(truth).double(), scored).numpy()
    np.testing.assert_allclose(total**2, mse / (truth[:, list(scored)].astype(np.float64) ** 2).mean((1, 2, 3)),
                               rtol=1e-10)
    assert total.dtype == per_channel.dtype == np.float64 and per_channel.shape == (3, 3)

    truth[1, 2] = 0.0  # a fluid at rest in one channel of element 1; element 2 all zero in the scored channels
    truth[2, list(scored)] = 0.0
    total, per_channel = relative_l2_errors(torch.as_tensor(estimate), torch.as_tensor(truth), scored)
    assert np.isnan(per_channel[1, 1]) and np.isfinite(per_channel[1, [0, 2]]).all() and np.isfinite(total[1])
    assert np.isnan(total[2]) and np.isnan(per_channel[2]).all() and np.isfinite(total[0])
    assert ctf_score(0.0) == 100.0 and ctf_score(1.0) == 0.0 and ctf_score(1.5) == -50.0
    np.testing.assert_array_equal(ctf_score(np.array([0.25, np.nan])), [75.0, np.nan])



@pytest.mark.parametrize("scored", [(2, 3), (0, 3), (1,)])
def test_a_run_of_scored_channels_reads_the_same_cells_as_a_list(scored: tuple[int, ...]) -> None:
    """Scored channels in a run are read through a view (no copy), others by index: both against numpy,
    the MSE standardized by a per-channel std too."""
    rng = np.random.default_rng(1)
    truth = rng.normal(size=(2, 4, 5, 3))
    estimate = truth + 0.1 * rng.normal(size=truth.shape)
    std = np.array([0.5, 2.0, 4.0, 8.0])
    total, per_channel = relative_l2_errors(torch.as_tensor(estimate), torch.as_tensor(truth), scored)
    np.testing.assert_allclose(total, _direct(estimate, truth, list(scored))[0], rtol=1e-12)
    np.testing.assert_allclose(per_channel, _direct(estimate, truth, list(scored))[1], rtol=1e-12)
    diff = (estimate - truth)[:, list(scored)] / std[list(scored)][None, :, None, None]
    mse = field_errors(torch.as_tensor(estimate), torch.as_tensor(truth), scored, torch.as_tensor(std))
    np.testing.assert_allclose(mse.numpy(), (diff**2).mean(axis=(1, 2, 3)), rtol=1e-12)

@pytest.fixture
def dambreak(make_synthetic) -> tuple[Dataset, object]:
    """A five-channel benchmark (synthetic dambreak data) and an untrained calibrated Koopman model."""
    ds = Dataset(make_synthetic("dambreak", n_t=5))
    model = build_model("dambreak", "koopman", r=8, preset="lite", dataset=ds, seed=0)
    model.calibration = calibrate(model, ds, [0, 1])
    model.calibration["Q_scale"] = torch.tensor(1.0, dtype=torch.float64)
    return ds, model


def test_a_run_records_the_relative_error_of_every_frame(dambreak) -> None:
    """The result's final relative errors are those of its final fields; at frame 0 the square is the MSE over
    the mean square of the truth."""
    ds, model = dambreak
    result = run_assimilation(model, ds, AssimilationConfig().replace(kind="ekf"), uncertainty=False)
    scored = list(ds.benchmark.scored_indices)
    total, per_channel = _direct(result.final_estimate, result.final_truth, scored)
    assert result.step_rel_l2.shape == result.step_mse.shape
    np.testing.assert_allclose(result.final_rel_l2, total, rtol=1e-6)
    np.testing.assert_allclose(result.final_channel_rel_l2, per_channel, rtol=1e-6)
    truth0 = np.stack([ds.trajectory("test", int(t))[0] for t in result.trajectories])
    mean_square = (truth0[:, scored].astype(np.float64) ** 2).reshape(len(truth0), -1).mean(1)
    np.testing.assert_allclose(result.step_rel_l2[:, 0] ** 2, result.step_mse[:, 0] / mean_square, rtol=1e-4)


def _check_info(info: dict, truth: np.ndarray, channels: tuple[str, ...], scored: list[int]) -> None:
    """An info's relative errors and score against numpy on its own estimate and the env's true state."""
    total, per_channel = _direct(info["estimate"][None], truth[None], scored)
    assert info["relative_l2"] == pytest.approx(total[0], rel=1e-6)
    assert info["score"] == pytest.approx(100 * (1 - total[0]), rel=1e-6)
    assert list(info["relative_l2_channels"]) == list(channels)
    np.testing.assert_allclose(list(info["relative_l2_channels"].values()), per_channel[0], rtol=1e-6)


def test_the_wrappers_infos_hold_the_relative_errors(dambreak) -> None:
    """LatentFilter's info at reset and each step, against numpy on info["estimate"] and the true state;
    the vector env's infos are those of N single envs, and stable-baselines3's list of infos passes them on."""
    import gymnasium as gym

    from dks_gym.wrappers import LatentFilter
    from dks_gym.wrappers.vector import LatentFilterVectorEnv, SB3VecEnv

    ds, model = dambreak
    bench = ds.benchmark
    scored = list(bench.scored_indices)
    singles = []
    for i in range(2):
        env = LatentFilter(gym.make("DKS/Dambreak-v0", data_path=str(ds.path)), model=model, filter="ekf")
        infos = [env.reset(seed=10 + i)[1]]
        _check_info(infos[0], env.unwrapped.true_state, bench.scored_channels, scored)
        for _ in range(2):
            infos.append(env.step(None)[-1])
            _check_info(infos[-1], env.unwrapped.true_state, bench.scored_channels, scored)
        singles.append(infos)
        env.close()
    venv = LatentFilterVectorEnv("dambreak", 2, model=model, filter="ekf", data_path=str(ds.path))
    batched = [venv.reset(seed=10)[1]] + [venv.step(np.zeros(2))[-1] for _ in range(2)]
    for k, infos in enumerate(batched):
        for i in range(2):
            assert infos["relative_l2"][i] == pytest.approx(singles[i][k]["relative_l2"], rel=2e-4)
            assert infos["score"][i] == pytest.approx(singles[i][k]["score"], rel=2e-4)
            for c in bench.scored_channels:
                assert infos["relative_l2_channels"][c][i] == pytest.approx(singles[i][k]["relative_l2_channels"][c],
                                                                            rel=2e-4)
    pytest.importorskip("stable_baselines3")
    sb3 = SB3VecEnv(LatentFilterVectorEnv("dambreak", 2, model=model, filter="ekf", data_path=str(ds.path)))
    sb3.seed(10)
    sb3.reset()
    sb3.step_async(np.zeros(2))
    out = sb3.step_wait()[-1]
    for i in range(2):
        assert out[i]["relative_l2"] == pytest.approx(float(batched[1]["relative_l2"][i]), rel=1e-6)
        assert out[i]["score"] == pytest.approx(float(batched[1]["score"][i]), rel=1e-6)
        assert out[i]["relative_l2_channels"] == pytest.approx(
            {c: float(v[i]) for c, v in batched[1]["relative_l2_channels"].items()}, rel=1e-6)


def test_records_hold_the_relative_errors_and_old_records_stay_valid(dambreak) -> None:
    """make_record's relative fields are the result's arrays summarized; a record without them (every record
    written before them) is valid; malformed ones are refused."""
    from dks_gym.evaluation.results import ResultsError, make_record, validate_record

    ds, model = dambreak
    result = run_assimilation(model, ds, AssimilationConfig().replace(kind="forward"), uncertainty=False)
    rec = make_record(result, experiment="main")
    final = result.step_rel_l2[:, -1]
    assert rec["final_rel_l2_mean"] == pytest.approx(final.mean(), rel=1e-12)
    assert rec["final_rel_l2_std"] == pytest.approx(final.std(ddof=1), rel=1e-12)
    np.testing.assert_allclose(rec["per_trajectory_final_rel_l2"], final, rtol=1e-12)
    np.testing.assert_allclose(rec["per_step_rel_l2_mean"], result.step_rel_l2.mean(0), rtol=1e-12)
    assert rec["final_score_mean"] == pytest.approx(100 * (1 - final.mean()), rel=1e-12)
    assert list(rec["final_channel_rel_l2_mean"]) == list(ds.scored_channels)
    np.testing.assert_allclose(list(rec["final_channel_rel_l2_mean"].values()),
                               result.final_channel_rel_l2.mean(0), rtol=1e-12)
    validate_record(rec)
    fields = ("final_rel_l2_mean", "final_rel_l2_std", "per_step_rel_l2_mean", "per_trajectory_final_rel_l2",
              "final_score_mean", "final_channel_rel_l2_mean")
    validate_record({k: v for k, v in rec.items() if k not in fields})
    validate_record(dict(rec, final_rel_l2_mean=None, final_score_mean=None))  # a truth of norm 0
    for name, bad in (("final_rel_l2_mean", "x"), ("final_score_mean", [1.0]),
                      ("per_trajectory_final_rel_l2", [0.1]), ("per_step_rel_l2_mean", [0.1, 0.2]),
                      ("final_channel_rel_l2_mean", {"p": "x"})):
        with pytest.raises(ResultsError, match=name):
            validate_record(dict(rec, **{name: bad}))


def _strip(doc: dict) -> dict:
    """The document as records written before the relative error would hold it."""
    return dict(doc, records=[{k: v for k, v in r.items() if "rel_l2" not in k and "score" not in k}
                              for r in doc["records"]])


def _rel(rec: dict) -> str:
    """A relative error and its score as the tables print them, written out here independently."""
    rel = rec["final_rel_l2_mean"]
    return f"{format(100 * rel, '#.3g').rstrip('.')} % ({100 * (1 - rel):.1f})"


def test_tables_show_the_relative_errors_only_where_the_records_hold_them(dambreak) -> None:
    """The reproduce tables (main and per channel), the demo table and `dks-gym compare` gain relative-L2
    columns with records that hold it, and print as before with records that predate it."""
    from dks_gym.evaluation.comparison import format_comparison
    from dks_gym.evaluation.demo import demo_table
    from dks_gym.evaluation.reproduce import tables_markdown
    from dks_gym.evaluation.results import make_record, new_results
    from dks_gym.evaluation.tabulate import Column, tabulate

    ds, model = dambreak
    records = [make_record(run_assimilation(model, ds, AssimilationConfig().replace(kind=f), uncertainty=False),
                           experiment="main") for f in ("forward", "ekf")]
    doc = new_results("dambreak", "lite", {"path": "x.h5", "fingerprint": "0"},
                      {"scored_channels": list(ds.scored_channels), "n_test": 2}, records)
    lines = tables_markdown(doc).splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("## Main comparison, approximate"))
    header = [c.strip() for c in lines[start + 2].strip("|").split("|")]
    koopman = [c.strip() for c in next(line for line in lines[start:] if line.startswith("| Koopman")).strip("|")
               .split("|")]
    assert header[3:5] == ["forward rel. L2 (score)", "EKF rel. L2 (score)"]
    assert koopman[3:5] == [_rel(records[0]), _rel(records[1])]
    channel_header = next(line for line in lines if line.startswith("| model | estimate |"))
    assert all(f"| {c} rel. L2 |" in channel_header for c in ds.scored_channels)
    old = tables_markdown(_strip(doc))
    assert "rel. L2" not in old and "(score)" not in old

    columns = [Column("kept", lambda r: "-"), Column("dropped", lambda r: "", optional=True),
               Column("shown", lambda r: "x", optional=True)]
    assert tabulate([{"a": 1}], columns) == "| kept | shown |\n|---|---|\n| - | x |"

    demo = [dict(r, model="koopman") for r in records]
    assert "relative L2 error" in demo_table(demo) and _rel(records[1]) in demo_table(demo)
    assert demo_table(_strip({"records": demo})["records"]) == demo_table(demo).split("\n\n")[0]

    compared = format_comparison(doc, doc)
    assert "rel. L2 A" in compared.splitlines()[0]
    assert f"{format(100 * records[0]['final_rel_l2_mean'], '#.3g').rstrip('.')} %" in compared.splitlines()[2]
    assert "rel. L2" not in format_comparison(_strip(doc), doc)


def test_shred_and_placement_records_and_the_ranked_table() -> None:
    """SHRED's per-frame relative errors (episodes of fields) against numpy, their record fields, and the
    placement ranking's column, shown only when the records hold it."""
    from dks_gym.evaluation.results import relative_fields
    from dks_gym_agents.shred_baseline import frame_relative_errors
    from dks_gym_agents.tables import ranked_table

    rng = np.random.default_rng(1)
    truth = rng.normal(size=(2, 3, 3, 4, 5))
    estimate = truth + 0.2 * rng.normal(size=truth.shape)
    total, per_channel = frame_relative_errors(estimate, truth, (0, 2))
    for e in range(2):
        expected = _direct(estimate[e], truth[e], [0, 2])
        np.testing.assert_allclose(total[e], expected[0], rtol=1e-12)
        np.testing.assert_allclose(per_channel[e], expected[1], rtol=1e-12)
    fields = relative_fields(total, per_channel[:, -1], ("u", "p"))
    assert fields["final_rel_l2_mean"] == pytest.approx(total[:, -1].mean())
    assert fields["final_score_mean"] == pytest.approx(100 * (1 - total[:, -1].mean()))
    assert fields["final_channel_rel_l2_mean"]["p"] == pytest.approx(per_channel[:, -1, 1].mean())

    def rec(policy: str, **more) -> dict:
        return {"experiment": f"placement/{policy}", "policy": policy, "per_trajectory_time_mean_mse": [1.0, 2.0],
                "trajectories": [0, 1], "time_mean_mse_mean": 1.5, "time_mean_mse_std": 0.7, "final_mse_mean": 1.0,
                "final_mse_std": 0.0, **more}

    config = {"model": "koopman", "model_preset": "lite", "r": 4, "filter": "ekf", "n_sensors": 4,
              "noise_level": 0.2, "n_episodes": 2, "n_test": 2, "noise_seeds": [0], "n_frames": 5}
    old = {"benchmark": "burgers", "records": [rec("qr"), rec("paper")], "config": config}
    assert "rel. L2" not in ranked_table(old)
    new = dict(old, records=[rec("qr", **fields), rec("paper")])
    lines = ranked_table(new).splitlines()
    assert "| final rel. L2 (score) |" in lines[0]
    qr = next(line for line in lines if "| qr |" in line)
    assert f"| {100 * fields['final_rel_l2_mean']:.3g} % ({fields['final_score_mean']:.1f}) |" in qr


CALIBRATED = Path(__file__).resolve().parents[1] / "docs" / "results" / "burgers-lite-calibrated" / "results.json.gz"
#: The relative L2 fields a record's MSEs determine (per frame only from its curves).
DERIVED = ("final_rel_l2_mean", "final_rel_l2_std", "per_trajectory_final_rel_l2", "final_score_mean",
           "final_channel_rel_l2_mean", "per_step_rel_l2_mean")


def _numbers(value: object) -> np.ndarray:
    return np.array(list(value.values()) if isinstance(value, dict) else value, dtype=np.float64)


def _agree(derived: dict, run: dict, name: str) -> None:
    """A derived field equals the run's to 1e-6, those that subtract (the std, the score 100 (1 - it)) to 1e-6 of
    the error they come from: a difference of nearly equal values magnifies the relative rounding of each."""
    scale = {"final_rel_l2_std": 1.0, "final_score_mean": 100.0}.get(name, 0.0) * run["final_rel_l2_mean"]
    np.testing.assert_allclose(_numbers(derived[name]), _numbers(run[name]), rtol=1e-6, atol=1e-6 * scale,
                               err_msg=name)


def test_the_migration_derives_the_relative_errors_the_runs_computed(burgers_paper, data_home, tmp_path) -> None:
    """From the MSEs the committed records store and freshly generated Burgers paper data (the committed
    fingerprint), the migration derives the relative L2 fields the runs computed from the fields themselves
    (float64 sums over the estimate and the truth) to 1e-6; it checks the fields a record holds, refuses
    other data, and the command adds the fields and their intervals once."""
    from dks_gym.dataset import DatasetMissing
    from dks_gym.evaluation.migrate import DataMismatch, add_relative, main, open_dataset
    from dks_gym.evaluation.results import load_results, save_results

    stored = load_results(CALIBRATED)
    doc = _strip(stored)
    with open_dataset(doc, data_home) as ds:
        assert add_relative(doc, ds).added == len(doc["records"])
        for derived, run in zip(doc["records"], stored["records"]):
            names = [n for n in DERIVED if n != "per_step_rel_l2_mean" or "per_trajectory_step_mse" in run]
            assert [n for n in DERIVED if n in derived] == names, run["experiment"]
            for name in names:
                _agree(derived, run, name)
        report = add_relative(stored, ds)  # records holding the fields: derived again and compared
        assert report.added == 0 and report.checked == len(stored["records"]) and report.max_deviation < 1e-6
        tampered = dict(stored, records=[dict(stored["records"][0], per_trajectory_final_rel_l2=[
            1.001 * v for v in stored["records"][0]["per_trajectory_final_rel_l2"]])])
        with pytest.raises(DataMismatch, match="not the data"):
            add_relative(tampered, ds)
    with pytest.raises(DataMismatch, match="fingerprint"):
        open_dataset(dict(doc, dataset=dict(doc["dataset"], fingerprint="0" * 64)), data_home)

    path = tmp_path / "results.json.gz"
    save_results(_strip(dict(stored, records=stored["records"][:4])), path)
    with pytest.raises(DatasetMissing, match="dks-gym data generate burgers --preset paper"):
        main(["--relative", "--data-home", str(tmp_path / "empty"), str(path)])
    assert main([str(path)]) == 0 and "final_rel_l2_mean" not in load_results(path)["records"][0]  # data-free
    assert main(["--relative", "--data-home", str(data_home), str(path)]) == 0
    migrated, before = load_results(path)["records"], path.read_bytes()
    assert all(m[n] == d[n] for m, d in zip(migrated, doc["records"]) for n in DERIVED if n in d)
    assert all(m["final_rel_l2_ci95"][0] <= m["final_rel_l2_mean"] <= m["final_rel_l2_ci95"][1] for m in migrated)
    assert main(["--relative", str(path)]) == 0 and path.read_bytes() == before  # once


def test_the_derivation_over_several_channels_and_without_curves(dambreak) -> None:
    """Five scored channels: the derived total relative error equals the run's (float32 MSE against float64 sums)
    with and without the per-trajectory curves; the per-channel one, which the MSE over all channels does not
    determine, is left out."""
    from dks_gym.evaluation.migrate import add_relative
    from dks_gym.evaluation.results import make_record, new_results

    ds, model = dambreak
    records = [make_record(run_assimilation(model, ds, AssimilationConfig().replace(kind=f), uncertainty=False),
                           experiment="main", keep_curves=f == "ekf") for f in ("forward", "ekf")]
    doc = _strip(new_results("dambreak", "lite", {"path": "x.h5", "fingerprint": "0"},
                             {"scored_channels": list(ds.scored_channels), "split": "test"}, records))
    report = add_relative(doc, ds)
    assert report.added == 2 and "final_channel_rel_l2_mean not derived (5 scored channels)" in report.notes
    for derived, run in zip(doc["records"], records):
        names = [n for n in DERIVED if n != "final_channel_rel_l2_mean"
                 and (n != "per_step_rel_l2_mean" or "per_trajectory_step_mse" in run)]
        assert [n for n in DERIVED if n in derived] == names
        for name in names:
            _agree(derived, run, name)


def test_the_budget_table_adds_the_relative_errors_only_where_the_records_hold_them() -> None:
    """budgets.md: a second table, per policy and budget, of the final relative L2 error and its score
    (random: the first seed), absent for records that predate the field."""
    from dks_gym.evaluation.results import load_results
    from dks_gym_agents.tables import budget_table

    folder = CALIBRATED.parents[1] / "placement" / "benchmark" / "burgers" / "none"
    docs = {int(p.parent.name[1:]): load_results(p) for p in folder.glob("m*/placement.json.gz")}
    table = budget_table(docs)
    old = budget_table({m: _strip(doc) for m, doc in docs.items()})
    start = table.index("\n\nFinal-time relative L2")
    end = table.find("\n\n", table.index("\n\n|", start) + 2)  # the relative table's end: the notes, or the end
    assert "relative L2" not in old and table[:start] + table[end if end >= 0 else -1:] == old
    lines = table[table.index("Final-time relative L2"):].splitlines()
    m = min(docs)
    for policy in ("paper", "random-0", "forward"):
        row = next(line for line in lines if line.startswith(f"| {policy.removesuffix('-0')} |"))
        rec = next(r for r in docs[m]["records"] if r["policy"] == policy)
        assert row.split(" | ")[1] == _rel(rec), policy
