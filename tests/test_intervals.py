"""The bootstrap intervals of dks_gym.evaluation.intervals: determinism, stratification, coverage, edge cases."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from dks_gym.evaluation.intervals import interval, interval_fields, iqm, strata_of


def test_iqm_is_the_mean_of_the_middle_half() -> None:
    assert iqm([1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 100.0]) == pytest.approx(np.mean([3.0, 4.0, 5.0, 6.0]))


def test_the_interval_is_deterministic_and_holds_its_statistic() -> None:
    x = np.random.default_rng(3).lognormal(size=25)
    for statistic, point in (("mean", np.mean(x)), ("iqm", iqm(x))):
        low, high = interval(x, statistic=statistic, seed=5)
        assert low < point < high
        assert interval(x, statistic=statistic, seed=5) == (low, high)
    assert interval(x, seed=6) != interval(x, seed=5)
    with pytest.raises(ValueError, match="statistic"):
        interval(x, statistic="median")


def test_too_few_or_non_finite_values_give_none_or_are_dropped() -> None:
    assert interval([]) is None
    assert interval([1.0]) is None
    assert interval([1.0, None, float("nan"), float("inf")]) is None
    assert interval([1.0, None, 3.0, float("nan")]) == interval([1.0, 3.0])
    assert interval([1.0, 2.0, 3.0], strata=[0, 1, 2]) is None  # no stratum to resample in
    with pytest.raises(ValueError, match="one label per value"):
        interval([1.0, 2.0], strata=[0])


def test_stratifying_by_trajectory_leaves_out_the_spread_between_trajectories() -> None:
    """Episodes of 10 trajectories x 3 noise seeds: the trajectories differ much more than their seeds, so the
    interval resampled within trajectories is far narrower than the plain one, and stratifying by single
    episodes (every stratum one value) leaves nothing to resample."""
    rng = np.random.default_rng(0)
    trajectories = np.repeat(np.arange(10), 3)
    values = rng.normal(size=10)[trajectories] + 0.05 * rng.normal(size=30)
    plain, stratified = interval(values), interval(values, trajectories)
    assert stratified[0] > plain[0] and stratified[1] < plain[1]
    assert (stratified[1] - stratified[0]) < 0.2 * (plain[1] - plain[0])
    assert plain[0] < values.mean() < plain[1] and stratified[0] < values.mean() < stratified[1]
    # A stratum of one value enters every resample as it is: it moves the interval but does not widen it.
    lone = interval(np.append(values, 100.0), np.append(trajectories, 99))
    assert lone[1] - lone[0] == pytest.approx((stratified[1] - stratified[0]) * 30 / 31, rel=0.2)


def test_strata_of_a_record_are_its_trajectories_only_when_they_repeat() -> None:
    assert strata_of([0, 1, 2]) is None
    assert strata_of(None) is None
    assert strata_of([0, 0, 1, 1]) == [0, 0, 1, 1]


@pytest.mark.parametrize("strata", [False, True])
def test_the_95_percent_interval_covers_the_true_mean_about_95_percent_of_the_time(strata: bool) -> None:
    """Coverage over 400 synthetic data sets (normal, 40 values; stratified: 4 strata of 10 with different
    means, the target the mean of the stratum means): between 90 % and 99 % (the binomial spread of 400
    draws at 95 % is 1.1 %; the percentile interval under-covers a little at this size, and within strata
    by the factor sqrt((n_h - 1) / n_h) on its width, see the module's notes)."""
    hits, n_sets = 0, 400
    offsets = np.linspace(-2.0, 2.0, 4)
    labels = np.repeat(np.arange(4), 10)
    for seed in range(n_sets):
        rng = np.random.default_rng(1000 + seed)
        if strata:
            values, truth = offsets[labels] + rng.normal(size=40), offsets.mean()
            low, high = interval(values, labels, n_resamples=999, seed=seed)
        else:
            values, truth = 3.0 + rng.normal(size=40), 3.0
            low, high = interval(values, n_resamples=999, seed=seed)
        hits += low <= truth <= high
    assert 0.90 <= hits / n_sets <= 0.99, f"coverage {hits / n_sets:.3f}"


def test_records_validate_their_interval_fields_and_the_migration_adds_them(tmp_path) -> None:
    from dks_gym.evaluation.migrate import add_intervals, main
    from dks_gym.evaluation.results import ResultsError, load_results, save_results, validate_record

    committed = Path(__file__).resolve().parents[1] / "docs/results/placement/burgers/koopman-paper/placement.json.gz"
    doc = load_results(committed)
    record = doc["records"][0]
    assert record["final_mse_ci95"][0] <= record["final_mse_mean"] <= record["final_mse_ci95"][1]
    assert record["time_mean_mse_ci95"][0] <= record["time_mean_mse_mean"] <= record["time_mean_mse_ci95"][1]
    for bad in ([1.0], [2.0, 1.0], "x", [None, 1.0]):
        with pytest.raises(ResultsError, match="final_mse_ci95"):
            validate_record({**record, "final_mse_ci95": bad})
    with pytest.raises(ResultsError, match="final_mse_iqm"):
        validate_record({**record, "final_mse_iqm": "x"})
    stored = {k: record.pop(k) for k in list(record) if k.endswith(("_iqm", "_ci95"))}
    validate_record(record)  # absent is fine
    save_results(doc, tmp_path / "placement.json.gz")
    assert main([str(tmp_path)]) == 0
    migrated = load_results(tmp_path / "placement.json.gz")["records"][0]
    fresh = interval_fields(record)  # not the stored values: another scipy may draw differently
    assert set(fresh) == set(stored) and all(migrated[k] == fresh[k] for k in stored)
    assert add_intervals({"records": [dict(migrated, final_mse_ci95=[0.0, 1.0])]})["records"][0][
        "final_mse_ci95"] == [0.0, 1.0]  # what a record holds stays


def test_tables_print_the_stored_interval_and_drop_its_column_for_older_records() -> None:
    from dks_gym.evaluation.formatting import interval as shown
    from dks_gym.evaluation.reproduce import tables_markdown
    from dks_gym.evaluation.results import load_results
    from dks_gym.evaluation.tabulate import mse_ci95

    assert shown(0.0123, 1234.0) == "[0.0123, 1.23e+03]" and shown(None, 1.0) == "-"
    doc = load_results(Path(__file__).resolve().parents[1] / "docs/results/burgers-lite/results.json.gz")
    ekf = next(r for r in doc["records"] if r["experiment"] == "main" and r["filter"] == "ekf")
    # stored, not recomputed: the interquartile mean, then the interval
    assert mse_ci95(dict(ekf, final_mse_iqm=1.5, final_mse_ci95=[1.0, 2.0])) == "1.5 [1, 2]"
    assert mse_ci95(ekf) in tables_markdown(doc) and "EKF IQM [95 % CI]" in tables_markdown(doc)
    for record in doc["records"]:
        record.pop("final_mse_ci95", None)
    assert "EKF IQM [95 % CI]" not in tables_markdown(doc)


def test_the_placement_ranking_states_each_paired_interval_and_whether_it_includes_zero() -> None:
    from dks_gym_agents.paired import add_paired_intervals, paired_vs_random
    from dks_gym_agents.tables import ranked_table

    from dks_gym.evaluation.results import load_results

    path = Path(__file__).resolve().parents[1] / "docs/results/placement/burgers/koopman-paper/placement.json.gz"
    doc = load_results(path)
    table = ranked_table(doc)
    assert "its 95 % CI (bootstrap)" in table and " better |" in table and " worse |" in table
    fresh = paired_vs_random(doc, intervals=True)
    for record in doc["records"]:
        stored = record["paired_vs_random"]["log_ratio_ci95"]
        assert stored[0] <= record["paired_vs_random"]["log_ratio_mean"] <= stored[1]
        assert fresh[record["policy"]]["log_ratio_ci95"] is not None
        record["paired_vs_random"]["log_ratio_ci95"] = [-1.0, 2.0]  # tables print what is stored
    assert "[-1.000, +2.000] includes 0" in ranked_table(doc)
    assert add_paired_intervals(doc)["records"][0]["paired_vs_random"]["log_ratio_ci95"] == [-1.0, 2.0]
    for record in doc["records"]:
        del record["paired_vs_random"]["log_ratio_ci95"]
    assert "95 % CI" not in ranked_table(doc)  # older documents print as they did
    add_paired_intervals(doc)
    assert all(r["paired_vs_random"]["log_ratio_ci95"] == fresh[r["policy"]]["log_ratio_ci95"] for r in doc["records"])
