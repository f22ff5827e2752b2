"""Run folders: a bad output place is found before any work, and a write that fails (a full
disk) leaves nothing behind and says why in one line."""

import errno

import numpy as np
import pytest

import mapex.results as results
from mapex.config import ExplorationConfig
from mapex.episode import run_episode
from mapex.prediction import make_predictor
from mapex.results import OutputError, check_output_folder, check_run_folder, write_results
from mapex.worlds import load_world


@pytest.fixture(scope="module")
def short_run():
    world = load_world("generated:2")
    return run_episode(world, "nearest", None, 0, 0, ExplorationConfig(steps=20)), world


def test_output_folder_is_created_and_left_clean(tmp_path):
    folder = check_output_folder(tmp_path / "a" / "b")
    assert folder.is_dir() and list(folder.iterdir()) == []


@pytest.mark.parametrize("check", [check_output_folder, check_run_folder])
def test_a_file_in_the_way_is_a_one_line_error(tmp_path, check):
    (tmp_path / "taken").write_text("a file")
    with pytest.raises(OutputError, match="cannot write results to .*taken") as info:
        check(tmp_path / "taken")
    assert "\n" not in str(info.value)


def test_a_folder_under_a_file_is_a_one_line_error(tmp_path):
    (tmp_path / "taken").write_text("a file")
    with pytest.raises(OutputError, match="cannot write results to") as info:
        check_run_folder(tmp_path / "taken" / "run")
    assert "\n" not in str(info.value)


def test_a_full_disk_leaves_no_staging_and_no_run(tmp_path, short_run, monkeypatch):
    def full_disk(*_):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(results, "_write_snapshots", full_disk)
    with pytest.raises(OutputError, match="No space left on device") as info:
        write_results(*short_run, tmp_path / "run")
    assert "\n" not in str(info.value)
    assert list(tmp_path.iterdir()) == []


def test_a_run_folder_replaces_an_older_one_whole(tmp_path, short_run):
    out = tmp_path / "run"
    out.mkdir()
    (out / results.SNAPSHOTS_FILE).write_text("an older run's")
    (out / results.METRICS_FILE).write_text("{}")
    write_results(*short_run, out)
    assert not (out / results.SNAPSHOTS_FILE).read_bytes().startswith(b"an older")
    assert (out / results.CURVES_FILE).is_file()
    assert [p.name for p in tmp_path.iterdir()] == ["run"]


def test_a_folder_holding_anything_else_is_refused_and_left_as_it_was(tmp_path, short_run):
    """`mapex run --out d` once deleted what d held (another run's results folder, a note)."""
    out = tmp_path / "d"
    (out / "x").mkdir(parents=True)
    (out / "n").write_text("mine")
    (out / results.METRICS_FILE).write_text("{}")
    with pytest.raises(OutputError, match=r"holds what is not a run's folder \(n, x\)") as info:
        write_results(*short_run, out)
    assert "\n" not in str(info.value)
    assert sorted(p.name for p in out.iterdir()) == [results.METRICS_FILE, "n", "x"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d"]  # no staging left


def test_every_run_records_its_path_length_and_idle_steps(short_run):
    result, world = short_run
    record = results.summary(result)
    expected = float(np.hypot(*np.diff(result.trajectory, axis=0).T).sum()) * world.resolution_m
    assert record["path_length_m"] == pytest.approx(expected, abs=0.01) and expected > 0
    still = int((np.diff(result.trajectory, axis=0) == 0).all(axis=1).sum())
    assert record["idle_steps"] == [still]
    assert record["reached"]["coverage"].keys() == {"0.8", "0.9", "0.95"}


def test_a_team_s_path_length_is_every_robot_s_summed():
    world = load_world("generated:2")
    result = run_episode(world, "nearest", None, 0, 0, ExplorationConfig(steps=20), robots=2)
    record = results.summary(result)
    assert record["path_length_m"] == pytest.approx(sum(result.path_lengths_m), abs=0.01)
    assert len(record["idle_steps"]) == 2 and record["team"]["robots"] == 2


@pytest.mark.parametrize(
    ("method", "predictor", "label"),
    [
        ("mapex", "oracle", "mapex@oracle"),
        ("mapex_team", "lama-v2", "mapex_team@lama-v2"),
        ("mapex", "classical", "mapex@classical"),
        ("mapex", "lama", "mapex"),  # the default keeps today's names
        ("mapex", "zenoh", "mapex"),  # what distributed runs recorded before
        ("mapex", None, "mapex"),
        ("nearest", "oracle", "nearest@oracle"),  # the same run, but the oracle's IoU and TU
        ("observed_map", "oracle", "observed_map@oracle"),
        ("pw_nbv", "lama-v2", "pw_nbv@lama-v2"),
        ("mapex_plus_observed", None, "mapex_plus_observed"),
    ],
)
def test_a_method_is_labelled_with_its_predictor_unless_the_default(method, predictor, label):
    assert results.method_label(method, predictor) == label
    assert results.episode_name("generated:0", method, 1, 0, 1, predictor) == (
        f"generated_0-{label}-start1-seed0" + ("-team1" if method == "mapex_team" else "")
    )


def test_runs_of_two_predictors_get_two_folders():
    world = load_world("generated:2")
    config = ExplorationConfig(steps=10)
    oracle = run_episode(world, "mapex", make_predictor("oracle", world.occupancy), 0, 0, config)
    classical = run_episode(world, "mapex", make_predictor("classical"), 0, 0, config)
    assert results.run_name(oracle) == "generated_2-mapex@oracle-start0-seed0"
    assert results.run_name(classical) == "generated_2-mapex@classical-start0-seed0"
    assert results.summary(oracle)["predictor"] == "oracle"
