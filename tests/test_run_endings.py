"""Runs that end loudly: SIGTERM marks a run interrupted and keeps its checkpoint; a diverged run and a full disk
fail in one line, and the report leaves a failed run out."""

from __future__ import annotations

import json
import signal
import subprocess
import time

import pytest

from tests.cli import run_command
from tests.short_runs import ROOT, evaluations, recipe_args, run_short

pytestmark = pytest.mark.runs


def test_sigterm_marks_the_run_interrupted_and_keeps_its_checkpoint(tmp_path, tiny_pc1_dataset):
    run_dir = tmp_path / "run"
    proc = subprocess.Popen(
        recipe_args(tiny_pc1_dataset, run_dir),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        cwd=ROOT,
        text=True,
    )
    deadline = time.monotonic() + 240
    while evaluations(run_dir) < 1 and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    _, stderr = proc.communicate(timeout=120)
    results = json.loads((run_dir / "results.json").read_text())
    assert results["status"] == "interrupted" and "SIGTERM" in results["error"]
    assert proc.returncode == 130 and "Traceback" not in stderr, stderr[-2000:]
    line = [ln for ln in stderr.splitlines() if ln.startswith("interrupted; continue with: python")]
    assert len(line) == 1 and f"hydra.run.dir={run_dir} resume=true" in line[0]
    assert (run_dir / "checkpoints" / "training_state.pt").exists() and not (run_dir / "run.lock").exists()


def test_a_diverged_run_fails_in_one_line_and_the_report_leaves_it_out(tmp_path, tiny_pc1_dataset):
    run_dir = tmp_path / "diverged"
    proc = run_short(tiny_pc1_dataset, run_dir, "train.lr=1e10", ok=False)
    failed = [ln for ln in proc.stderr.splitlines() if ln.startswith("failed: ")]
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert len(failed) == 1 and "is not finite" in failed[0] and "by step" in failed[0]
    results = json.loads((run_dir / "results.json").read_text())
    assert results["status"] == "failed" and "TrainingDiverged" in results["error"]
    assert not list(ROOT.glob("MUJOCO_LOG.TXT"))
    report = run_command(["recipes/report.py", tmp_path])
    assert report.returncode != 0 and "no finished results.json" in report.stderr
    assert f"skipped {run_dir}: failed (TrainingDiverged:" in report.stderr


def test_a_full_disk_fails_the_run_in_one_line_and_leaves_no_temporary_file(tmp_path, tiny_pc1_dataset):
    import resource

    def small_files():  # every write past 150 kB fails (EFBIG), as on a full disk
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (150_000, 150_000))

    run_dir = tmp_path / "run"
    proc = subprocess.run(
        recipe_args(tiny_pc1_dataset, run_dir),
        capture_output=True,
        text=True,
        timeout=300,
        cwd=ROOT,
        preexec_fn=small_files,
    )
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert proc.stderr.strip().splitlines()[-1].startswith("error: cannot write")
    assert json.loads((run_dir / "results.json").read_text())["status"] == "failed"
    assert not [p for p in run_dir.rglob("*.tmp")] and not (run_dir / "run.lock").exists()
