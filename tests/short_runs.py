"""Short runs of the main recipe on the suite's tiny collected dataset, for the tests of what becomes of a run:
killed and resumed, refused, interrupted, failed, swept."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

from tests.cli import run_command

ROOT = Path(__file__).resolve().parents[1]
RECIPE = str(ROOT / "recipes" / "spoildice_dsrl.py")
# 300 steps of 64 samples, an evaluation of 2 episodes every 100: long enough to be killed at a chosen point
SHORT = ["preset=smoke", "train.steps=300", "train.batch_size=64", "train.eval_episodes=2", "progress=false"]


def composed_settings(dataset, *overrides):
    """The main recipe's settings, composed in-process with Hydra's compose API: the smoke preset on ``dataset``
    (2 safe and 2 performant episodes), no progress bars, then ``overrides``."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(ROOT / "configs"), version_base="1.3"):
        return compose(
            "spoildice_dsrl",
            overrides=[
                "preset=smoke",
                f"dataset.source=file:{dataset}",
                "dataset.n_safe=2",
                "dataset.n_performant=2",
                "progress=false",
                *overrides,
            ],
        )


def recipe_args(dataset, run_dir, *overrides) -> list[str]:
    """The command line of a short run in ``run_dir`` on ``dataset`` (2 safe and 2 performant episodes)."""
    data = [f"dataset.source=file:{dataset}", "dataset.n_safe=2", "dataset.n_performant=2"]
    return [sys.executable, RECIPE, *SHORT, *data, f"hydra.run.dir={run_dir}", *overrides]


def run_short(dataset, run_dir, *overrides, ok=True):
    """A short run in this process (the kills need a process of their own); ``ok``: it must succeed."""
    proc = run_command(recipe_args(dataset, run_dir, *overrides)[1:])
    if ok:
        assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


def evaluations(run_dir: Path) -> int:
    """How many evaluations the run in ``run_dir`` has recorded so far (0 before its first results.json)."""
    try:
        return len(json.loads((run_dir / "results.json").read_text())["evaluations"])
    except (OSError, ValueError, KeyError):
        return 0


def kill_command_when(argv: list[str], condition, *, timeout: float = 240, required: bool = True) -> bool:
    """Start ``argv`` (a command line, output discarded) and SIGKILL it as soon as ``condition()`` holds;
    fails if ``timeout`` seconds pass, or if the command ends first (with ``required=False`` that returns
    False instead: a condition that holds only in a short window can be missed by a poll on a loaded machine)."""
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=ROOT)
    try:
        deadline = time.monotonic() + timeout
        while not condition():
            if proc.poll() is not None:
                assert not required, "the command ended before it could be killed"
                return False
            assert time.monotonic() < deadline
            time.sleep(0.01)
        proc.send_signal(signal.SIGKILL)
        return True
    finally:
        proc.kill()
        proc.wait()


def kill_when(dataset, run_dir, condition, *overrides, required: bool = True) -> bool:
    """A short run in ``run_dir``, killed with SIGKILL as soon as ``condition(run_dir)`` holds (see
    :func:`kill_command_when` for ``required``)."""
    return kill_command_when(
        recipe_args(dataset, run_dir, *overrides), lambda: condition(run_dir), required=required
    )


def files(run_dir: Path) -> dict[str, tuple[bytes, int]]:
    """Every file of the directory with its bytes and modification time (what a refused command must keep)."""
    return {
        str(p.relative_to(run_dir)): (p.read_bytes(), p.stat().st_mtime_ns)
        for p in run_dir.rglob("*")
        if p.is_file()
    }
