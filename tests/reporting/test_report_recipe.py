"""``recipes/report.py`` (spoil-report) on finished runs the tests write themselves: tables, plots and learning
curves, and the runs it refuses to put together (a seed twice, other training settings, other data), and
outputs that must be the files the user named."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.cli import run_command

pytestmark = pytest.mark.runs

ROOT = Path(__file__).resolve().parents[2]


def _report_module():
    import importlib.util

    spec = importlib.util.spec_from_file_location("report", ROOT / "recipes" / "report.py")
    report = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(report)
    return report


def _finished_run(folder: Path, seed: int, fingerprint: str | None, name: str = "pc1-data") -> Path:
    metrics = {"normalized_feasible_return": 0.5, "normalized_cost": 0.5, "normalized_return": 0.6}
    results = {
        "status": "finished",
        "dataset": name,
        "algo": "bc",
        "seed": seed,
        "aggregate": metrics,
        "total_seconds": 60.0,
        "evaluations": [{"step": 100, **metrics}],
        "data": {"fingerprint": fingerprint},
    }
    folder.mkdir(parents=True)
    (folder / "results.json").write_text(json.dumps(results))
    return folder


def test_report_refuses_to_average_runs_of_different_data(tmp_path):
    report = _report_module()
    _finished_run(tmp_path / "a", 0, "aaaa")
    _finished_run(tmp_path / "b", 1, "aaaa")
    _finished_run(tmp_path / "legacy", 2, None)  # made before runs recorded their data: not checked
    assert len(report.load_runs([tmp_path])[("pc1-data", "bc")]) == 3
    _finished_run(tmp_path / "c", 3, "bbbb")
    with pytest.raises(ValueError, match="trained on different data.*data aaaa.*data bbbb"):
        report.load_runs([tmp_path])


def test_report_tables_and_plots_finished_runs(tmp_path):
    def run(folder, algo, seed, feasible, cost, status="finished"):
        diagnostics = {"variance_share": {"bellman": 0.1 * seed}, "weight_share": {"cost>0": {"weight": 0.2}}}
        results = {
            "dice_diagnostics": diagnostics if algo == "spoildice" else None,
            "algo": algo,
            "dataset": "d",
            "seed": seed,
            "status": status,
            "total_seconds": 60.0,
            "evaluations": [
                {"step": step, "normalized_feasible_return": feasible * f, "normalized_cost": cost * f}
                for step, f in ((100, 0.5), (200, 1.0))
            ],
            "aggregate": {
                "normalized_feasible_return": feasible,
                "normalized_cost": cost,
                "normalized_return": 1.0,
            },
        }
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "results.json").write_text(json.dumps(results))

    run("a0", "spoildice", 0, 0.5, 0.5)
    run("a1", "spoildice", 1, 0.7, 0.9)
    run("b0", "bc", 0, 0.3, 4.0)
    run("b1", "bc", 1, 0.9, 9.0, status="training")  # unfinished: ignored
    cmd = [
        "recipes/report.py",
        str(tmp_path),
        "--out",
        str(tmp_path / "t.md"),
        "--plot",
        str(tmp_path / "t.png"),
        "--curves",
        str(tmp_path / "c.png"),
    ]
    proc = run_command(cmd, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    table = (tmp_path / "t.md").read_text()
    assert "| SpoilDICE | 2 | **0.60 ± 0.10** | **0.70 ± 0.20** |" in table  # safe on average: bold
    assert "| 0.50 / 0.50, 0.70 / 0.90 | 5 % / 20 % |" in table  # per-seed values, diagnostics
    assert "| BC | 1 | 0.30 | 4.00 | 1.00 | 0.30 / 4.00 | - |" in table  # no DICE diagnostics
    assert "| BC | 1 | 0.30 | 4.00 |" in table  # one seed: no standard error, not safe
    assert table.index("| BC |") < table.index("| SpoilDICE |")  # the paper's order
    assert (tmp_path / "t.png").stat().st_size > 1000
    assert (tmp_path / "c.png").stat().st_size > 1000

    # a seed found twice is an error, not a silent third sample
    run("a0-again", "spoildice", 0, 0.5, 0.5)
    proc = run_command(cmd, cwd=ROOT)
    assert proc.returncode != 0 and "seed 0 of spoildice on d twice" in proc.stderr
    (tmp_path / "a0-again" / "results.json").unlink()

    # runs of one dataset with different training budgets are not put in one table
    (tmp_path / "a0" / "config.yaml").write_text("train:\n  steps: 10000\n")
    (tmp_path / "b0" / "config.yaml").write_text("train:\n  steps: 500\n")
    proc = run_command(cmd, cwd=ROOT)
    assert proc.returncode != 0 and "different train settings" in proc.stderr


def test_report_learning_curves_average_seeds_at_shared_steps():
    report = _report_module()

    def seed(values, steps=(100, 200)):
        return {
            "evaluations": [
                {"step": s, "normalized_feasible_return": v, "normalized_cost": 2 * v}
                for s, v in zip(steps, values, strict=True)
            ]
        }

    runs = {("d", "bc"): [seed([0.2, 0.4]), seed([0.4, 0.8]), seed([0.6, 1.0, 1.0], steps=(100, 200, 300))]}
    curves = report.learning_curves(runs)[("d", "bc")]
    assert curves["steps"] == [100, 200]  # 300 is not reached by every seed
    (m100, se100), (m200, _) = curves["normalized_feasible_return"]
    assert m100 == pytest.approx(0.4) and se100 == pytest.approx(0.2 / 3**0.5)
    assert m200 == pytest.approx(2.2 / 3)
    assert curves["normalized_cost"][0][0] == pytest.approx(0.8)


@pytest.mark.parametrize(
    "flag, target, message",
    [
        ("--plot", "DIR", "is a directory"),
        ("--plot", "plot", "ending in .png, .pdf or .svg"),
        ("--curves", "DIR", "is a directory"),
        ("--out", "DIR", "is a directory"),
        ("--out", "/proc/report.md", "cannot write"),
    ],
)
def test_report_outputs_are_files_the_user_named(tmp_path, flag, target, message):
    runs = tmp_path / "runs"
    _finished_run(runs / "a", 0, "aaaa")
    out_dir = tmp_path / "existing"
    out_dir.mkdir()
    (tmp_path / "existing.png").write_text("the user's own file")
    path = (
        str(out_dir) if target == "DIR" else str(tmp_path / target) if not target.startswith("/") else target
    )
    proc = run_command(["recipes/report.py", str(runs), flag, path])
    assert proc.returncode != 0 and message in proc.stderr and "Traceback" not in proc.stderr, proc.stderr
    assert (tmp_path / "existing.png").read_text() == "the user's own file" and not list(out_dir.iterdir())
