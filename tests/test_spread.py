"""The spread diagnostics (dks_gym.assimilation.spread), each against something independent.

* the ranks of the truth against scipy's ``rankdata`` (ties: within the span scipy gives, uniform over it);
* the rank histogram flat when the truth is drawn like the members (chi-square at a fixed seed), sloped when
  it is shifted, U-shaped when the members are too narrow, dome-shaped when too wide;
* the fixed cells on the Burgers grid (computed by hand) and on a masked two-channel grid;
* the core's ranks against the EnKF's members decoded here, step by step;
* records with the new fields round-trip through save and load, are validated, and tabulate and draw; records
  without them (the committed cylinder results) tabulate without the columns and draw no figure.

The spread-skill ratio of an exactly calibrated filter (1 within sampling error, well below 1 when told too
little process noise) is checked in tests/test_uncertainty.py, beside coverage and NEES on the same runs.
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy import stats

from dks_gym.assimilation import Assimilation, AssimilationConfig, FilterConfig, close_envs, episode_envs
from dks_gym.assimilation import run_assimilation
from dks_gym.assimilation.spread import rank_cells, rank_histogram, spread_skill, truth_ranks
from dks_gym.benchmarks import get_benchmark
from dks_gym.dataset import Dataset
from dks_gym.evaluation.experiment import EXPERIMENTS
from dks_gym.evaluation.results import (
    ResultsError,
    load_results,
    make_record,
    new_results,
    save_results,
    validate_record,
)
from dks_gym.evaluation.tabulate import Records
from dks_gym.models import build_model

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results"


# Ranks and histograms -------------------------------------------------------------------------------------
def test_truth_ranks_match_scipy_rankdata() -> None:
    rng = np.random.default_rng(0)
    members, truth = rng.normal(size=(50, 10, 6)), rng.normal(size=(50, 6))
    ranks = truth_ranks(members, truth, np.random.default_rng(1))
    # The truth's rank among members and truth together (1-based, no ties in continuous draws), less one.
    pooled = np.concatenate([members, truth[:, None]], axis=1)
    expected = stats.rankdata(pooled, axis=1)[:, -1] - 1
    np.testing.assert_array_equal(ranks, expected.astype(np.int64))
    # Ties (integer values): a rank between the lowest and the highest rank scipy gives the tied group.
    members, truth = rng.integers(0, 3, size=(400, 7, 5)), rng.integers(0, 3, size=(400, 5))
    ranks = truth_ranks(members, truth, np.random.default_rng(2))
    pooled = np.concatenate([members, truth[:, None]], axis=1)
    low = stats.rankdata(pooled, axis=1, method="min")[:, -1] - 1
    high = stats.rankdata(pooled, axis=1, method="max")[:, -1] - 1
    assert np.all((low <= ranks) & (ranks <= high)) and np.any(low < high)
    # Every member equal to the truth: the rank is uniform over 0..n.
    tied = truth_ranks(np.zeros((4000, 7, 1)), np.zeros((4000, 1)), np.random.default_rng(3))
    assert stats.chisquare(rank_histogram(tied, 7)).pvalue > 0.01
    # Reproducible from the generator's seed.
    np.testing.assert_array_equal(ranks, truth_ranks(members, truth, np.random.default_rng(2)))
    with pytest.raises(ValueError, match="do not match"):
        truth_ranks(members, truth[:, :2], rng)
    with pytest.raises(ValueError, match=r"\[0, 7\]"):
        rank_histogram(np.array([8]), 7)


def test_rank_histogram_is_flat_only_for_a_calibrated_ensemble() -> None:
    rng = np.random.default_rng(4)
    n, draws = 9, 6000
    members = rng.normal(size=(draws, n, 1))

    def histogram(truth: np.ndarray) -> np.ndarray:
        counts = rank_histogram(truth_ranks(members, truth[:, None], np.random.default_rng(5)), n)
        assert counts.shape == (n + 1,) and counts.sum() == draws
        return counts

    flat = histogram(rng.normal(size=draws))
    assert stats.chisquare(flat).pvalue > 0.01, flat  # the truth is one more member
    shifted = histogram(rng.normal(size=draws) + 1.0)  # a biased ensemble: the truth ranks high
    assert stats.chisquare(shifted).pvalue < 1e-10 and shifted[n // 2 + 1:].sum() > 0.75 * draws, shifted
    narrow = histogram(2.0 * rng.normal(size=draws))  # members too narrow: the truth often outside them
    assert min(narrow[0], narrow[-1]) > 3 * np.median(narrow[1:-1]), narrow
    wide = histogram(0.4 * rng.normal(size=draws))  # members too wide: the truth in the middle
    assert max(wide[0], wide[-1]) < 0.5 * wide[n // 2], wide


def test_spread_skill_averages_the_squares_first() -> None:
    predicted = np.array([[1.0, 4.0], [9.0, 0.0]])
    mse = np.array([[4.0, 1.0], [1.0, 0.0]])
    np.testing.assert_allclose(spread_skill(predicted, mse), [np.sqrt(10 / 5), np.sqrt(4 / 1)])
    assert np.isnan(spread_skill(predicted[:, 1:], np.zeros((2, 1)))[0])  # no error: no ratio


def test_rank_cells_are_equidistant_fluid_cells_off_the_sensors() -> None:
    bench = get_benchmark("burgers")
    cells = rank_cells(bench, np.ones(bench.grid, dtype=bool))
    np.testing.assert_array_equal(cells, 64 + 128 * np.arange(8))  # the sensors sit at 32 + 64 j

    class TwoChannels:  # a masked 6 x 5 grid scoring channels 0 and 2, two sensors
        scored_indices = (0, 2)

        @staticmethod
        def paper_layout() -> np.ndarray:
            return np.array([7, 12])

    mask = np.ones((6, 5), dtype=bool)
    mask[2:4, 1:3] = False  # a solid body
    cells = rank_cells(TwoChannels(), mask, count=6)
    channel, cell = np.divmod(cells, 30)
    assert set(channel) == {0, 2} and np.all(mask.ravel()[cell]) and not np.isin(cell, [7, 12]).any()
    assert len(np.unique(cells)) == 6 and np.all(np.diff(cells) > 0)
    with pytest.raises(ValueError, match="at most"):
        rank_cells(TwoChannels(), mask, count=60)


# The core and the loop ------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def pdmd(burgers_small: Path):
    ds = Dataset(burgers_small)
    model = build_model("burgers", "pdmd", r=8, preset="lite", dataset=ds, seed=0)
    model.fit_dataset(ds)
    return model


ENKF = FilterConfig(kind="enkf", n_members=8, Q=1e-4, P0=1.0)


def test_core_ranks_match_the_members_decoded_here(pdmd, burgers_small: Path) -> None:
    envs = episode_envs(Dataset(burgers_small), np.array([0, 1]), np.array([0, 3]), split="test", noise_level=0.2)
    core = Assimilation(pdmd, ENKF)
    assert core.start(envs, seed=0).sensor_ranks is None  # frame 0: no step yet
    fixed = core.rank_cells
    for _ in range(3):
        steps = [env.step(None) for env in envs]
        snap = core.step(envs, np.stack([s[0] for s in steps]), np.stack([s[4]["sensors"] for s in steps]))
        for b, env in enumerate(envs):
            with torch.no_grad():
                E = core.filter.ensemble[b]
                members = pdmd.decode(E, torch.full((len(E),), env.mu)).flatten(1).double().numpy()
            truth = np.asarray(env.true_state, dtype=np.float64).ravel()
            for cells, ranks in ((env.sensors, snap.sensor_ranks[b]), (fixed, snap.cell_ranks[b])):
                np.testing.assert_array_equal(ranks, (members[:, cells] < truth[cells]).sum(0))
    close_envs(envs)
    ekf = Assimilation(pdmd, FilterConfig(kind="ekf", Q=1e-4, P0=1.0))
    envs = episode_envs(Dataset(burgers_small), np.array([0]), np.array([0]), split="test", noise_level=0.2)
    ekf.start(envs, seed=0)
    step = envs[0].step(None)
    snap = ekf.step(envs, step[0][None], step[4]["sensors"][None])
    assert snap.sensor_ranks is None and ekf.rank_cells is None and snap.spread_skill.shape == (1,)
    close_envs(envs)


def _runs(model, data: Path) -> list[dict]:
    """Calibrated-experiment records of an EKF and an EnKF run over two test trajectories."""
    config = AssimilationConfig(filter=ENKF)
    records = []
    for kind in ("ekf", "enkf"):
        result = run_assimilation(model, data, config.replace(kind=kind), trajectories=[0, 1])
        records.append(make_record(result, experiment="calibrated"))
    return records


def test_records_round_trip_validate_tabulate_and_draw(pdmd, burgers_small: Path, tmp_path: Path) -> None:
    ekf, enkf = _runs(pdmd, burgers_small)
    n_steps = len(enkf["per_step_mse_mean"]) - 1
    assert "rank_histogram_sensors" not in ekf and ekf["final_spread_skill"] > 0
    assert len(enkf["rank_histogram_sensors"]) == len(enkf["rank_histogram_cells"]) == 9
    assert sum(enkf["rank_histogram_sensors"]) == 2 * n_steps * 16  # trajectories x steps x sensors
    assert sum(enkf["rank_histogram_cells"]) == 2 * n_steps * 8
    assert enkf["per_step_spread_skill"][-1] == enkf["final_spread_skill"]
    doc = new_results("burgers", "lite", {"path": "burgers-small.h5"}, {"n_frames": n_steps + 1}, [ekf, enkf])
    back = load_results(save_results(doc, tmp_path / "results.json.gz"))
    assert back["records"] == doc["records"]
    for change, message in ((dict(rank_histogram_cells=[1] * 8), "n_members \\+ 1"),
                            (dict(rank_histogram_cells=[-1] + [1] * 8), "non-negative"),
                            (dict(per_step_spread_skill=[1.0]), "per_step_spread_skill"),
                            (dict(final_spread_skill="1"), "final_spread_skill")):
        with pytest.raises(ResultsError, match=message):
            validate_record({**enkf, **change})
    with pytest.raises(ResultsError, match="EnKF record"):
        validate_record({**ekf, "rank_histogram_sensors": enkf["rank_histogram_sensors"]})
    # The calibrated experiment's table gains the spread-skill columns and its figure is drawn ...
    calibrated = EXPERIMENTS["calibrated"]
    text = "\n\n".join(section.markdown() for section in calibrated.tables(Records(back)))
    assert "spread-skill, final" in text and "spread-skill, all frames" in text
    (figure,) = calibrated.figures(Records(back), tmp_path)
    assert figure.name == "spread.png" and figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # ... while records without the fields (older ones) print the table as before and draw nothing.
    old = copy.deepcopy(back)
    for rec in old["records"]:
        for name in ("final_spread_skill", "per_step_spread_skill", "rank_histogram_sensors", "rank_histogram_cells"):
            rec.pop(name, None)
    old_text = "\n\n".join(section.markdown() for section in calibrated.tables(Records(old)))
    assert "spread-skill" not in old_text and "Spread-skill" not in old_text
    assert "NEES, final" in old_text and calibrated.figures(Records(old), tmp_path / "old") == []


def test_committed_records_without_the_fields_still_tabulate() -> None:
    """The committed cylinder records stripped of the spread fields (as an older file has them) print the
    committed calibrated tables less the spread-skill columns, which are the scores table's last two."""
    doc = load_results(RESULTS / "cylinder" / "results.json.gz")
    assert any("final_spread_skill" in r for r in doc["records"])
    for rec in doc["records"]:
        for name in ("final_spread_skill", "per_step_spread_skill", "rank_histogram_sensors", "rank_histogram_cells"):
            rec.pop(name, None)
    committed = (RESULTS / "cylinder" / "tables.md").read_text().splitlines()
    sections = EXPERIMENTS["calibrated"].tables(Records(doc))
    assert sections
    for line in "\n\n".join(section.markdown() for section in sections).splitlines():
        if line.startswith("|"):  # a row of the committed table, its last two cells (spread-skill) dropped
            assert any(c == line or c.startswith(line[:-1]) and c.count("|") == line.count("|") + 2
                       for c in committed), line
        else:
            assert "spread-skill" not in line.lower() and (not line or line in committed), line
