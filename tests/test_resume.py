"""Runs that survive: a run killed with SIGKILL (mid-training, mid-evaluation) resumes and ends exactly as an
uninterrupted run, ``seeds=[...]`` included; a start or a refused command never changes a run."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import pytest
import torch

from tests.cli import run_command
from tests.short_runs import evaluations, files, kill_when, run_short

pytestmark = pytest.mark.runs


def _episodes_on_disk(run_dir: Path) -> int:
    from spoil_torchrl.eval import read_rollouts

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return int(read_rollouts(run_dir / "rollouts.mcap").episodes.batch_size[0])
    except Exception:  # not there yet, or caught mid-header
        return 0


def _plain_mcap_episodes(path: Path) -> list[tuple[int, int]]:
    """(evaluation step, length) of every episode summary, read with the plain mcap reader."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return [
            (json.loads(m.data)["evaluation_step"], json.loads(m.data)["length"])
            for _, _, m in make_reader(f).iter_messages(topics=["/eval/episode"])
        ]


@pytest.fixture(scope="module")
def uninterrupted(tmp_path_factory, tiny_pc1_dataset):
    run_dir = tmp_path_factory.mktemp("full")
    run_short(tiny_pc1_dataset, run_dir)
    return run_dir


def _same_run(a: Path, b: Path) -> None:
    ra, rb = (json.loads((d / "results.json").read_text()) for d in (a, b))
    assert rb["status"] == "finished" and rb["resumed_at"]
    strip = ("seconds", "eval_seconds")  # wall times
    assert [{k: v for k, v in e.items() if k not in strip} for e in ra["evaluations"]] == [
        {k: v for k, v in e.items() if k not in strip} for e in rb["evaluations"]
    ]
    assert ra["aggregate"] == rb["aggregate"] and ra["dice_diagnostics"] == rb["dice_diagnostics"]
    pa, pb = (torch.load(d / "checkpoints" / "policy.pt", weights_only=True)["actor"] for d in (a, b))
    assert pa.keys() == pb.keys() and all(torch.equal(pa[k], pb[k]) for k in pa)
    assert _plain_mcap_episodes(b / "rollouts.mcap") == _plain_mcap_episodes(a / "rollouts.mcap")
    assert not (b / "rollouts.mcap.before-resume").exists() and not (b / "run.lock").exists()
    for log in (a / "logs").rglob("*.csv"):  # every step logged once
        assert (b / log.relative_to(a)).read_text().count("\n") == log.read_text().count("\n"), log.name


def _no_discriminator_training(monkeypatch) -> list:
    """Make every discriminator training of the DICE algorithms fail loudly; returns the calls it saw."""
    from spoil_torchrl.algorithms import dice

    calls = []

    def trained_again(*args, **kwargs):
        calls.append(args)
        raise AssertionError("the resumed run trained its discriminators again")

    monkeypatch.setattr(dice, "train_discriminators", trained_again)
    return calls


def test_a_run_killed_mid_training_resumes_bit_exactly(
    tmp_path, tiny_pc1_dataset, uninterrupted, monkeypatch
):
    from spoil_torchrl.runs.directory import run_status

    run_dir = tmp_path / "run"
    kill_when(tiny_pc1_dataset, run_dir, lambda d: evaluations(d) >= 2)
    assert run_status(run_dir) == "killed"
    assert (run_dir / "checkpoints" / "pretraining.pt").is_file()  # stored before the main stage began
    # a plain restart refuses to overwrite it, with one clear line and no traceback
    proc = run_short(tiny_pc1_dataset, run_dir, ok=False)
    assert proc.returncode == 2 and "resume=true" in proc.stderr and "Traceback" not in proc.stderr
    # the report says why it leaves the run out
    report = run_command(["recipes/report.py", tmp_path, uninterrupted], real=True)  # spoil-report's process
    assert report.returncode == 0 and f"skipped {run_dir}: killed" in report.stderr
    calls = _no_discriminator_training(monkeypatch)
    run_short(tiny_pc1_dataset, run_dir, "resume=true")
    assert calls == []  # the stored pre-training was loaded, not computed
    _same_run(uninterrupted, run_dir)
    results = json.loads((run_dir / "results.json").read_text())
    assert [part["stage"] for part in results["ran_on"]] == ["pre-training", "main", "main"]
    assert (
        results["ran_on"][-1]["from_step"] == results["resumed_at"][-1] and "resumed_elsewhere" not in results
    )


def test_a_run_resumed_where_its_pretraining_would_differ_continues_from_the_stored_one(
    tmp_path, tiny_pc1_dataset, uninterrupted, monkeypatch
):
    """As if resumed on another CPU: a discriminator initialised differently from now on and another machine.
    The run continues from its stored pre-training, ends as the uninterrupted run and says where it ran; a run
    without a stored pre-training (made before they were stored) computes it again and is refused."""
    from spoil_torchrl.algorithms import discriminators
    from spoil_torchrl.runs import lifecycle

    run_dir, legacy = tmp_path / "run", tmp_path / "legacy"
    kill_when(tiny_pc1_dataset, run_dir, lambda d: (d / "checkpoints" / "training_state.pt").exists())
    shutil.copytree(run_dir, legacy)
    (legacy / "checkpoints" / "pretraining.pt").unlink()
    make_discriminator = discriminators.make_discriminator

    def perturbed(*args, **kwargs):
        network = make_discriminator(*args, **kwargs)
        with torch.no_grad():
            next(network.parameters()).add_(1e-3)
        return network

    monkeypatch.setattr(discriminators, "make_discriminator", perturbed)
    monkeypatch.setattr(lifecycle, "current_machine", lambda: {"host": "elsewhere", "cpu": "another CPU"})
    run_short(tiny_pc1_dataset, run_dir, "resume=true")
    _same_run(uninterrupted, run_dir)
    results = json.loads((run_dir / "results.json").read_text())
    assert results["resumed_elsewhere"] is True
    step = results["resumed_at"][-1]
    where = {k: v for k, v in results["ran_on"][-1].items() if k != "setup_seconds"}
    assert where == {"stage": "main", "from_step": step, "host": "elsewhere", "cpu": "another CPU"}
    proc = run_short(tiny_pc1_dataset, legacy, "resume=true", ok=False)
    assert proc.returncode == 2 and "did not reproduce" in proc.stderr and "Traceback" not in proc.stderr


def test_a_run_killed_mid_evaluation_resumes_bit_exactly(tmp_path, tiny_pc1_dataset, uninterrupted):
    # killed while an evaluation's episodes are on disk but the evaluation is not recorded yet: a window of
    # milliseconds that a poll of the MCAP file can miss on a loaded machine, so a run that ends first is
    # started again in a fresh directory (at most three times)
    condition = lambda d: _episodes_on_disk(d) > 2 * max(evaluations(d), 1)  # noqa: E731
    for attempt in range(3):
        run_dir = tmp_path / f"run{attempt}"
        if kill_when(tiny_pc1_dataset, run_dir, condition, required=False):
            break
    else:
        pytest.fail("three runs ended before an evaluation's episodes were seen on disk unrecorded")
    assert _episodes_on_disk(run_dir) > 2 * evaluations(run_dir)
    run_short(tiny_pc1_dataset, run_dir, "resume=auto")
    _same_run(uninterrupted, run_dir)


def test_seeds_run_each_seed_as_its_own_run_and_resume_bit_exactly(tmp_path, tiny_pc1_dataset, uninterrupted):
    """``seeds=[0,1]``: each seed's files, settings and pre-training are its single run's, its main stage the
    same up to float rounding (one vmapped update). Killed between its seeds' checkpoints, it continues from the
    last step both seeds have (seed 0's previous checkpoint) and ends as the uninterrupted run."""
    seeds = ["seeds=[0,1]"]
    full = tmp_path / "full"
    run_short(tiny_pc1_dataset, full, *seeds)
    alone = json.loads((uninterrupted / "results.json").read_text())  # seed 0 alone
    for seed in (0, 1):
        results = json.loads((full / f"seed{seed}" / "results.json").read_text())
        assert results["status"] == "finished" and results["seed"] == seed
        assert results["update_step"] == "vectorised, eager"  # the smoke preset does not compile
        assert [e["step"] for e in results["evaluations"]] == [100, 200, 300]
        assert len(_plain_mcap_episodes(full / f"seed{seed}" / "rollouts.mcap")) == 6
        assert list((full / f"seed{seed}" / "logs").rglob("dice.loss_nu.csv"))
        config = (full / f"seed{seed}" / "config.yaml").read_text()
        assert f"\nseed: {seed}\n" in config and "seeds" not in config  # the single run's settings
        # its evaluations' episodes were rolled out from a copy of the policy, in a worker process or in the
        # run's: evaluating the policy file it saved gives them again
        _same_final_evaluation(full / f"seed{seed}", results)
    seed0 = json.loads((full / "seed0" / "results.json").read_text())
    assert seed0["diagnostics"] == alone["diagnostics"] and seed0["data"] == alone["data"]
    # the main stage: the same draws, another graph (float rounding, which Adam's first steps scale up to the
    # learning rate; tests/trainers/test_vectorized.py compares steps to 1e-4 with SGD)
    first, first_alone = seed0["evaluations"][0]["dice"], alone["evaluations"][0]["dice"]
    assert first["dice/spread_nu"] == pytest.approx(first_alone["dice/spread_nu"], rel=2e-2)

    killed = tmp_path / "killed"
    saved = killed / "seed1" / "checkpoints"
    kill_when(
        tiny_pc1_dataset,
        killed,
        lambda d: (saved / "training_state.pt").is_file() and _step(saved / "training_state.pt") == 200,
        *seeds,
    )
    # as if killed between the two seeds' checkpoints of step 200: seed 1's is still the one of step 100
    shutil.copyfile(saved / "training_state.previous.pt", saved / "training_state.pt")
    assert _step(saved / "training_state.pt") == 100
    # seed 1's stored pre-training made on other data: refused after seed 0's data is loaded, and no seed's
    # files (logs, results, settings, locks) change
    from spoil_torchrl.runs.checkpoint import load_checkpoint, save_checkpoint

    stored = killed / "seed1" / "checkpoints" / "pretraining.pt"
    good = stored.read_bytes()
    save_checkpoint(stored, load_checkpoint(stored) | {"data_fingerprint": "0" * 64})
    before = files(killed)
    proc = run_short(tiny_pc1_dataset, killed, *seeds, "resume=true", ok=False)
    assert proc.returncode == 2 and str(stored) in proc.stderr and "other data" in proc.stderr
    assert files(killed) == before
    stored.write_bytes(good)
    run_short(tiny_pc1_dataset, killed, *seeds, "resume=true")
    assert json.loads((killed / "seed0" / "results.json").read_text())["resumed_at"] == [100]
    for seed in (0, 1):
        _same_run(full / f"seed{seed}", killed / f"seed{seed}")


def _same_final_evaluation(run_dir: Path, results: dict) -> None:
    from omegaconf import OmegaConf

    from spoil_torchrl.eval import Evaluator
    from spoil_torchrl.zoo import load_policy

    cfg = OmegaConf.load(run_dir / "config.yaml")
    policy, meta = load_policy(run_dir / "checkpoints" / "policy.pt")
    assert meta["info"]["step"] == results["evaluations"][-1]["step"]
    evaluator = Evaluator(
        cfg.task.env_id,
        cost_threshold=1.0,
        return_range=(0.0, 1.0),
        episodes=cfg.train.eval_episodes,
        seed=10_000 + cfg.seed,  # the recipe's evaluation seed
        num_envs=cfg.task.eval_num_envs,
    )
    again, last = evaluator(policy)["episodes"], results["evaluations"][-1]["episodes"]
    assert (again["return"], again["cost"], again["length"]) == (last["return"], last["cost"], last["length"])


def _step(checkpoint: Path) -> int | None:
    from spoil_torchrl.runs.checkpoint import CheckpointError, load_checkpoint

    try:
        return int(load_checkpoint(checkpoint)["step"])
    except CheckpointError:  # being replaced
        return None


def _refuses_a_damaged_or_foreign_stored_pretraining(run_dir: Path, dataset) -> None:
    """A resume refuses a truncated stored pre-training, one of other settings and one of other data, in one
    line naming the file, and changes nothing in the run directory (its lock included)."""
    from spoil_torchrl.runs.checkpoint import load_checkpoint, save_checkpoint

    stored = run_dir / "checkpoints" / "pretraining.pt"
    good = stored.read_bytes()
    state = load_checkpoint(stored)
    damaged = {
        "truncated": good[: len(good) // 2],
        "other settings": state | {"config_yaml": state["config_yaml"] + "another_setting: 1\n"},
        "other data": state | {"data_fingerprint": "0" * 64},
    }
    for case, content in damaged.items():
        if isinstance(content, bytes):
            stored.write_bytes(content)
        else:
            save_checkpoint(stored, content)
        before = files(run_dir)
        proc = run_short(dataset, run_dir, "resume=true", ok=False)
        assert proc.returncode == 2 and str(stored) in proc.stderr, (case, proc.stderr[-2000:])
        assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1, case
        assert files(run_dir) == before, case
    assert "other data" in proc.stderr
    stored.write_bytes(good)


def test_resume_refuses_other_settings_and_a_damaged_checkpoint(tmp_path, tiny_pc1_dataset):
    run_dir = tmp_path / "run"
    kill_when(tiny_pc1_dataset, run_dir, lambda d: (d / "checkpoints" / "training_state.pt").exists())
    before = files(run_dir)
    assert ".hydra/overrides.yaml" in before and "run.lock" in before  # the killed run's record and lock
    proc = run_short(tiny_pc1_dataset, run_dir, "resume=true", "train.lr=0.1", ok=False)
    assert proc.returncode == 2 and "train.lr" in proc.stderr
    assert files(run_dir) == before  # the refused command changed nothing, Hydra's record included
    proc = run_short(tiny_pc1_dataset, run_dir, ok=False)  # a start over it
    assert proc.returncode == 2 and "already holds a run" in proc.stderr and files(run_dir) == before
    _refuses_a_damaged_or_foreign_stored_pretraining(run_dir, tiny_pc1_dataset)
    checkpoint = run_dir / "checkpoints" / "training_state.pt"
    data = bytearray(checkpoint.read_bytes())
    data[len(data) // 2] ^= 0xFF
    checkpoint.write_bytes(bytes(data))
    proc = run_short(tiny_pc1_dataset, run_dir, "resume=true", ok=False)
    assert proc.returncode == 2 and str(checkpoint) in proc.stderr and "Traceback" not in proc.stderr


def test_commands_refused_on_a_finished_run_leave_it_byte_identical(
    tmp_path, uninterrupted, tiny_pc1_dataset
):
    run_dir = tmp_path / "run"
    shutil.copytree(uninterrupted, run_dir)
    before = files(run_dir)
    for overrides, message in (
        ((), "already holds a run"),
        (("resume=true",), "has finished"),
        (("resume=auto", "train.lr=0.5"), "has finished"),
    ):
        proc = run_short(tiny_pc1_dataset, run_dir, *overrides, ok=False)
        assert proc.returncode == 2 and message in proc.stderr, proc.stderr[-2000:]
        assert files(run_dir) == before, overrides
