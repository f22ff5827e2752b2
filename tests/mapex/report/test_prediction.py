"""The prediction report: each method beside its twin under the same predictor, the oracle on
coverage only, and each predictor against the reference, paired episode by episode."""

from __future__ import annotations

import json

import pytest
from run_folders import write_run

from mapex.report.prediction import main, report_json


def write_campaign(root) -> None:
    """Two worlds x two starts: mapex and its twin under lama-v2 and lama, mapex under the
    oracle. mapex gains 0.02 coverage over its twin under lama, loses 0.01 under lama-v2;
    the oracle gains 0.05; lama's IoU is 0.1 above lama-v2's for both."""
    for world in ("a", "b"):
        for start in (0, 1):
            jitter = 0.001 * start  # episodes differ, the differences do not
            for predictor, gain, iou in (("lama-v2", -0.01, 0.4), ("lama", 0.02, 0.5)):
                write_run(root, world, "observed_map", start, cov=0.6 + jitter, iou=iou,
                          predictor=predictor)  # fmt: skip
                write_run(root, world, "mapex", start, cov=0.6 + jitter + gain, iou=iou + 0.01,
                          predictor=predictor)  # fmt: skip
            write_run(root, world, "mapex", start, cov=0.65 + jitter, iou=1.0, predictor="oracle")


def test_methods_pair_with_their_twin_and_the_reference(tmp_path, capsys):
    write_campaign(tmp_path / "runs")
    assert main([str(tmp_path / "runs"), "--json", str(tmp_path / "p.json")]) == 0
    figures = json.loads((tmp_path / "p.json").read_text())
    twins = {(r["method"], r["predictor"]): r for r in figures["twins"]}
    assert set(twins) == {("mapex", "lama"), ("mapex", "lama-v2"), ("mapex", "oracle")}
    assert twins[("mapex", "lama")]["difference"]["coverage"]["mean"] == pytest.approx(0.02)
    assert twins[("mapex", "lama-v2")]["difference"]["coverage"]["mean"] == pytest.approx(-0.01)
    assert twins[("mapex", "lama")]["difference"]["iou"]["mean"] == pytest.approx(0.01)
    oracle = twins[("mapex", "oracle")]
    assert oracle["difference"]["coverage"]["mean"] == pytest.approx(0.05)
    assert oracle["difference"]["iou"]["mean"] is None  # the truth's IoU: not compared
    assert oracle["episodes"] == 4 and oracle["against"] == "observed_map"
    against = {(r["method"], r["predictor"]): r for r in figures["against_reference"]}
    assert against[("mapex", "lama")]["difference"]["iou"]["mean"] == pytest.approx(0.1)
    assert against[("observed_map", "lama")]["difference"]["coverage"]["mean"] == pytest.approx(0)
    text = capsys.readouterr().out
    assert "| `mapex` | `lama` | 4 |" in text and "+0.020 ± 0.000" in text


def test_only_common_episodes_are_paired(tmp_path):
    write_campaign(tmp_path / "runs")
    write_run(tmp_path / "runs", "c", "mapex", 0, cov=0.9, predictor="lama")  # no twin run
    from mapex.report.runs import load_folders

    figures = report_json(load_folders([tmp_path / "runs"]), "lama-v2")
    row = next(r for r in figures["twins"] if r["predictor"] == "lama")
    assert row["episodes"] == 4
    assert row["difference"]["coverage"]["mean"] == pytest.approx(0.02)


@pytest.mark.parametrize("setup", ["empty", "no_twins", "missing"])
def test_nothing_to_compare_is_one_line(tmp_path, capsys, setup):
    root = tmp_path / "runs"
    root.mkdir()
    if setup == "no_twins":
        write_run(root, "a", "nearest", 0)
    target = root if setup != "missing" else tmp_path / "none"
    assert main([str(target)]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and error[0].startswith("mapex.report.prediction: ")


def test_a_predictor_whose_twin_ran_under_another_is_compared_on_coverage_only(tmp_path):
    write_campaign(tmp_path / "runs")
    for world in ("a", "b"):
        for start in (0, 1):
            write_run(tmp_path / "runs", world, "mapex", start, cov=0.63 + 0.001 * start,
                      iou=0.7, predictor="lama-v3")  # fmt: skip
    from mapex.report.runs import load_folders

    figures = report_json(load_folders([tmp_path / "runs"]), "lama-v2")
    row = next(r for r in figures["twins"] if r["predictor"] == "lama-v3")
    assert row["against"] == "observed_map" and row["episodes"] == 4
    assert row["difference"]["coverage"]["mean"] == pytest.approx(0.03)
    assert row["difference"]["iou"]["mean"] is None  # the twin's IoU is another G's
