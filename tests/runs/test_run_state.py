"""Checkpoints, run-directory locks and the resume checks, on hand-made files."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
import torch
from tensordict import TensorDict

from spoil_torchrl.data import DualDemoBuffers
from spoil_torchrl.runs.checkpoint import (
    CheckpointError,
    load_checkpoint,
    rng_state,
    save_checkpoint,
    set_rng_state,
)
from spoil_torchrl.runs.directory import (
    CHECKPOINT_NAME,
    LOCK_NAME,
    RunDirError,
    claim_run_dir,
    read_lock,
    release_run_dir,
    run_status,
)
from spoil_torchrl.runs.resume import (
    csv_row_counts,
    pretraining_fingerprint,
    settings_differ,
    trim_csv_logs,
)


def _buffers(seed: int = 0) -> DualDemoBuffers:
    n = 40
    episodes = TensorDict(
        {
            "observation": torch.arange(n, dtype=torch.float32).unsqueeze(-1),
            "episode": torch.arange(n) // 10,
            "is_init": (torch.arange(n) % 10 == 0).unsqueeze(-1),
        },
        [n],
    )
    return DualDemoBuffers(episodes, {"safe": [0], "unlabeled": [0, 1, 2, 3]}, batch_size=5, seed=seed)


# -- checkpoints ----------------------------------------------------------------------------------------------


def test_checkpoint_round_trip_keeps_every_kind_of_value(tmp_path):
    state = {
        "step": 500,
        "net": {"w": torch.randn(3, 2)},
        "results": {"evaluations": [{"step": 500, "cost": float("nan"), "note": None}]},
        "rng": rng_state(),
    }
    save_checkpoint(tmp_path / "state.pt", state)
    back = load_checkpoint(tmp_path / "state.pt")
    assert back["step"] == 500 and torch.equal(back["net"]["w"], state["net"]["w"])
    assert back["results"]["evaluations"][0]["note"] is None
    assert torch.equal(back["rng"]["torch"], state["rng"]["torch"])
    assert not (tmp_path / "state.pt.tmp").exists()


@pytest.mark.parametrize(
    "damage",
    ["truncate", "flip_payload", "not_a_checkpoint", "other_format", "missing"],
)
def test_a_damaged_checkpoint_is_refused_with_the_file_named(tmp_path, damage):
    path = tmp_path / "state.pt"
    save_checkpoint(path, {"step": 1, "w": torch.randn(100)})
    if damage == "truncate":
        path.write_bytes(path.read_bytes()[:300])
    elif damage == "flip_payload":  # bytes of the weights changed, the recorded checksum kept
        outer = torch.load(path, weights_only=True)
        payload = bytearray(outer["payload"])
        payload[len(payload) // 2] ^= 0xFF
        outer["payload"] = bytes(payload)
        torch.save(outer, path)
    elif damage == "not_a_checkpoint":
        torch.save({"w": torch.zeros(1)}, path)
    elif damage == "other_format":
        torch.save({"format": "something/9", "sha256": "", "payload": b""}, path)
    else:
        path.unlink()
    with pytest.raises(CheckpointError, match=str(path)):
        load_checkpoint(path)


def test_rng_state_restores_torch_and_every_buffer_stream():
    buffers = _buffers()
    torch.manual_seed(3)
    state = rng_state(buffers)
    first = (torch.rand(4), buffers.sample())
    set_rng_state(state, buffers)
    again = (torch.rand(4), buffers.sample())
    assert torch.equal(first[0], again[0])
    for role in ("safe", "unlabeled", "init"):
        assert torch.equal(first[1][role, "observation"], again[1][role, "observation"])
    with pytest.raises(ValueError, match="roles"):
        _buffers().set_rng_state({"safe": state["buffers"]["safe"]})


# -- resume checks --------------------------------------------------------------------------------------------


def test_pretraining_fingerprint_sees_data_annotations_and_diagnostics():
    a, b = _buffers(), _buffers(seed=7)  # sampling seeds do not change the stored data
    assert pretraining_fingerprint(a, {"t": 1.0}) == pretraining_fingerprint(b, {"t": 1.0})
    assert pretraining_fingerprint(a, {"t": 1.0}) != pretraining_fingerprint(a, {"t": 1.5})
    b.annotate("unlabeled", "support", lambda td: (td["observation"] > 3).float())
    a.annotate("unlabeled", "support", lambda td: (td["observation"] > 4).float())
    assert pretraining_fingerprint(a, {}) != pretraining_fingerprint(b, {})


def test_settings_differ_names_the_changed_keys():
    old = "seed: 0\ntrain:\n  steps: 100\n  lr: 0.1\nprogress: true\n"
    assert settings_differ(old, old.replace("progress: true", "progress: false")) == []
    assert settings_differ(old, old.replace("steps: 100", "steps: 200").replace("seed: 0", "seed: 1")) == [
        "seed",
        "train.steps",
    ]


def test_trim_csv_logs_restores_the_row_counts(tmp_path):
    (tmp_path / "scalars").mkdir()
    (tmp_path / "scalars" / "a.csv").write_text("1,0.1\n2,0.2\n")
    counts = csv_row_counts(tmp_path)
    assert counts == {os.path.join("scalars", "a.csv"): 2}
    (tmp_path / "scalars" / "a.csv").write_text("1,0.1\n2,0.2\n3,0.3\n")
    (tmp_path / "scalars" / "b.csv").write_text("3,1\n")
    trim_csv_logs(tmp_path, counts)
    assert (tmp_path / "scalars" / "a.csv").read_text() == "1,0.1\n2,0.2\n"
    assert not (tmp_path / "scalars" / "b.csv").exists()
    assert csv_row_counts(tmp_path / "nothing") == {}


# -- run directories ------------------------------------------------------------------------------------------


def _results(run_dir, status):
    (run_dir / "results.json").write_text(json.dumps({"status": status}))


def test_claim_refuses_a_directory_that_holds_a_run(tmp_path):
    assert claim_run_dir(tmp_path) is False and read_lock(tmp_path)["pid"] == os.getpid()
    _results(tmp_path, "training")
    release_run_dir(tmp_path)
    assert not (tmp_path / LOCK_NAME).exists()
    with pytest.raises(RunDirError, match="resume=true"):
        claim_run_dir(tmp_path)
    with pytest.raises(RunDirError, match="no checkpoint"):
        claim_run_dir(tmp_path, resume=True)
    assert claim_run_dir(tmp_path, resume="auto") is False  # nothing to continue: starts afresh
    release_run_dir(tmp_path)
    (tmp_path / CHECKPOINT_NAME).parent.mkdir()
    (tmp_path / CHECKPOINT_NAME).write_bytes(b"x")
    assert claim_run_dir(tmp_path, resume=True) is True
    release_run_dir(tmp_path)
    _results(tmp_path, "finished")
    with pytest.raises(RunDirError, match="finished"):
        claim_run_dir(tmp_path, resume=True)
    with pytest.raises(RunDirError, match="resume must be"):
        claim_run_dir(tmp_path, resume="yes")


def test_a_live_process_keeps_its_directory_and_a_dead_one_reads_as_killed(tmp_path):
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        lock = {"pid": child.pid, "process_start": None, "host": os.uname().nodename, "job": None}
        (tmp_path / LOCK_NAME).write_text(json.dumps(lock))
        _results(tmp_path, "training")
        assert run_status(tmp_path) == "training"
        with pytest.raises(RunDirError, match=f"process {child.pid}"):
            claim_run_dir(tmp_path, resume="auto")
    finally:
        child.kill()
        child.wait()
    assert run_status(tmp_path) == "killed"
    (tmp_path / LOCK_NAME).write_text(json.dumps({**lock, "host": "another-host"}))
    assert run_status(tmp_path) == "training on another-host"
    _results(tmp_path, "failed")
    assert run_status(tmp_path) == "failed"
    assert run_status(tmp_path / "missing") == "missing"


def test_a_requeued_cluster_job_takes_over_its_own_lock(tmp_path, monkeypatch):
    monkeypatch.setenv("SLURM_JOB_ID", "4242")
    lock = {"pid": 1, "process_start": None, "host": "node-a", "job": "slurm:4242:"}
    (tmp_path / LOCK_NAME).write_text(json.dumps(lock))
    _results(tmp_path, "training")
    assert claim_run_dir(tmp_path, resume="auto") is False
    assert read_lock(tmp_path)["job"] == "slurm:4242:"


def test_the_seeds_continue_from_the_last_step_they_all_have(tmp_path):
    from spoil_torchrl.runs.seed_run import (
        PREVIOUS_CHECKPOINT,
        common_checkpoints,
        keep_previous_checkpoints,
    )

    seeds = [tmp_path / "seed0", tmp_path / "seed1"]
    for step in (100, 200):  # two rounds of checkpoints, as a seeds=[...] run writes them
        keep_previous_checkpoints(seeds)
        for seed_dir in seeds:
            save_checkpoint(seed_dir / CHECKPOINT_NAME, {"step": step})
    keep_previous_checkpoints(seeds)  # the third round: killed after seed 0's checkpoint
    save_checkpoint(seeds[0] / CHECKPOINT_NAME, {"step": 300})
    chosen = common_checkpoints(seeds, [True, True])
    assert chosen == [seeds[0] / PREVIOUS_CHECKPOINT, seeds[1] / CHECKPOINT_NAME]
    assert [load_checkpoint(path)["step"] for path in chosen] == [200, 200]
    assert common_checkpoints(seeds, [False, False]) == [None, None]
    with pytest.raises(CheckpointError, match="no checkpoint to continue in .*seed1"):
        common_checkpoints(seeds, [True, False])
    save_checkpoint(seeds[1] / CHECKPOINT_NAME, {"step": 50})
    save_checkpoint(seeds[1] / PREVIOUS_CHECKPOINT, {"step": 40})
    with pytest.raises(CheckpointError, match="share no step .*resume each seed on its own"):
        common_checkpoints(seeds, [True, True])


def _claim_when_released(run_dir, barrier, outcomes, hold):
    barrier.wait()
    try:
        claim_run_dir(run_dir)
    except RunDirError:
        outcomes.put("refused")
        return
    outcomes.put("claimed")
    hold.wait(30)  # keep the claim while the others try
    release_run_dir(run_dir)


def _one_claimant_trials(tmp_path, trials: int, processes: int) -> None:
    import multiprocessing

    context = multiprocessing.get_context("fork")
    for trial in range(trials):
        run_dir = tmp_path / f"trial{trial}"
        barrier, outcomes, hold = context.Barrier(processes), context.Queue(), context.Event()
        workers = [
            context.Process(target=_claim_when_released, args=(run_dir, barrier, outcomes, hold))
            for _ in range(processes)
        ]
        for worker in workers:
            worker.start()
        results = sorted(outcomes.get(timeout=30) for _ in workers)
        hold.set()
        for worker in workers:
            worker.join(30)
        assert results == ["claimed"] + ["refused"] * (processes - 1), f"trial {trial}: {results}"


def test_processes_released_at_once_on_one_directory_give_one_claimant(tmp_path):
    _one_claimant_trials(tmp_path, trials=25, processes=4)


@pytest.mark.slow
def test_one_claimant_over_many_trials(tmp_path):
    _one_claimant_trials(tmp_path, trials=250, processes=6)


def test_a_refused_claim_leaves_the_directory_as_it_was(tmp_path):
    _results(tmp_path, "finished")
    before = sorted(p.name for p in tmp_path.iterdir())
    for resume in (False, True, "auto"):
        with pytest.raises(RunDirError):
            claim_run_dir(tmp_path, resume=resume)
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no lock file left behind
    _results(tmp_path, "killed")

    def other_settings(resuming):
        raise RunDirError("other settings")

    (tmp_path / CHECKPOINT_NAME).parent.mkdir()
    (tmp_path / CHECKPOINT_NAME).write_bytes(b"x")
    with pytest.raises(RunDirError, match="other settings"):
        claim_run_dir(tmp_path, resume=True, check=other_settings)
    assert not (tmp_path / LOCK_NAME).exists()
    (tmp_path / "file").write_text("")
    with pytest.raises(RunDirError, match="is a file"):
        claim_run_dir(tmp_path / "file")


def test_resume_auto_passes_over_a_finished_run_only_with_its_settings_and_stack(tmp_path):
    import json

    import pytest

    from spoil_torchrl.runs.directory import RunDirError
    from spoil_torchrl.runs.resume import finished_already
    from spoil_torchrl.stack import current_stack

    run = tmp_path / "cell"
    run.mkdir()
    (run / "config.yaml").write_text("seed: 0\n")
    (run / "results.json").write_text(json.dumps({"status": "finished", "stack": current_stack()}))
    assert finished_already(run, "seed: 0\n", "auto")["status"] == "finished"
    assert (
        finished_already(run, "seed: 0\n", False) is None and finished_already(run, "seed: 0\n", True) is None
    )
    (run / "results.json").write_text(
        json.dumps({"status": "finished", "stack": dict(current_stack(), mujoco="0.1")})
    )
    with pytest.raises(RunDirError, match="finished on another software stack"):
        finished_already(run, "seed: 0\n", "auto")
    (run / "results.json").write_text(json.dumps({"status": "failed"}))
    assert finished_already(run, "seed: 0\n", "auto") is None  # a failed cell is run again
