"""Run folders: a bad output place is found before any work, and a write that fails (a full
disk) leaves nothing behind and says why in one line."""

import errno

import pytest

import mapex.results as results
from mapex.config import ExplorationConfig
from mapex.episode import run_episode
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
    (out / "stale.txt").write_text("old")
    write_results(*short_run, out)
    assert not (out / "stale.txt").exists() and (out / results.METRICS_FILE).is_file()
    assert [p.name for p in tmp_path.iterdir()] == ["run"]
