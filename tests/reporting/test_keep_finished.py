"""``keep_finished`` (``spoil-report --keep``): the finished runs' ``results.json`` and ``config.yaml`` copied
out of a sweep's folders, nothing else, and nothing kept before overwritten."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from spoil_torchrl.reporting.keep import keep_finished
from tests.cli import run_command

CELL = "fig4b/n_performant2/bc/seed0"


def _run(folder: Path, status: str, seed: int = 0, *, config: bool = True) -> Path:
    run_dir = folder / "fig4b" / "n_performant2" / "bc" / f"seed{seed}"
    run_dir.mkdir(parents=True)
    if config:
        (run_dir / "config.yaml").write_text(f"seed: {seed}\n")
    (run_dir / "results.json").write_text(json.dumps({"status": status, "seed": seed}))
    (run_dir / "checkpoints").mkdir()
    (run_dir / "checkpoints" / "policy.pt").write_bytes(b"weights")
    (run_dir / "rollouts.mcap").write_bytes(b"episodes")
    return run_dir


def _files(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())


def test_only_the_finished_runs_small_files_are_kept(tmp_path):
    runs, dest = tmp_path / "runs", tmp_path / "kept"
    _run(runs, "finished", seed=0)
    _run(runs, "failed", seed=1)
    _run(runs, "training", seed=2)  # no lock and no process: killed
    _run(runs, "finished", seed=3, config=False)  # its training budget could not be checked
    kept = keep_finished([runs], dest)
    assert kept.copied == [CELL] and not kept.already and not kept.refused
    assert _files(dest) == [f"{CELL}/config.yaml", f"{CELL}/results.json"]
    reasons = sorted((p.parent.name, reason.split(" (")[0]) for p, reason in kept.skipped)
    assert reasons == [("seed1", "failed"), ("seed2", "killed"), ("seed3", "no config.yaml")]


def test_a_copy_cut_short_is_finished_and_a_kept_run_left_alone(tmp_path):
    runs, dest = tmp_path / "runs", tmp_path / "kept"
    run_dir = _run(runs, "finished")
    (dest / CELL).mkdir(parents=True)
    (dest / CELL / "config.yaml").write_text("seed: 0\n")  # killed before results.json was written
    assert keep_finished([runs], dest).copied == [CELL]
    assert (dest / CELL / "results.json").read_bytes() == (run_dir / "results.json").read_bytes()
    again = run_command(["recipes/report.py", "--keep", dest, runs])
    assert again.returncode == 0 and "0 runs kept" in again.stdout and "1 already there" in again.stdout


def test_a_run_kept_with_other_contents_is_refused_and_left_as_it_was(tmp_path):
    runs, dest = tmp_path / "runs", tmp_path / "kept"
    run_dir = _run(runs, "finished")
    keep_finished([runs], dest)
    (run_dir / "config.yaml").write_text(
        "seed: 0\ntrain:\n  steps: 5\n"
    )  # the run started over, other settings
    kept = keep_finished([runs], dest)
    assert kept.refused == [CELL] and not kept.copied
    assert (dest / CELL / "config.yaml").read_text() == "seed: 0\n"

    ran = run_command(["recipes/report.py", "--keep", dest, runs])
    assert ran.returncode == 1 and "keeps other files for 1 run(s)" in ran.stderr and CELL in ran.stderr
    assert (dest / CELL / "config.yaml").read_text() == "seed: 0\n"


def test_two_runs_at_one_place_are_not_both_kept(tmp_path):
    """Two sweeps with the same layout: the first one's run is kept, the second refused, not mixed with it."""
    dest = tmp_path / "kept"
    _run(tmp_path / "a", "finished")
    other = _run(tmp_path / "b", "finished")
    (other / "config.yaml").write_text("seed: 0\nlr: 1\n")
    kept = keep_finished([tmp_path / "a", tmp_path / "b"], dest)
    assert kept.copied == [CELL] and kept.refused == [CELL]
    assert (dest / CELL / "config.yaml").read_text() == "seed: 0\n"


def test_overlapping_or_missing_folders_are_refused_before_anything_is_copied(tmp_path):
    runs = tmp_path / "runs"
    _run(runs, "finished")
    for folders, dest in (
        ([runs], runs / "kept"),  # the kept copies would be found again
        ([runs / "fig4b"], runs),
        ([runs, runs / "fig4b"], tmp_path / "kept"),  # each run twice
    ):
        with pytest.raises(ValueError, match="overlap"):
            keep_finished(folders, dest)
    with pytest.raises(FileNotFoundError, match="no such folder"):
        keep_finished([runs, tmp_path / "nothing"], tmp_path / "kept")
    assert not (tmp_path / "kept").exists() and not (runs / "kept").exists()
    ran = run_command(["recipes/report.py", "--keep", runs / "kept", "--figure", runs])
    assert ran.returncode == 2 and "drop --figure" in ran.stderr
