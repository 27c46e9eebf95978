"""The report skips, in one line naming the run and what is wrong, every ``results.json`` that is not a
finished run's results, and reports the others (in this process: tests/cli.py)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from spoil_torchrl.reporting.experiments import load_experiment
from tests.cli import run_command
from tests.test_command_errors import _results_json

ROOT = Path(__file__).resolve().parents[1]

#: folder name -> (the results.json written there, what its "skipped" line says)
ODD_FILES = {
    "a_list": ("[1, 2]", "holds a list, not a JSON object"),
    "a_number": ("3", "holds a number, not a JSON object"),
    "no_status": (json.dumps({"dataset": "d", "algo": "bc", "seed": 1}), "no status in its results.json"),
    "no_aggregate": (
        json.dumps({"status": "finished", "dataset": "d", "algo": "bc", "seed": 1, "total_seconds": 1.0}),
        "finished, but its results.json has no aggregate, evaluations",
    ),
    "an_expert": (
        json.dumps({"status": "finished", "config": {}, "frames": 100}),
        "has no dataset, algo, seed, aggregate",
    ),
    "aggregate_without_cost": (
        json.dumps(
            {
                "status": "finished",
                "dataset": "d",
                "algo": "bc",
                "seed": 3,
                "aggregate": {"normalized_feasible_return": 0.5, "normalized_return": 0.5},
                "evaluations": [],
                "total_seconds": 1.0,
            }
        ),
        "its aggregate has no normalized_cost",
    ),
    "aggregate_a_list": (
        json.dumps(
            {
                "status": "finished",
                "dataset": "d",
                "algo": "bc",
                "seed": 2,
                "aggregate": [],
                "evaluations": [],
                "total_seconds": 1.0,
            }
        ),
        "aggregate is not a mapping",
    ),
}


def _odd_runs(folder: Path) -> None:
    for name, (text, _) in ODD_FILES.items():
        (folder / name).mkdir(parents=True)
        (folder / name / "results.json").write_text(text)


def test_the_report_skips_what_is_not_a_finished_run_and_reports_the_rest(tmp_path):
    _results_json(tmp_path / "good", 0)
    _odd_runs(tmp_path)
    ran = run_command(["recipes/report.py", str(tmp_path)], cwd=ROOT)
    assert ran.returncode == 0, ran.stderr[-2000:]
    assert "Traceback" not in ran.stderr
    assert "| 1 |" in ran.stdout  # the one good seed is reported
    skipped = [line for line in ran.stderr.splitlines() if line.startswith("skipped ")]
    assert len(skipped) == len(ODD_FILES), ran.stderr
    for name, (_, reason) in ODD_FILES.items():
        assert any(line.startswith(f"skipped {tmp_path / name}: ") and reason in line for line in skipped), (
            name
        )


@pytest.mark.parametrize("name", list(ODD_FILES))
def test_an_odd_results_file_alone_ends_the_report_in_one_line(tmp_path, name):
    text, reason = ODD_FILES[name]
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "results.json").write_text(text)
    ran = run_command(["recipes/report.py", str(tmp_path)], cwd=ROOT)
    assert ran.returncode == 1 and "Traceback" not in ran.stderr, ran.stderr[-2000:]
    assert f"skipped {tmp_path / 'run'}: " in ran.stderr and reason in ran.stderr
    assert "no finished results.json" in ran.stderr


def test_an_experiment_leaves_odd_results_files_out(tmp_path):
    _odd_runs(tmp_path)
    skipped: list = []
    with pytest.raises(ValueError, match="no finished cell of an experiment"):
        load_experiment([tmp_path], skipped=skipped)
    by_reason = {path.parent.name: reason for path, reason in skipped}
    assert sorted(by_reason) == sorted(ODD_FILES)  # each one skipped, none taken as a cell
    assert by_reason["no_aggregate"].startswith("finished, but its results.json has no aggregate")
    assert by_reason["an_expert"].startswith("finished, but its results.json has no dataset, algo, seed")
    assert "not a mapping" in by_reason["aggregate_a_list"]
    assert by_reason["aggregate_without_cost"].startswith("not a cell of an experiment")
