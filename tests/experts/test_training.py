"""PPO / PPO-Lagrangian training loop: a tiny run end to end, checkpoints, the Lagrange update, and exact
resumption after a kill or SIGTERM."""

from __future__ import annotations

import functools
import json
from pathlib import Path

import pytest
import torch

from spoil_torchrl.experts.ppo import EpisodeTracker, PPOConfig, train_ppo
from tests.experts.helpers import needs_safety_gymnasium, tiny_config, train, without_times


def test_episode_tracker_spans_batches():
    from tensordict import TensorDict

    def batch(rewards, costs, dones):
        n = len(rewards)
        return TensorDict(
            {
                "next": {
                    "reward": torch.tensor(rewards).view(n, 1),
                    "cost": torch.tensor(costs).view(n, 1),
                    "done": torch.tensor(dones).view(n, 1),
                }
            },
            [n],
        )

    tracker = EpisodeTracker()
    assert tracker.update(batch([1.0, 1.0], [0.0, 1.0], [False, False]))[2] == 0
    ret, cost, n = tracker.update(batch([1.0, 2.0, 5.0], [1.0, 0.0, 3.0], [True, False, True]))
    # episode 1: rewards 1+1+1, costs 0+1+1; episode 2: rewards 2+5, costs 0+3
    assert (ret, cost, n) == (5.0, 2.5, 2)


@needs_safety_gymnasium
@pytest.mark.parametrize("lagrangian", [False, True])
def test_tiny_ppo_run_writes_checkpoints(tmp_path, lagrangian):
    from spoil_torchrl.envs import make_env
    from spoil_torchrl.modules import make_actor

    config = PPOConfig(
        total_frames=1000,
        frames_per_batch=500,
        epochs=1,
        minibatch_size=250,
        lagrangian=lagrangian,
        checkpoint_every=1,
        cost_limit=0.0,
    )
    log = train_ppo(
        functools.partial(make_env, "SafetyPointCircle1-v0", seed=0), 28, 2, config, tmp_path, progress=False
    )
    assert [line["frames"] for line in log] == [500, 1000]
    checkpoints = sorted(tmp_path.glob("ckpt_*.pt"))
    assert len(checkpoints) == 2
    state = torch.load(checkpoints[-1], weights_only=True)
    actor = make_actor(28, 2, hidden_cells=config.hidden_cells)
    actor.load_state_dict(state["actor"])
    assert json.loads((tmp_path / "config.json").read_text())["lagrangian"] == lagrangian
    lines = (tmp_path / "log.jsonl").read_text().splitlines()
    assert len(lines) == 2
    if lagrangian:  # cost limit 0 and a random policy that leaves the band: lambda must have grown
        assert log[-1]["lagrange"] > 0
    else:
        assert log[-1]["lagrange"] == 0


@needs_safety_gymnasium
@pytest.mark.parametrize(("normalize", "num_envs"), [(False, 1), (True, 1), (False, 2)])
def test_killed_training_resumes_to_the_uninterrupted_policies(tmp_path, monkeypatch, normalize, num_envs):
    # num_envs=2: every batch from two environments in lockstep, 500 frames (one episode) each
    from spoil_torchrl.experts import ppo as ppo_module
    from spoil_torchrl.experts.replay import read_replay
    from spoil_torchrl.zoo import load_policy

    settings = dict(
        normalize_observations=normalize,
        num_envs=num_envs,
        frames_per_batch=500 * num_envs,
        total_frames=2000 * num_envs,
    )
    train(tmp_path / "whole", tiny_config(**settings))
    update = ppo_module.ppo_update

    def killed_in_batch_four(learner, batch, config, index, cost, **kwargs):
        if index == 3:  # after batch 3 was logged, but the last training state is batch 2's
            raise KeyboardInterrupt("killed")
        return update(learner, batch, config, index, cost, **kwargs)

    monkeypatch.setattr(ppo_module, "ppo_update", killed_in_batch_four)
    with pytest.raises(KeyboardInterrupt):
        train(tmp_path / "cut", tiny_config(**settings))
    assert json.loads((tmp_path / "cut" / "results.json").read_text())["status"] == "interrupted"
    assert len(without_times(tmp_path / "cut" / "log.jsonl")) == 3
    monkeypatch.setattr(ppo_module, "ppo_update", update)
    train(tmp_path / "cut", tiny_config(**settings), resume=True)

    whole, cut = tmp_path / "whole", tmp_path / "cut"
    names = sorted(p.name for p in whole.glob("ckpt_*.pt"))
    assert names == sorted(p.name for p in cut.glob("ckpt_*.pt")) and len(names) == 2
    for name in names:
        a, b = torch.load(whole / name, weights_only=True), torch.load(cut / name, weights_only=True)
        assert a.keys() == b.keys()
        for key in a["actor"]:
            assert torch.equal(a["actor"][key], b["actor"][key]), (name, key)
    assert without_times(cut / "log.jsonl") == without_times(whole / "log.jsonl")  # every batch once
    replay_a, replay_b = read_replay(whole / "replay"), read_replay(cut / "replay")
    from spoil_torchrl.data.episodes import episodes_from_arrays
    from spoil_torchrl.data.labeling import replay_statistics

    table_h = replay_statistics(episodes_from_arrays(replay_a), 25.0, safe_optimal_return=40.0)
    assert table_h["trajectories"] == 4  # one recorded episode per batch
    assert all((replay_a[k] == replay_b[k]).all() for k in replay_a) and set(replay_a["batch"]) == {
        0,
        1,
        2,
        3,
    }
    results = json.loads((cut / "results.json").read_text())
    assert results["status"] == "finished" and results["resumed_at"] == [1000 * num_envs]
    assert results["frames"] == 2000 * num_envs
    policy, meta = load_policy(cut / names[-1], env_id="SafetyPointCircle1-v0")
    assert meta["observation_norm"] is normalize
    if normalize:  # the statistics of the batches before the last one, carried inside the policy
        norm = policy.module[0].module[0]
        assert bool((norm.scale > 0).all()) and not torch.equal(norm.loc, torch.zeros_like(norm.loc))


@needs_safety_gymnasium
def test_sigterm_keeps_the_batch_it_arrived_in_and_resumes_from_it(tmp_path, monkeypatch):
    from spoil_torchrl import stopping
    from spoil_torchrl.experts import ppo as ppo_module

    train(tmp_path / "whole", tiny_config(checkpoint_every=4))
    update = ppo_module.ppo_update

    def sigterm_in_batch_two(learner, batch, config, index, cost, **kwargs):
        result = update(learner, batch, config, index, cost, **kwargs)
        if index == 1:  # what stop_on_signals' handler records when SIGTERM arrives
            monkeypatch.setattr(stopping, "_stop_reason", "signal SIGTERM")
        return result

    monkeypatch.setattr(ppo_module, "ppo_update", sigterm_in_batch_two)
    with pytest.raises(KeyboardInterrupt, match="SIGTERM"):
        train(tmp_path / "cut", tiny_config(checkpoint_every=4))
    monkeypatch.setattr(stopping, "_stop_reason", None)
    monkeypatch.setattr(ppo_module, "ppo_update", update)
    assert json.loads((tmp_path / "cut" / "results.json").read_text())["status"] == "interrupted"
    train(tmp_path / "cut", tiny_config(checkpoint_every=4), resume=True)
    results = json.loads((tmp_path / "cut" / "results.json").read_text())
    assert results["resumed_at"] == [1000]  # the state of batch 2 (not a checkpoint batch) was kept
    a = torch.load(tmp_path / "whole" / "ckpt_000002000.pt", weights_only=True)["actor"]
    b = torch.load(tmp_path / "cut" / "ckpt_000002000.pt", weights_only=True)["actor"]
    assert all(torch.equal(a[k], b[k]) for k in a)


@needs_safety_gymnasium
def test_resume_refuses_other_settings(tmp_path):
    from spoil_torchrl.runs.checkpoint import CheckpointError

    train(tmp_path, tiny_config(total_frames=1000))
    with pytest.raises(CheckpointError, match="ppo.actor_lr"):
        train(tmp_path, tiny_config(total_frames=1000, actor_lr=1e-3), resume=True)


@needs_safety_gymnasium
def test_diverged_training_fails_with_one_line(tmp_path):
    from spoil_torchrl.divergence import TrainingDiverged

    with pytest.raises(TrainingDiverged, match="batch 0: .* not finite"):
        train(tmp_path, tiny_config(actor_lr=1e30, critic_lr=1e30, max_grad_norm=1e30))
    assert json.loads((tmp_path / "results.json").read_text())["status"] == "failed"


def test_ppo_config_refuses_impossible_sizes():
    with pytest.raises(ValueError, match="minibatch_size = 2000 is larger"):
        PPOConfig(frames_per_batch=1000, minibatch_size=2000)
    with pytest.raises(ValueError, match="record_episodes"):
        PPOConfig(record_episodes=-1)


@pytest.mark.slow
@needs_safety_gymnasium
def test_expert_recipe_killed_with_sigkill_resumes_exactly(tmp_path):
    import signal
    import subprocess
    import sys
    import time

    root = Path(__file__).resolve().parents[1]
    args = [
        sys.executable,
        str(root / "recipes" / "train_experts.py"),
        "ppo.total_frames=4000",
        "ppo.frames_per_batch=500",
        "ppo.minibatch_size=250",
        "ppo.epochs=2",
        "ppo.checkpoint_every=2",
        "threads=1",
        "progress=false",
    ]

    def start(run_dir, *extra):
        return subprocess.Popen(
            [*args, f"hydra.run.dir={run_dir}", *extra],
            cwd=tmp_path,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )

    whole = start(tmp_path / "whole")
    assert whole.wait(timeout=300) == 0, whole.stdout.read()[-2000:]
    cut = start(tmp_path / "cut")
    log = tmp_path / "cut" / "log.jsonl"
    deadline = time.monotonic() + 240
    while not (log.exists() and len(log.read_text().splitlines()) >= 5):  # past the state of batch 4
        assert cut.poll() is None and time.monotonic() < deadline
        time.sleep(0.01)
    cut.send_signal(signal.SIGKILL)
    cut.wait()
    resumed = start(tmp_path / "cut", "resume=auto")
    assert resumed.wait(timeout=300) == 0, resumed.stdout.read()[-2000:]
    a = torch.load(tmp_path / "whole" / "ckpt_000004000.pt", weights_only=True)["actor"]
    b = torch.load(tmp_path / "cut" / "ckpt_000004000.pt", weights_only=True)["actor"]
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert without_times(tmp_path / "cut" / "log.jsonl") == without_times(tmp_path / "whole" / "log.jsonl")
    assert json.loads((tmp_path / "cut" / "results.json").read_text())["resumed_at"] == [2000]
    term = start(tmp_path / "term")
    log = tmp_path / "term" / "log.jsonl"
    while not (log.exists() and len(log.read_text().splitlines()) >= 2):
        assert term.poll() is None and time.monotonic() < deadline + 240
        time.sleep(0.01)
    term.send_signal(signal.SIGTERM)
    output = term.communicate(timeout=120)[0]
    assert term.returncode != 0 and "Traceback" not in output, output[-2000:]
    assert "interrupted; continue with: python recipes/train_experts.py" in output
    assert json.loads((tmp_path / "term" / "results.json").read_text())["status"] == "interrupted"
    files = {p: p.read_bytes() for p in sorted((tmp_path / "term").rglob("*")) if p.is_file()}
    other = start(tmp_path / "term", "resume=true", "ppo.epochs=3")  # refused: other settings
    output = other.communicate(timeout=120)[0]
    assert other.returncode != 0 and "ppo.epochs" in output and "Traceback" not in output, output[-2000:]
    assert {p: p.read_bytes() for p in sorted((tmp_path / "term").rglob("*")) if p.is_file()} == files
    again = start(tmp_path / "cut", "resume=auto")  # a finished run is not trained again
    assert again.wait(timeout=120) == 0 and "finished already" in again.stdout.read()
    again = start(tmp_path / "cut", "resume=true")
    assert again.wait(timeout=120) != 0 and "has finished" in again.stdout.read()
