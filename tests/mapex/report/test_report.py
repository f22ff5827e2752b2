"""The evaluation report: AUC table, relative improvements, figures and the command line,
on small synthetic results folders written in the format of mapex.results."""

import json
import math
import shutil
import subprocess
import sys

import numpy as np
import pytest
from run_folders import SHAPE, write_run

from mapex.methods import ABLATIONS, BEYOND_PAPER, FOLLOW_UP, MAIN_COMPARISON
from mapex.report import (
    auc_table,
    choose_snapshot_runs,
    load_folders,
    load_runs,
    load_snapshots,
    load_trajectories,
    main,
    mean_curve,
    missing_runs,
    order_methods,
    plot_snapshots,
    relative_improvement,
    relative_improvements,
    write_report,
)
from mapex.report.config import ReportConfig
from mapex.report.runs import RunRecord
from mapex.results import CAMPAIGN_FILE, campaign_record


@pytest.fixture
def results(tmp_path):
    """Two worlds, two starts; MapEx, Nearest (no predictor snapshot) and UPEN."""
    root = tmp_path / "results"
    write_run(root, "generated:1", "mapex", 0, cov=0.6, iou=0.5, tu=0.4)
    write_run(root, "generated:1", "mapex", 1, cov=0.8, iou=0.7, tu=0.6, degraded=[5, 6])
    write_run(root, "generated:2", "mapex", 0, cov=0.7, iou=0.3, tu=0.5)
    write_run(root, "generated:1", "nearest", 0, cov=0.5, iou=0.4, tu=0.5, prediction=False)
    write_run(root, "generated:1", "nearest", 1, cov=0.4, iou=0.4, tu=0.3, early=True)
    write_run(
        root, "generated:2", "nearest", 0, cov=0.6, iou=0.4, tu=0.4, degraded=[], early=True,
        end_reason="unreachable",
    )  # fmt: skip
    write_run(root, "generated:1", "upen", 1, cov=0.7, iou=0.5, tu=0.0)
    return root


def test_auc_table_means_and_standard_errors(results):
    table = auc_table(load_runs(results))
    assert table.methods == ("nearest", "upen", "mapex")
    mapex = table.row("mapex")
    assert (mapex.runs, mapex.early_terminations, mapex.degraded_runs) == (3, 0, 1)
    # coverage 0.6, 0.8, 0.7: mean 0.7, sd 0.1, SE 0.1 / sqrt(3)
    assert mapex.auc["coverage"].mean == pytest.approx(0.7)
    assert mapex.auc["coverage"].se == pytest.approx(0.1 / math.sqrt(3))
    assert mapex.auc["iou"].mean == pytest.approx(0.5)
    assert mapex.auc["iou"].se == pytest.approx(0.2 / math.sqrt(3))
    nearest = table.row("nearest")
    assert (nearest.runs, nearest.early_terminations, nearest.degraded_runs) == (3, 2, 0)
    assert (nearest.explored_ends, nearest.unreachable_ends) == (1, 1)
    assert nearest.auc["coverage"].mean == pytest.approx(0.5)
    assert nearest.auc["tu"].se == pytest.approx(0.1 / math.sqrt(3))
    upen = table.row("upen")
    assert upen.auc["coverage"].n == 1 and math.isnan(upen.auc["coverage"].se)
    # per world: generated:1 mapex = starts 0 and 1 only, SE of two values = half their gap
    world = {r.method: r for r in table.by_world["generated:1"]}
    assert world["mapex"].auc["coverage"].mean == pytest.approx(0.7)
    assert world["mapex"].auc["coverage"].se == pytest.approx(0.1)
    assert [r.method for r in table.by_world["generated:2"]] == ["nearest", "mapex"]


def test_relative_improvement_formula(results):
    assert relative_improvement(0.6, 0.5) == pytest.approx(20.0)
    assert relative_improvement(0.4, 0.5) == pytest.approx(-20.0)
    assert math.isnan(relative_improvement(0.5, 0.0))
    improvements = relative_improvements(auc_table(load_runs(results)))
    assert list(improvements) == ["nearest", "upen"]
    nearest = improvements["nearest"]
    assert nearest["coverage"] == pytest.approx((0.7 - 0.5) / 0.5 * 100)
    assert nearest["iou"] == pytest.approx((0.5 - 0.4) / 0.4 * 100)
    assert nearest["tu"] == pytest.approx((0.5 - 0.4) / 0.4 * 100)
    assert nearest["mean"] == pytest.approx((40 + 25 + 25) / 3)
    upen = improvements["upen"]  # TU AUC 0: no ratio, left out of the mean
    assert math.isnan(upen["tu"])
    assert upen["mean"] == pytest.approx(np.mean([0.0, 0.0]))
    assert relative_improvements(auc_table(load_runs(results)), reference="absent") == {}


def test_staging_and_broken_folders(results, capsys):
    write_run(results / ".staging", "generated:9", "mapex")  # lives at .staging/<run>
    staged = write_run(results, "generated:9", "mapex", start=3)
    staged.rename(results / ".generated_9-mapex-start3-seed0.abc")
    broken = results / "broken-run"
    broken.mkdir()
    (broken / "metrics.json").write_text("{not json")
    runs = load_runs(results)
    assert len(runs) == 7 and "generated:9" not in {r.world for r in runs}
    warnings = capsys.readouterr().err.strip().splitlines()
    assert len(warnings) == 1 and "broken-run" in warnings[0]


def test_method_order():
    order = ReportConfig().method_order
    assert order == MAIN_COMPARISON + ABLATIONS + BEYOND_PAPER + FOLLOW_UP
    assert order[:4] == ("nearest", "upen", "ig_hector", "mapex")
    assert order[4:8] == ("deterministic", "no_variance", "observed_map", "no_visibility")
    assert order[8:] == ("mapex_path", "mapex_plus", "mapex_plus_observed", "pipe", "pw_nbv")
    shuffled = ["zeta", "no_visibility", "mapex", "alpha", "deterministic", "nearest", "upen"]
    assert order_methods(shuffled, order) == [
        "nearest",
        "upen",
        "mapex",
        "deterministic",
        "no_visibility",
        "alpha",
        "zeta",
    ]


def test_mean_curve_with_bands(tmp_path):
    write_run(tmp_path, "w", "mapex", 0, cov=0.2, tu=0.1)
    write_run(tmp_path, "w", "mapex", 1, cov=0.4, tu=0.5, steps=100)
    runs = load_runs(tmp_path)
    coverage = mean_curve(runs, "coverage")
    assert coverage.steps.tolist() == [0, 50, 100, 150, 200]
    np.testing.assert_allclose(coverage.mean, [0.3, 0.3, 0.3, 0.2, 0.2])
    np.testing.assert_allclose(coverage.se[:3], 0.1)
    assert np.isnan(coverage.se[3:]).all()  # one run only past step 100
    tu = mean_curve(runs, "tu")
    assert tu.steps.tolist() == [0, 100, 200]
    np.testing.assert_allclose(tu.mean, [0.3, 0.3, 0.1])


def test_snapshot_runs_share_world_and_start(tmp_path):
    write_run(tmp_path, "a", "mapex", 0)
    write_run(tmp_path, "a", "nearest", 0)
    write_run(tmp_path, "b", "nearest", 2)
    write_run(tmp_path, "b", "mapex", 2, seed=1)
    write_run(tmp_path, "b", "mapex", 2, seed=0)
    write_run(tmp_path, "b", "upen", 2)
    write_run(tmp_path, "b", "upen", 3, snapshots=False)
    runs = load_runs(tmp_path)
    chosen = choose_snapshot_runs(runs, ReportConfig().method_order)
    assert [(r.method, r.world, r.start, r.seed) for r in chosen] == [
        ("nearest", "b", "start2", 0),
        ("upen", "b", "start2", 0),
        ("mapex", "b", "start2", 0),
    ]
    pick = next(r for r in runs if r.world == "a")
    picked = choose_snapshot_runs(runs, ReportConfig().method_order, pick)
    assert [(r.method, r.world) for r in picked] == [("nearest", "a"), ("mapex", "a")]


def is_png(path):
    return path.is_file() and path.stat().st_size > 100 and path.read_bytes()[:4] == b"\x89PNG"


def test_write_report_files_and_numbers(results, tmp_path):
    runs = load_runs(results)
    files, summary = write_report(runs, tmp_path / "out", warn=lambda m: None)
    names = sorted(p.name for p in files.figures)
    assert names == ["curves-generated_1.png", "curves-generated_2.png", "curves.png"] + [
        "snapshots.png"
    ]
    assert all(is_png(p) for p in files.figures)
    data = json.loads(files.json.read_text())
    assert list(data["methods"]) == ["nearest", "upen", "mapex"]
    assert data["methods"]["mapex"]["auc"]["coverage"]["mean"] == pytest.approx(0.7)
    assert data["methods"]["upen"]["auc"]["coverage"]["se"] is None
    assert data["improvements"]["over"]["nearest"]["coverage"] == pytest.approx(40.0)
    assert data["run_counts"]["generated:1"] == {"nearest": 2, "upen": 1, "mapex": 2}
    assert data["run_counts"]["generated:2"]["upen"] == 0
    assert data["by_world"]["generated:2"]["mapex"]["runs"] == 1
    assert data["snapshot_steps"] == [200]  # 500 and 1000 not reached by any run
    assert data["snapshot_runs"][0].startswith(
        "generated_1-nearest-start1"
    )  # upen has start 1 only
    markdown = files.markdown.read_text()
    assert "| mapex | 3 | 0 (0 / 0 / 0) | 1 | 0.700 ± 0.058 |" in markdown
    assert "| nearest | 3 | 2 (1 / 1 / 0) | 0 |" in markdown
    assert data["methods"]["nearest"]["early_ends_by_reason"] == {
        "explored": 1,
        "unreachable": 1,
        "iou_reached": 0,
    }
    assert "| nearest | +40.0 % | +25.0 % | +25.0 % | +30.0 % |" in markdown
    assert "| generated:1 | 2 | 1 | 2 | 5 |" in markdown
    assert markdown.index("| nearest |") < markdown.index("| upen |") < markdown.index("| mapex")
    assert "0.700 ± 0.058" in summary and "+40.0 %" in summary


def test_a_report_failing_on_a_full_disk_leaves_the_old_files_whole(results, tmp_path, monkeypatch):
    import errno

    from matplotlib.figure import Figure

    runs, out = load_runs(results), tmp_path / "out"
    files, _ = write_report(runs, out, warn=lambda m: None)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    saved = Figure.savefig

    def full_disk(self, path, *args, **kwargs):
        if "generated_2" in str(path):  # the third figure: the first two are replaced
            saved(self, path, *args, **kwargs)
            raise OSError(errno.ENOSPC, "No space left on device")
        return saved(self, path, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", full_disk)
    with pytest.raises(OSError, match="No space left"):
        write_report(runs, out, warn=lambda m: None)
    after = {p.name: p.read_bytes() for p in out.iterdir()}
    assert sorted(after) == sorted(before)  # no partial file left behind
    assert after["curves-generated_2.png"] == before["curves-generated_2.png"]
    assert is_png(files.figures[0]) and json.loads(files.json.read_text())


def test_teams_of_different_sizes_are_rows_of_their_own(tmp_path):
    for robots, cov in ((2, 0.6), (4, 0.8)):
        folder = write_run(tmp_path / "r", "generated:1", "mapex_team", cov=cov)
        metrics = json.loads((folder / "metrics.json").read_text())
        metrics["team"] = {"robots": robots}
        (folder / "metrics.json").write_text(json.dumps(metrics))
        folder.rename(folder.with_name(f"{folder.name}-team{robots}"))
    write_run(tmp_path / "r", "generated:1", "mapex", cov=0.5)
    table = auc_table(load_runs(tmp_path / "r"), ["mapex"])
    assert [row.method for row in table.rows] == ["mapex", "mapex_team x2", "mapex_team x4"]


def write_team_run(root, method, robots, overlap, start=0):
    """A team run: write_run's folder with the team entry and every robot's trajectory
    (robot k walks along row 3 + k, one cell per step, for 200 steps)."""
    folder = write_run(root, "generated:1", method, start=start)
    metrics = json.loads((folder / "metrics.json").read_text())
    metrics["team"] = {
        "robots": robots, "overlap": overlap, "path_length_m": [20.0 + k for k in range(robots)],
        "lost_at": {"1": 120} if robots > 2 else {},
    }  # fmt: skip
    (folder / "metrics.json").write_text(json.dumps(metrics))
    rows = [f"{t},{k},{3 + k},{min(t, SHAPE[1] - 1)}" for t in range(201) for k in range(robots)]
    (folder / "trajectories.csv").write_text("step,robot,row,col\n" + "\n".join(rows) + "\n")
    return folder.rename(folder.with_name(f"{folder.name}-team{robots}"))


def test_team_runs_get_a_team_table_and_a_figure_of_every_robots_path(tmp_path):
    root = tmp_path / "r"
    write_run(root, "generated:1", "mapex")
    write_team_run(root, "mapex_team", 2, 0.6)
    write_team_run(root, "mapex_team", 2, 0.8, start=1)
    write_team_run(root, "mapex_independent", 2, 0.9)
    write_team_run(root, "mapex_team", 4, 0.7)
    runs = load_runs(root)
    files, _ = write_report(runs, tmp_path / "out")
    report = (tmp_path / "out" / "report.md").read_text()
    assert "| mapex_team x2 | 2 | 0.700 ± 0.100 | 20 |" in report
    assert "| mapex_team x4 | 1 | 0.700 | 22 | 1 |" in report  # one run with a lost robot
    data = json.loads((tmp_path / "out" / "report.json").read_text())
    assert data["teams"]["mapex_independent x2"]["overlap"]["mean"] == 0.9
    assert len(data["team_snapshot_runs"]) == 3  # one run per team method, on one start
    assert (
        is_png(tmp_path / "out" / "teams.png") and tmp_path / "out" / "teams.png" in files.figures
    )
    team = next(r for r in runs if r.method == "mapex_team x4")
    paths = load_trajectories(team, until_step=100)
    assert len(paths) == 4 and paths[3].shape == (101, 2) and tuple(paths[3][-1]) == (6, 17)


def test_team_runs_shorter_than_any_snapshot_still_get_their_figure(tmp_path):
    folder = write_team_run(tmp_path / "r", "mapex_team", 2, 0.5)
    empty = np.zeros(0, np.uint8)  # what mapex.results writes when no snapshot step was reached
    np.savez_compressed(folder / "snapshots.npz", steps=np.zeros(0, np.int64), observed=empty)
    files, _ = write_report(load_runs(tmp_path / "r"), tmp_path / "out", warn=lambda _: None)
    assert is_png(tmp_path / "out" / "teams.png")


def test_single_robot_reports_have_no_team_part(results, tmp_path):
    write_report(load_runs(results), tmp_path / "out")
    assert "## Teams" not in (tmp_path / "out" / "report.md").read_text()
    assert not (tmp_path / "out" / "teams.png").exists()


def test_mixed_budgets_are_flagged(tmp_path):
    write_run(tmp_path / "r", "w", "mapex", 0, steps=200)
    write_run(tmp_path / "r", "w", "nearest", 0, steps=100)
    notes = []
    files, _ = write_report(load_runs(tmp_path / "r"), tmp_path / "out", warn=notes.append)
    assert any("time budgets" in n for n in notes)
    assert "time budgets" in files.markdown.read_text()


def test_cli_writes_report_to_default_folder(results, capsys):
    pick = "generated_2-mapex-start0-seed0"
    assert main([str(results), "--snapshot-run", pick, "--allow-missing"]) == 0
    out = results / "report"
    assert (out / "report.md").is_file() and is_png(out / "snapshots.png")
    data = json.loads((out / "report.json").read_text())
    assert [name.split("-")[0] for name in data["snapshot_runs"]] == ["generated_2"] * 2
    stdout = capsys.readouterr().out
    assert "| method | runs |" in stdout and "report.md" in stdout
    assert main([str(results), "--allow-missing"]) == 0  # the report folder is not a run
    assert "skipping" not in capsys.readouterr().err


def test_missing_runs_are_every_method_on_every_world_start_and_seed(results):
    assert missing_runs(load_runs(results)) == [
        "generated_1-upen-start0-seed0",
        "generated_2-upen-start0-seed0",
    ]


def test_a_missing_team_run_is_named_as_its_folder_would_be(tmp_path):
    """A team's run is labelled `mapex_team x2` but lives in `...-seed0-team2`."""
    team = {"robots": 2, "overlap": 0.5}
    runs = [
        RunRecord(tmp_path / name, {"world": "generated:1", "method": method,
                                    "start_index": start, "seed": 0, "team": team}, *[None] * 4)
        for name, method, start in (("a", "mapex_team", 0), ("b", "mapex_team", 1),
                                    ("c", "mapex_assign", 0))
    ]  # fmt: skip
    assert missing_runs(runs) == ["generated_1-mapex_assign-start1-seed0-team2"]


def test_a_report_with_missing_or_broken_runs_is_refused_unless_allowed(results, capsys):
    (results / "generated_1-mapex-start1-seed0" / "curves.csv").unlink()
    assert main([str(results)]) == 2
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert "3 run(s) missing or unreadable" in error and "--allow-missing" in error
    assert not (results / "report").exists()
    assert main([str(results), "--allow-missing"]) == 0
    text = (results / "report" / "report.md").read_text()
    assert "reported without 3 missing or unreadable run(s)" in text
    assert "generated_1-mapex-start1-seed0 (unreadable)" in text
    assert "generated_2-upen-start0-seed0" in text


def run_cli(*args):
    return subprocess.run(
        [sys.executable, "-m", "mapex.report", *args], capture_output=True, text=True, timeout=120
    )


@pytest.mark.slow  # runs the command in a process of its own
def test_cli_errors(tmp_path, capsys):
    empty = tmp_path / "empty"
    (empty / ".staging-run").mkdir(parents=True)
    assert main([str(empty)]) == 2
    assert "no finished runs" in capsys.readouterr().err
    write_run(tmp_path / "r", "w", "mapex")
    assert main([str(tmp_path / "r"), "--snapshot-run", "nosuch"]) == 2
    assert "nosuch" in capsys.readouterr().err
    done = run_cli(str(tmp_path / "missing"))
    assert done.returncode == 2 and "Traceback" not in done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "missing" in lines[0] and "does not exist" in lines[0]


@pytest.mark.slow  # runs the command in a process of its own
def test_cli_help():
    done = run_cli("--help")
    assert done.returncode == 0 and "RESULTS_DIR" in done.stdout and "--snapshot-run" in done.stdout


def test_snapshots_without_prediction_or_file(tmp_path):
    write_run(tmp_path / "r", "w", "nearest", prediction=False)
    write_run(tmp_path / "r", "w", "mapex")
    runs = load_runs(tmp_path / "r")
    pairs = [(runs[0], None), (runs[1], load_snapshots(runs[1]))]
    assert pairs[1][1].prediction is None and pairs[1][1].at(200) is not None
    assert pairs[1][1].at(500) is None
    steps = plot_snapshots(tmp_path / "s.png", pairs, ReportConfig(snapshot_steps=(100, 300)))
    assert steps == (100,) and is_png(tmp_path / "s.png")


# ---------------------------------------------------------------- merging shards' folders


def split_into_shards(results, root, count: int = 3) -> list:
    """The run folders of `results` dealt over `count` new folders, as shards write them."""
    shards = [root / f"shard-{k}" for k in range(count)]
    for k, run in enumerate(sorted(p for p in results.iterdir() if p.is_dir())):
        shards[k % count].mkdir(parents=True, exist_ok=True)
        shutil.copytree(run, shards[k % count] / run.name)
    return shards


def test_the_merged_shards_report_what_one_folder_of_them_all_does(results, tmp_path):
    shards = split_into_shards(results, tmp_path)
    assert main([str(results), "--allow-missing"]) == 0
    assert main([*map(str, shards), "--out", str(tmp_path / "merged"), "--allow-missing"]) == 0
    whole = json.loads((results / "report" / "report.json").read_text())
    assert json.loads((tmp_path / "merged" / "report.json").read_text()) == whole
    whole_md = (results / "report" / "report.md").read_text()
    assert (tmp_path / "merged" / "report.md").read_text() == whole_md


def test_an_episode_in_two_folders_counts_once_when_its_records_agree(results, tmp_path):
    name, twin = "generated_1-mapex-start0-seed0", tmp_path / "twin"
    shutil.copytree(results / name, twin / name)
    metrics_path = twin / name / "metrics.json"
    metrics = json.loads(metrics_path.read_text())  # run again: other time, other workers
    metrics |= {"wall_time_s": 9.5, "member_workers": {"replans": [[0, ["ev7-g-0"]]]}}
    metrics_path.write_text(json.dumps(metrics))
    runs = load_folders([results, twin])
    assert [r.name for r in runs] == [r.name for r in load_runs(results)]
    assert runs[0].path.parent == results  # the first folder's is kept


@pytest.mark.parametrize(
    ("change", "field"),
    [({"auc": {"coverage": 0.61, "iou": 0.5, "tu": 0.4}}, "auc.coverage (0.61, not 0.6)"),
     ({"replans": 4}, "replans (4, not 3)"), ({"extra": 1}, "the fields they hold")],
)  # fmt: skip
def test_an_episode_in_two_folders_with_different_records_is_refused(
    results, tmp_path, capsys, change, field
):
    name = "generated_1-mapex-start0-seed0"
    shutil.copytree(results / name, tmp_path / "other" / name)
    metrics = json.loads((tmp_path / "other" / name / "metrics.json").read_text()) | change
    (tmp_path / "other" / name / "metrics.json").write_text(json.dumps(metrics))
    out = tmp_path / "merged"
    assert main([str(results), str(tmp_path / "other"), "--out", str(out), "--allow-missing"]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and name in error[0] and field in error[0]
    assert str(results) in error[0] and str(tmp_path / "other") in error[0]
    assert not out.exists()


def write_campaign(folder, names: list[str], shards: int = 3) -> None:
    record = campaign_record(dict.fromkeys(names, 200), {}, shards)
    (folder / CAMPAIGN_FILE).write_text(json.dumps(record))


def test_missing_episodes_are_the_ones_a_campaign_lists_and_no_folder_holds(tmp_path, capsys):
    shards = [tmp_path / "a", tmp_path / "b"]
    write_run(shards[0], "w", "mapex", 0)
    write_run(shards[1], "w", "nearest", 0)
    listed = ["w-mapex-start0-seed0", "w-nearest-start0-seed0", "w-nearest-start1-seed0"]
    for folder in shards:
        write_campaign(folder, listed)  # every shard lists every episode
    out = str(tmp_path / "merged")
    assert main([*map(str, shards), "--out", out]) == 2  # nearest start 1 never ran
    error = capsys.readouterr().err
    assert "1 run(s) missing" in error and "w-nearest-start1-seed0" in error
    assert main([*map(str, shards), "--out", out, "--allow-missing"]) == 0
    text = (tmp_path / "merged" / "report.md").read_text()
    assert "reported without 1 missing" in text and "w-nearest-start1-seed0" in text
    write_run(shards[1], "w", "nearest", 1)
    assert main([*map(str, shards), "--out", out]) == 2  # and now mapex on start 1 (inferred)
    assert "w-mapex-start1-seed0" in capsys.readouterr().err
    write_run(shards[0], "w", "mapex", 1)
    assert main([*map(str, shards), "--out", out]) == 0  # complete now


def test_merge_errors_are_one_line(tmp_path, capsys):
    write_run(tmp_path / "a", "w", "mapex")
    write_run(tmp_path / "b", "w", "nearest")
    assert main([str(tmp_path / "a"), str(tmp_path / "b")]) == 2
    assert "name the merged report's folder with --out" in capsys.readouterr().err
    assert main([str(tmp_path / "a"), str(tmp_path / "a")]) == 0  # one folder named twice
    (tmp_path / "b" / CAMPAIGN_FILE).write_text("{")
    assert main([str(tmp_path / "a"), str(tmp_path / "b"), "--out", str(tmp_path / "m")]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and CAMPAIGN_FILE in error[0] and "unreadable" in error[0]


def test_runs_of_other_predictors_are_labelled_apart_and_their_folders_found(tmp_path):
    """`mapex@oracle` and `mapex@lama-v2` beside the default's plain `mapex` (and an older
    distributed record's `zenoh`); a method that reads no prediction is labelled too (its
    IoU and TU are the predictor's)."""
    root = tmp_path / "results"
    write_run(root, "w", "mapex", 0, cov=0.6)
    write_run(root, "w", "mapex", 1, cov=0.6, predictor="zenoh")
    write_run(root, "w", "mapex", 0, cov=0.9, predictor="oracle")
    write_run(root, "w", "mapex", 0, cov=0.7, predictor="lama-v2")
    write_run(root, "w", "nearest", 0, cov=0.5, predictor="oracle")
    runs = load_runs(root)
    assert sorted(run.path.name for run in runs) == [
        "w-mapex-start0-seed0",
        "w-mapex-start1-seed0",
        "w-mapex@lama-v2-start0-seed0",
        "w-mapex@oracle-start0-seed0",
        "w-nearest@oracle-start0-seed0",
    ]
    table = auc_table(runs)
    assert set(table.methods) == {"mapex", "mapex@oracle", "mapex@lama-v2", "nearest@oracle"}
    assert table.row("mapex").runs == 2
    assert table.row("mapex@oracle").auc["coverage"].mean == pytest.approx(0.9)
    assert missing_runs(runs) == [  # named as their folders are
        "w-mapex@lama-v2-start1-seed0",
        "w-mapex@oracle-start1-seed0",
        "w-nearest@oracle-start1-seed0",
    ]
