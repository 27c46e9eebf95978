"""Commands refuse what a user can fix with one line on stderr and an exit status, never a traceback, and leave
every file outside the run directory as it was: the main recipe on bad data, settings and run directories, and
the report, inspect and expert-training commands (in this process: tests/cli.py)."""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import pytest

from spoil_torchrl.data.hdf5 import write_dsrl_file
from tests.cli import run_command
from tests.data.helpers import make_arrays
from tests.test_bad_inputs import _arrays_file, _good, _task_metadata, _truncated

ROOT = Path(__file__).resolve().parents[1]


# -- through the recipe: one line on stderr, exit status 2, nothing outside the run directory touched ----------


def _snapshot(folder: Path) -> dict[str, str]:
    return {
        str(p): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.rglob("*")) if p.is_file()
    }


@pytest.mark.parametrize(
    "overrides, match",
    [
        (["algo.kappa=2"], "algo.kappa = 2"),
        (["train.discriminator_steps=0"], "train.discriminator_steps = 0"),
        (["threads=0"], "threads = 0"),
        (["resume=maybe"], "resume must be one of"),
        (["algo.name=sac"], "has no builder"),
        (["logger.type=tensorbord"], "'tensorbord' is not a logger"),
        (["DATA=negative"], "costs are negative"),
        (["DATA=truncated"], "truncated or corrupt|corrupt"),
        (["RUN=existing"], "already holds a run"),
        (["RUN=blocked-checkpoints"], "cannot write checkpoints"),
        (["normalize_observations=no"], "normalize_observations = 'no'"),
        (["threads=999"], "threads = 999"),
        (["dataset.return_range=[0,40,-7]"], "dataset.return_range"),
        (["task.eval_num_envs=0"], "task.eval_num_envs = 0"),
        (["dataset.source=generated:no-such-data"], "unknown generated dataset 'no-such-data'"),
        (["dataset.source=foo:bar"], "dataset.source = 'foo:bar': unknown dataset source; use one of 'file:"),
        (["algo.distribution=gaussian"], "algo.distribution = 'gaussian': expected tanh_normal"),
        (["algo=bc", "algo.distribution=categorical"], "SafetyPointCircle1-v0's actions are continuous"),
        (
            ["DATA=task", "dataset.n_safe=1", "dataset.n_performant=1", "dataset.n_unlabeled=1000"],
            "fewer than n_unlabeled=1000",
        ),
        (["DATA=no-safe"], "no episode has cost <= 25"),
        (
            ["DATA=wrong-size", "dataset.cost_threshold=25", "dataset.return_range=[0,1]"],
            "observation/action sizes 4/2",
        ),
        (["DATA=big-actions"], "action values lie outside SafetyPointCircle1-v0's bounds"),
        (["RUN=a-file"], "is a file, not a run directory"),
        (["RUN=uncreatable"], "cannot be created"),
        (
            ["DATA=task", "dataset.n_safe=1", "dataset.n_performant=1", "logger=wandb"],
            "logger=wandb cannot start|needs the wandb package",
        ),
    ],
)
def test_the_recipe_reports_user_errors_in_one_line(tmp_path, overrides, match):
    data_dir = tmp_path / "data"
    data_dir.mkdir()
    data = _good(data_dir / "ok.hdf5")
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    if "DATA=negative" in overrides:
        data = _arrays_file(costs=lambda a: a - 1.0)(data_dir / "negative.hdf5")
    if "DATA=truncated" in overrides:
        data = _truncated(data_dir / "truncated.hdf5")
    task_file = dict(lengths=(30, 20, 40), obs_dim=28)  # PointCircle1's sizes
    if "DATA=no-safe" in overrides:
        arrays = make_arrays(**task_file)
        arrays["costs"] = arrays["costs"] * 0 + 5.0  # every episode far over the threshold of 25
        data = write_dsrl_file(data_dir / "no-safe.hdf5", arrays, metadata=_task_metadata())
    if "DATA=task" in overrides:  # a good PointCircle1 file
        data = write_dsrl_file(data_dir / "task.hdf5", make_arrays(**task_file), metadata=_task_metadata())
    if "DATA=big-actions" in overrides:
        arrays = make_arrays(**task_file)
        arrays["actions"] = arrays["actions"] * 1e6
        data = write_dsrl_file(data_dir / "big-actions.hdf5", arrays, metadata=_task_metadata())
    if "RUN=existing" in overrides:
        (run_dir / "results.json").write_text(json.dumps({"status": "finished"}))
    if "RUN=a-file" in overrides:
        run_dir.rmdir()
        run_dir.write_text("a file where the run directory should be")
    if "RUN=uncreatable" in overrides:
        run_dir = run_dir / "file" / "run"
        (run_dir.parent.parent / "file").write_text("")
    existing_run = "RUN=existing" in overrides
    run_before = _snapshot(run_dir) if existing_run else None
    if "RUN=blocked-checkpoints" in overrides:
        (run_dir / "checkpoints").write_text("a file where the folder should be")
    overrides = [o for o in overrides if not o.startswith(("DATA=", "RUN="))]
    before = _snapshot(data_dir)
    cmd = [
        "recipes/spoildice_dsrl.py",
        "preset=smoke",
        "progress=false",
        f"dataset.source=file:{data}",
        f"hydra.run.dir={run_dir}",
        *overrides,
    ]
    # wandb keeps process-wide state (an earlier test's offline run would let it start here): its own process
    proc = run_command(cmd, cwd=ROOT, real=any(o.startswith("logger=wandb") for o in overrides))
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert len(errors) == 1 and re.search(match, errors[0]), proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    assert _snapshot(data_dir) == before
    assert not (run_dir / "run.lock").exists()
    if existing_run:  # a refused command leaves an existing run as it was
        assert _snapshot(run_dir) == run_before


# -- the other commands: report, inspect, expert training -----------------------------------------------------


def _results_json(folder: Path, seed: int, steps: int = 100) -> None:
    metrics = {"normalized_feasible_return": 0.5, "normalized_cost": 0.5, "normalized_return": 0.5}
    folder.mkdir(parents=True)
    (folder / "results.json").write_text(
        json.dumps(
            {
                "status": "finished",
                "dataset": "d",
                "algo": "bc",
                "seed": seed,
                "aggregate": metrics,
                "total_seconds": 1.0,
                "evaluations": [{"step": 100, **metrics}],
            }
        )
    )
    (folder / "config.yaml").write_text(f"train:\n  steps: {steps}\n")


def _command_case(tmp_path: Path, case: str) -> list[str]:
    report, inspect = [str(ROOT / "recipes" / "report.py")], ["-m", "spoil_torchrl.inspect"]
    experts = [
        str(ROOT / "recipes" / "train_experts.py"),
        "progress=false",
        f"hydra.run.dir={tmp_path / 'expert'}",
    ]
    if case == "report: no such folder":
        return [*report, str(tmp_path / "nowhere")]
    if case == "report: only an unreadable results.json":
        (tmp_path / "run").mkdir()
        (tmp_path / "run" / "results.json").write_text("{not json")
        return [*report, str(tmp_path)]
    if case == "report: one dataset, two budgets":
        _results_json(tmp_path / "a", 0, steps=100)
        _results_json(tmp_path / "b", 1, steps=200)
        return [*report, str(tmp_path)]
    if case == "report: a seed twice":
        _results_json(tmp_path / "a", 0)
        _results_json(tmp_path / "b", 0)
        return [*report, str(tmp_path)]
    if case == "inspect: no such file":
        return [*inspect, str(tmp_path / "missing.mcap")]
    if case == "inspect: a text file":
        (tmp_path / "notes.mcap").write_text("not a rollout file")
        return [*inspect, str(tmp_path / "notes.mcap")]
    if case == "inspect: an empty file":
        (tmp_path / "empty.mcap").write_bytes(b"")
        return [*inspect, str(tmp_path / "empty.mcap")]
    if case == "experts: unknown task":
        return [*experts, "env_id=SafetyPointCircle9-v0"]
    if case == "experts: minibatch larger than the batch":
        return [*experts, "ppo.frames_per_batch=100", "ppo.minibatch_size=1000"]
    if case == "experts: more threads than cores":
        return [*experts, "threads=999"]
    if case == "experts: run directory is a file":
        (tmp_path / "expert").write_text("")
        return experts
    if case == "experts: resume with nothing to resume":
        (tmp_path / "expert").mkdir()
        (tmp_path / "expert" / "results.json").write_text('{"status": "training"}')
        return [*experts, "resume=true"]
    raise AssertionError(case)


COMMAND_CASES = {
    "report: no such folder": "no such folder",
    "report: only an unreadable results.json": "unreadable",
    "report: one dataset, two budgets": "different train settings",
    "report: a seed twice": "seed 0 of bc on d twice",
    "inspect: no such file": "missing.mcap",
    "inspect: a text file": "notes.mcap",
    "inspect: an empty file": "empty.mcap",
    "experts: unknown task": "unknown task 'SafetyPointCircle9-v0'",
    "experts: minibatch larger than the batch": "minibatch_size = 1000 is larger",
    "experts: more threads than cores": "threads = 999",
    "experts: run directory is a file": "is a file, not a run directory",
    "experts: resume with nothing to resume": "has no checkpoint",
}


@pytest.mark.parametrize("case", list(COMMAND_CASES))
def test_the_other_commands_report_user_errors_in_one_line(tmp_path, case):
    cmd = _command_case(tmp_path, case)
    before = _snapshot(tmp_path)
    proc = run_command(cmd, cwd=tmp_path)
    assert proc.returncode != 0 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert re.search(COMMAND_CASES[case], proc.stderr), proc.stderr[-2000:]
    assert _snapshot(tmp_path) == before  # nothing written, nothing changed
