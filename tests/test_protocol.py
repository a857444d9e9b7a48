"""The versioned protocols (dks_gym.benchmarks.protocol) and results files that name theirs: every committed file
names its protocol, ``dks-gym compare`` refuses a mismatched pair (``--force`` compares it), the migration of an
older file gives the committed bytes."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import gymnasium as gym
import pytest
from click.testing import CliRunner

import dks_gym  # noqa: F401  (registers the env ids)
from dks_gym.benchmarks import BENCHMARKS
from dks_gym.benchmarks.protocol import BUDGETS, PROTOCOLS, get_protocol
from dks_gym.evaluation.commands import compare_command
from dks_gym.evaluation.comparison import compare
from dks_gym.evaluation.conformance import (
    ProtocolMismatch,
    protocol_differences,
    record_settings,
    run_settings,
    stamp_protocol,
)
from dks_gym.evaluation.migrate import RESULTS_NAMES, main, results_files
from dks_gym.evaluation.results import ResultsError, load_results, save_results, validate

RESULTS = Path(__file__).resolve().parents[1] / "docs" / "results"
BENCH = RESULTS / "placement" / "benchmark"


def test_one_protocol_per_benchmark_with_the_benchmarks_channels_and_env_ids() -> None:
    assert set(PROTOCOLS) == set(BENCHMARKS)
    for name, protocol in PROTOCOLS.items():
        assert protocol.scored_channels == BENCHMARKS[name].scored_channels
        assert protocol.env_id in gym.registry  # the env version (-v0) is the protocol's
        assert (protocol.name, protocol.version) == ("dks-v1", 1) and protocol.n_sensors == BUDGETS
        assert json.loads(json.dumps(protocol.to_dict()))["scored_channels"] == list(protocol.scored_channels)
        assert protocol.describe().startswith(f"dks-v1 v1 ({name}")
    assert get_protocol("Cylinder") is PROTOCOLS["cylinder"]
    with pytest.raises(ValueError, match="burgers"):
        get_protocol("channel")


def test_deviations_name_the_fields_a_run_leaves() -> None:
    protocol = PROTOCOLS["cylinder"]
    assert protocol.deviations({"n_sensors": 4, "noise_level": 0.2, "noise_seeds": [0], "initial": "approximate",
                                "scored_channels": ["u", "v", "p"], "faults": None, "trajectories": "all"}) == {}
    assert protocol.deviations({"n_sensors": 3, "noise_level": 0.1, "noise_seeds": [0, 1], "initial": "exact"}) == {
        "n_sensors": 3, "noise_level": 0.1, "noise_seeds": [0, 1], "initial": "exact"}
    with pytest.raises(ValueError, match="not a protocol field"):
        protocol.deviations({"r": 32})  # the model's size is the method's, not the protocol's


def test_every_committed_results_file_names_its_protocol() -> None:
    files = results_files([RESULTS])
    assert len(files) >= 130
    for path in files:
        doc = load_results(path)
        assert doc["protocol"] == stamp_protocol(copy.deepcopy(doc))["protocol"], path
        assert doc["protocol"]["name"] == "dks-v1" and doc["protocol"]["benchmark"] == doc["benchmark"]
    # the reproduce experiments that leave the protocol are marked per record, the others are not
    doc = load_results(RESULTS / "burgers-lite" / "results.json.gz")
    assert doc["protocol"]["deviations"] == {}
    marks = {(r["experiment"], r["noise"], r["initial"]): r.get("protocol_deviations") for r in doc["records"]}
    assert marks[("noise", 0.1, "approximate")] == ["noise_level"]
    assert marks[("main", 0.2, "exact")] == ["initial"] and marks[("main", 0.2, "approximate")] is None
    assert all("protocol_deviations" not in r for r in doc["records"] if r["experiment"] in ("latent", "multistep")
               and r["initial"] == "approximate" and r["noise"] == 0.2)
    assert load_results(RESULTS / "burgers" / "results.json.gz")["protocol"]["deviations"] == {"model_preset": "paper"}


def test_compare_refuses_a_mismatched_pair_and_force_compares_it() -> None:
    m4, m16 = BENCH / "cylinder/none/m4/placement.json.gz", BENCH / "cylinder/none/m16/placement.json.gz"
    result = CliRunner().invoke(compare_command, [str(m4), str(m16)])
    assert result.exit_code != 0
    assert "not made under the same protocol" in result.output and "n_sensors: A=4, B=16" in result.output
    faulty = BENCH / "cylinder/default/m16/placement.json.gz"
    result = CliRunner().invoke(compare_command, [str(m16), str(faulty)])
    assert result.exit_code != 0 and "faults: A=None, B={'dropout': 0.1" in result.output
    result = CliRunner().invoke(compare_command, [str(m4), str(m16), "--force"])
    assert result.exit_code == 0, result.output
    assert "note: not the same protocol settings (compared with --force): n_sensors: A=4, B=16" in result.output
    assert "placement/qr" in result.output
    # the same protocol and settings (another set of policies): compared, no note
    result = CliRunner().invoke(compare_command, [str(m16), str(BENCH / "cylinder/greedy-none/m16/placement.json.gz")])
    assert result.exit_code == 0 and "note:" not in result.output


def test_protocol_name_version_and_fields_must_agree() -> None:
    a = load_results(RESULTS / "burgers-lite" / "results.json.gz")
    assert protocol_differences(a, a) == [] and compare(a, a)
    b = copy.deepcopy(a)
    b["protocol"]["version"] = 2
    with pytest.raises(ProtocolMismatch, match=r"version: A=1, B=2"):
        compare(a, b)
    b = copy.deepcopy(a)
    b["protocol"]["noise_level"] = 0.1
    assert protocol_differences(a, b) == ["noise_level (protocol): A=0.2, B=0.1"]
    b = copy.deepcopy(a)
    del b["protocol"]
    assert protocol_differences(a, b)[0].startswith("protocol: A=dks-v1 v1, B=none")
    assert protocol_differences(b, b) == []  # two files of an older dks-gym compare as before
    other = load_results(RESULTS / "cylinder" / "results.json.gz")
    assert "benchmark (protocol): A='burgers', B='cylinder'" in protocol_differences(a, other)
    assert compare(a, other, force=True)


def test_migration_of_an_older_file_gives_the_committed_bytes(tmp_path: Path) -> None:
    committed = BENCH / "burgers/noise3-none/m4/placement.json.gz"
    old = load_results(committed)
    del old["protocol"]
    for record in old["records"]:
        record.pop("protocol_deviations", None)
    save_results(old, tmp_path / "run" / "placement.json.gz")
    (tmp_path / "run" / "other.json").write_text("{}")  # not a results document: left alone
    assert main([str(tmp_path)]) == 0
    assert (tmp_path / "run" / "placement.json.gz").read_bytes() == committed.read_bytes()
    assert load_results(committed)["protocol"]["deviations"] == {"noise_seeds": [0, 1, 2]}
    assert main([str(tmp_path)]) == 0 and (tmp_path / "run" / "placement.json.gz").read_bytes() == \
        committed.read_bytes()  # idempotent


def test_the_migration_knows_the_placement_file_name() -> None:
    from dks_gym_agents.records import PLACEMENT_FILE

    assert PLACEMENT_FILE in RESULTS_NAMES


def test_a_malformed_protocol_block_is_refused() -> None:
    doc = load_results(RESULTS / "burgers-lite-calibrated" / "results.json.gz")
    for bad, match in (({"version": 1}, "name"), ({"name": "dks-v1", "version": 0}, "version"),
                       ({"name": "dks-v1", "version": 1, "deviations": []}, "deviations")):
        with pytest.raises(ResultsError, match=match):
            validate(dict(doc, protocol=bad))
    doc = copy.deepcopy(doc)
    doc["records"][0]["protocol_deviations"] = "initial"
    with pytest.raises(ResultsError, match="protocol_deviations"):
        validate(doc)


def test_settings_read_from_a_document() -> None:
    doc = load_results(BENCH / "dambreak/default/m8/placement.json.gz")
    settings = run_settings(doc)
    assert settings["n_sensors"] == 8 and settings["noise_seeds"] == [0] and settings["data_preset"] == "paper"
    assert record_settings(doc, doc["records"][0]) == {"noise_level": 0.2, "initial": "approximate",
                                                       "trajectories": "all"}


def test_reproduce_refuses_to_extend_a_file_of_another_protocol_version(tmp_path: Path) -> None:
    from dks_gym.evaluation.reproduce import _previous

    doc = load_results(RESULTS / "burgers-lite-calibrated" / "results.json.gz")
    assert _previous(RESULTS / "burgers-lite-calibrated" / "results.json.gz", "burgers", "lite", doc["dataset"])
    doc["protocol"]["version"] = 2
    path = save_results(doc, tmp_path / "results.json.gz")
    with pytest.raises(ResultsError, match="protocol dks-v1 v2, not dks-v1 v1"):
        _previous(path, "burgers", "lite", doc["dataset"])
