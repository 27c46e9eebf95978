"""``keep_finished`` (``spoil-report --keep``): the finished runs' ``results.json`` and ``config.yaml`` copied
out of a sweep's folders, nothing else, and nothing kept before overwritten."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from spoil_torchrl.runs.experiments import keep_finished
from tests.cli import run_command


def _run(folder: Path, status: str, seed: int = 0) -> Path:
    run_dir = folder / "fig4b" / "n_performant2" / "bc" / f"seed{seed}"
    run_dir.mkdir(parents=True)
    (run_dir / "config.yaml").write_text(f"seed: {seed}\n")
    (run_dir / "results.json").write_text(json.dumps({"status": status, "seed": seed}))
    (run_dir / "checkpoints").mkdir()
    (run_dir / "checkpoints" / "policy.pt").write_bytes(b"weights")
    (run_dir / "rollouts.mcap").write_bytes(b"episodes")
    return run_dir


def test_only_the_finished_runs_small_files_are_kept(tmp_path):
    runs, dest = tmp_path / "runs", tmp_path / "kept"
    _run(runs, "finished", seed=0)
    _run(runs, "failed", seed=1)
    _run(runs, "training", seed=2)  # no lock and no process: killed
    kept = keep_finished([runs], dest)
    assert kept.copied == ["fig4b/n_performant2/bc/seed0"] and not kept.already and not kept.refused
    assert sorted(str(p.relative_to(dest)) for p in dest.rglob("*") if p.is_file()) == [
        "fig4b/n_performant2/bc/seed0/config.yaml",
        "fig4b/n_performant2/bc/seed0/results.json",
    ]
    assert sorted((p.parent.name, reason) for p, reason in kept.skipped) == [
        ("seed1", "failed"),
        ("seed2", "killed"),
    ]


def test_a_run_kept_with_other_contents_is_refused_and_left_as_it_was(tmp_path):
    runs, dest = tmp_path / "runs", tmp_path / "kept"
    run_dir = _run(runs, "finished")
    keep_finished([runs], dest)
    (run_dir / "config.yaml").write_text(
        "seed: 0\ntrain:\n  steps: 5\n"
    )  # the run started over, other settings
    kept = keep_finished([runs], dest)
    assert kept.refused == ["fig4b/n_performant2/bc/seed0"] and not kept.copied
    assert (dest / "fig4b/n_performant2/bc/seed0/config.yaml").read_text() == "seed: 0\n"

    ran = run_command(["recipes/report.py", "--keep", dest, runs])
    assert ran.returncode == 1 and "keeps other files for 1 runs" in ran.stderr and "seed0" in ran.stderr
    assert (dest / "fig4b/n_performant2/bc/seed0/config.yaml").read_text() == "seed: 0\n"


def test_a_destination_inside_the_searched_folders_is_refused(tmp_path):
    runs = tmp_path / "runs"
    _run(runs, "finished")
    with pytest.raises(ValueError, match="overlap"):
        keep_finished([runs], runs / "kept")
    with pytest.raises(ValueError, match="overlap"):
        keep_finished([runs / "fig4b"], runs)
    with pytest.raises(FileNotFoundError, match="no such folder"):
        keep_finished([tmp_path / "nothing"], tmp_path / "kept")
    ran = run_command(["recipes/report.py", "--keep", runs / "kept", "--figure", runs])
    assert ran.returncode == 2 and "drop --figure" in ran.stderr
