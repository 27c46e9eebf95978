"""``python -m spoil_torchrl.eval.dice_explain``: each run it cannot explain gets one line naming it and
why, the others are explained, and the exit status says whether all were (in this process: tests/cli.py)."""

from __future__ import annotations

import json
from pathlib import Path

from tests.cli import run_command

ROOT = Path(__file__).resolve().parents[2]
COMMAND = ["-m", "spoil_torchrl.eval.dice_explain"]

DIAG = {
    "role": "unlabeled",
    "spread": {"nu": 0.0, "bellman": 0.0, "advantage": 1.0},
    "variance_share": {"bellman": 0.0, "reward": 1.0},
    "weight_share": {"cost>0": {"weight": 0.31, "transitions": 0.2}},
    "effective_sample_size": 0.5,
}


def _run(folder: Path, content) -> Path:
    folder.mkdir(parents=True)
    text = content if isinstance(content, str) else json.dumps(content)
    (folder / "results.json").write_text(text)
    return folder


def _errors(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.startswith("error: ")]


def test_no_argument_prints_the_usage():
    ran = run_command(COMMAND)
    assert ran.returncode == 2 and "usage:" in ran.stderr and "RUN_DIR" in ran.stderr


def test_each_run_that_cannot_be_explained_gets_one_line_and_the_others_go_on(tmp_path):
    runs = tmp_path / "runs"
    good = _run(runs / "spoildice_s0", {"status": "finished", "algo": "spoildice", "dice_diagnostics": DIAG})
    _run(runs / "bc_s0", {"status": "finished", "algo": "bc"})
    bad = {
        "corrupt": _run(runs / "corrupt", "{not json"),
        "a list": _run(runs / "a_list", "[1, 2]"),
        "failed": _run(
            runs / "failed",
            {"status": "failed", "algo": "spoildice", "error": "TrainingDiverged: nu is not finite"},
        ),
        "malformed": _run(
            runs / "malformed", {"status": "finished", "algo": "spoildice", "dice_diagnostics": {"role": "x"}}
        ),
    }
    named_bc = _run(tmp_path / "named_bc", {"status": "finished", "algo": "bc"})
    missing = tmp_path / "missing"
    ran = run_command([*COMMAND, str(missing), str(runs), str(named_bc)])
    assert ran.returncode == 1, ran.stderr
    assert "Traceback" not in ran.stderr
    assert f"{good}:\n" in ran.stdout and "nearly flat" in ran.stdout  # explained, in spite of the others
    errors = _errors(ran.stderr)
    assert len(errors) == 6, ran.stderr
    assert f"error: {missing}: no such folder" in errors
    assert f"error: {bad['corrupt']}: results.json is unreadable" in ran.stderr
    assert f"error: {bad['a list']}: results.json holds a JSON list" in ran.stderr
    assert f"error: {bad['failed']}: no dice_diagnostics" in ran.stderr
    assert "status failed: TrainingDiverged: nu is not finite" in ran.stderr
    assert f"error: {bad['malformed']}: its dice_diagnostics are incomplete" in ran.stderr
    assert f"error: {named_bc}: no dice_diagnostics (bc is not a DICE method)" in errors  # named: an error
    assert f"skipped {runs / 'bc_s0'}: no dice_diagnostics (bc is not a DICE method)" in ran.stderr


def test_a_folder_of_committed_runs_is_explained_and_a_named_bc_run_refused():
    mixed = ROOT / "docs" / "results" / "mixed"
    ran = run_command([*COMMAND, str(mixed)])
    assert ran.returncode == 0 and not _errors(ran.stderr), ran.stderr[-2000:]
    assert f"{mixed / 'spoildice_s0'}:\n" in ran.stdout
    assert f"skipped {mixed / 'bc_s0'}: " in ran.stderr
    ran = run_command([*COMMAND, str(mixed / "bc_s0")])
    assert ran.returncode == 1 and "Traceback" not in ran.stderr
    assert _errors(ran.stderr) == [f"error: {mixed / 'bc_s0'}: no dice_diagnostics (bc is not a DICE method)"]


def test_a_folder_without_runs_or_dice_runs_is_an_error(tmp_path):
    ran = run_command([*COMMAND, str(tmp_path)])
    assert ran.returncode == 1 and _errors(ran.stderr) == [
        f"error: {tmp_path}: no results.json in it or under it (not a run directory)"
    ]
    _run(tmp_path / "bc_s0", {"status": "finished", "algo": "bc"})
    ran = run_command([*COMMAND, str(tmp_path)])
    assert ran.returncode == 1 and "no DICE run to explain" in ran.stderr
