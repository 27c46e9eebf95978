"""PPO / PPO-Lagrangian training loop: a tiny run end to end, checkpoints and the Lagrange update."""

from __future__ import annotations

import functools
import importlib.util
import json
from pathlib import Path

import pytest
import torch

from spoil_torchrl.experts.ppo import EpisodeTracker, PPOConfig, train_ppo


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


needs_safety_gymnasium = pytest.mark.skipif(
    importlib.util.find_spec("safety_gymnasium") is None, reason="safety-gymnasium not installed"
)


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


def _tiny_config(**changes):
    base = dict(
        total_frames=2000,
        frames_per_batch=500,
        epochs=1,
        minibatch_size=250,
        hidden_cells=(16,),
        checkpoint_every=2,
        record_episodes=1,
        lagrangian=True,
        cost_limit=0.0,
    )
    return PPOConfig(**(base | changes))


def _train(run_dir, config, resume=False):
    from spoil_torchrl.envs import make_env

    return train_ppo(
        functools.partial(make_env, "SafetyPointCircle1-v0"),
        28,
        2,
        config,
        run_dir,
        progress=False,
        resume=resume,
        env_id="SafetyPointCircle1-v0",
    )


def _without_times(path):
    return [
        {k: v for k, v in json.loads(line).items() if k != "seconds"}
        for line in path.read_text().splitlines()
    ]


@needs_safety_gymnasium
@pytest.mark.parametrize(("normalize", "num_envs"), [(False, 1), (True, 1), (False, 2)])
def test_killed_training_resumes_to_the_uninterrupted_policies(tmp_path, monkeypatch, normalize, num_envs):
    # num_envs=2: every batch from two environments in lockstep, 500 frames (one episode) each
    from spoil_torchrl.experts import ppo as ppo_module
    from spoil_torchrl.experts.replay import read_replay
    from spoil_torchrl.zoo import load_policy

    _train(
        tmp_path / "whole",
        _tiny_config(
            normalize_observations=normalize,
            num_envs=num_envs,
            frames_per_batch=500 * num_envs,
            total_frames=2000 * num_envs,
        ),
    )
    update = ppo_module.ppo_update

    def killed_in_batch_four(learner, batch, config, index, cost, **kwargs):
        if index == 3:  # after batch 3 was logged, but the last training state is batch 2's
            raise KeyboardInterrupt("killed")
        return update(learner, batch, config, index, cost, **kwargs)

    monkeypatch.setattr(ppo_module, "ppo_update", killed_in_batch_four)
    with pytest.raises(KeyboardInterrupt):
        _train(
            tmp_path / "cut",
            _tiny_config(
                normalize_observations=normalize,
                num_envs=num_envs,
                frames_per_batch=500 * num_envs,
                total_frames=2000 * num_envs,
            ),
        )
    assert json.loads((tmp_path / "cut" / "results.json").read_text())["status"] == "interrupted"
    assert len(_without_times(tmp_path / "cut" / "log.jsonl")) == 3
    monkeypatch.setattr(ppo_module, "ppo_update", update)
    _train(
        tmp_path / "cut",
        _tiny_config(
            normalize_observations=normalize,
            num_envs=num_envs,
            frames_per_batch=500 * num_envs,
            total_frames=2000 * num_envs,
        ),
        resume=True,
    )

    whole, cut = tmp_path / "whole", tmp_path / "cut"
    names = sorted(p.name for p in whole.glob("ckpt_*.pt"))
    assert names == sorted(p.name for p in cut.glob("ckpt_*.pt")) and len(names) == 2
    for name in names:
        a, b = torch.load(whole / name, weights_only=True), torch.load(cut / name, weights_only=True)
        assert a.keys() == b.keys()
        for key in a["actor"]:
            assert torch.equal(a["actor"][key], b["actor"][key]), (name, key)
    assert _without_times(cut / "log.jsonl") == _without_times(whole / "log.jsonl")  # every batch once
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
    from spoil_torchrl.experts import ppo as ppo_module
    from spoil_torchrl.trainers import offline

    _train(tmp_path / "whole", _tiny_config(checkpoint_every=4))
    update = ppo_module.ppo_update

    def sigterm_in_batch_two(learner, batch, config, index, cost, **kwargs):
        result = update(learner, batch, config, index, cost, **kwargs)
        if index == 1:  # what stop_on_signals' handler records when SIGTERM arrives
            monkeypatch.setattr(offline, "_stop_reason", "signal SIGTERM")
        return result

    monkeypatch.setattr(ppo_module, "ppo_update", sigterm_in_batch_two)
    with pytest.raises(KeyboardInterrupt, match="SIGTERM"):
        _train(tmp_path / "cut", _tiny_config(checkpoint_every=4))
    monkeypatch.setattr(offline, "_stop_reason", None)
    monkeypatch.setattr(ppo_module, "ppo_update", update)
    assert json.loads((tmp_path / "cut" / "results.json").read_text())["status"] == "interrupted"
    _train(tmp_path / "cut", _tiny_config(checkpoint_every=4), resume=True)
    results = json.loads((tmp_path / "cut" / "results.json").read_text())
    assert results["resumed_at"] == [1000]  # the state of batch 2 (not a checkpoint batch) was kept
    a = torch.load(tmp_path / "whole" / "ckpt_000002000.pt", weights_only=True)["actor"]
    b = torch.load(tmp_path / "cut" / "ckpt_000002000.pt", weights_only=True)["actor"]
    assert all(torch.equal(a[k], b[k]) for k in a)


@needs_safety_gymnasium
def test_resume_refuses_other_settings(tmp_path):
    from spoil_torchrl.runs.checkpoint import CheckpointError

    _train(tmp_path, _tiny_config(total_frames=1000))
    with pytest.raises(CheckpointError, match="ppo.actor_lr"):
        _train(tmp_path, _tiny_config(total_frames=1000, actor_lr=1e-3), resume=True)


@needs_safety_gymnasium
def test_diverged_training_fails_with_one_line(tmp_path):
    from spoil_torchrl.divergence import TrainingDiverged

    with pytest.raises(TrainingDiverged, match="batch 0: .* not finite"):
        _train(tmp_path, _tiny_config(actor_lr=1e30, critic_lr=1e30, max_grad_norm=1e30))
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
    assert _without_times(tmp_path / "cut" / "log.jsonl") == _without_times(tmp_path / "whole" / "log.jsonl")
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


def test_running_observation_statistics_equal_the_batch_statistics():
    from spoil_torchrl.experts.ppo_update import PPOLearner

    learner = PPOLearner(3, 1, PPOConfig(hidden_cells=(4,), normalize_observations=True))
    x = torch.randn(1000, 3, dtype=torch.float64) * torch.tensor([1.0, 10.0, 0.1]) + 5.0
    for part in x.split([100, 400, 500]):
        learner.observe(part.float())
    assert torch.allclose(learner.obs_mean, x.float().double().mean(0), atol=1e-6)
    assert torch.allclose(learner.norm.scale, x.float().std(0, unbiased=False) + 1e-3, rtol=1e-4)


def test_lockstep_batches_count_and_record_each_environment_s_own_episodes(tmp_path):
    """A [num_envs, T] batch: an environment's episode cut at the batch's end is neither counted nor recorded,
    and never joined to the next environment's first episode."""
    from tensordict import TensorDict

    from spoil_torchrl.experts.replay import ReplayRecorder, read_replay

    # env 0: an episode of 2 steps, then 2 steps cut; env 1: episodes of 1 and 3 steps
    done = torch.tensor([[False, True, False, False], [True, False, False, True]]).unsqueeze(-1)
    reward = torch.arange(8.0).reshape(2, 4, 1)
    batch = TensorDict(
        {
            "observation": reward.clone(),
            "action": torch.zeros(2, 4, 1),
            "next": {
                "observation": reward + 0.5,
                "reward": reward,
                "cost": torch.ones(2, 4, 1),
                "terminated": torch.zeros_like(done),
                "truncated": done,
                "done": done,
            },
        },
        [2, 4],
    )
    mean_return, mean_cost, episodes = EpisodeTracker().update(batch)
    # returns 0+1 = 1 (env 0), 4 (env 1), 5+6+7 = 18 (env 1); costs 2, 1, 3
    assert (
        episodes == 3 and mean_return == pytest.approx((1 + 4 + 18) / 3) and mean_cost == pytest.approx(2.0)
    )
    assert ReplayRecorder(tmp_path, episodes=2).record(batch, 0) == 2
    assert read_replay(tmp_path)["rewards"].tolist() == [0.0, 1.0, 4.0]  # env 0's episode, then env 1's first
    assert ReplayRecorder(tmp_path, episodes=5).record(batch, 0) == 3
    assert read_replay(tmp_path)["rewards"].tolist() == [0.0, 1.0, 4.0, 5.0, 6.0, 7.0]


def test_num_envs_must_split_the_batch():
    with pytest.raises(ValueError, match="does not split over ppo.num_envs = 3"):
        PPOConfig(frames_per_batch=1000, minibatch_size=100, num_envs=3)
    with pytest.raises(ValueError, match="num_envs"):
        PPOConfig(num_envs=0)


def test_lockstep_refuses_batches_too_short_for_one_episode(tmp_path):
    config = PPOConfig(total_frames=4000, frames_per_batch=4000, minibatch_size=500, num_envs=16)
    with pytest.raises(ValueError, match="250 steps per environment and batch, fewer than one"):
        _train(tmp_path / "run", config)
    assert not (tmp_path / "run").exists()  # refused before anything is written


@needs_safety_gymnasium
def test_omnisafe_options_stop_epochs_on_kl_decay_the_actor_rate_and_standardise_separately(
    tmp_path, monkeypatch
):
    from spoil_torchrl.experts import ppo as ppo_module
    from spoil_torchrl.experts import ppo_update as update_module

    seen = {"lr": [], "advantage_std": []}
    original = update_module.ppo_update

    def watched(learner, batch, config, index, cost, *, batches=1):
        epochs = original(learner, batch, config, index, cost, batches=batches)
        seen["lr"].append(learner.optim.param_groups[0]["lr"])
        seen["advantage_std"].append(float(batch["advantage"].std()))
        return epochs

    monkeypatch.setattr(ppo_module, "ppo_update", watched)
    config = _tiny_config(
        epochs=20, actor_lr=3e-2, target_kl=1e-6, lr_decay=True, advantage_standardization="separate"
    )
    log = _train(tmp_path / "run", config)
    assert [line["epochs"] for line in log] == [1, 1, 1, 1]  # a large step passes a tiny KL target at once
    assert seen["lr"] == pytest.approx([3e-2 * (1 - i / 4) for i in range(4)])
    # lambda > 0 (cost limit 0): the combination of two standardised advantages is not standardised again
    assert any(abs(std - 1.0) > 1e-3 for std in seen["advantage_std"])
    with pytest.raises(ValueError, match="expected combined or separate"):
        PPOConfig(advantage_standardization="both")
    with pytest.raises(ValueError, match="target_kl"):
        PPOConfig(target_kl=0.0)
    with pytest.raises(ValueError, match="lr_decay"):
        PPOConfig(lr_decay="yes")


@needs_safety_gymnasium
def test_fixed_cost_penalty_trains_on_the_penalised_advantage_with_a_fixed_multiplier(tmp_path, monkeypatch):
    from spoil_torchrl.experts import ppo as ppo_module
    from spoil_torchrl.experts import ppo_update as update_module

    seen = []
    original = update_module.ppo_update

    def watched(learner, batch, config, index, cost, *, batches=1):
        epochs = original(learner, batch, config, index, cost, batches=batches)
        reward_advantage = batch["value_target"] - batch["state_value"]  # GAE's target is advantage + value
        seen.append((reward_advantage, batch["cost_advantage"].clone(), batch["advantage"].clone()))
        return epochs

    monkeypatch.setattr(ppo_module, "ppo_update", watched)
    beta = 2.5
    log = _train(tmp_path / "penalty", _tiny_config(lagrangian=False, cost_penalty=beta))
    # cost limit 0 and a random policy that leaves the band: a Lagrangian multiplier would have moved
    assert [line["lagrange"] for line in log] == [beta] * 4
    for reward_advantage, cost_advantage, advantage in seen:
        assert cost_advantage.abs().max() > 0  # the penalty has something to act on
        penalised = reward_advantage - beta * cost_advantage  # the advantage of reward - beta * cost
        expected = (penalised - penalised.mean()) / (penalised.std() + 1e-8)
        torch.testing.assert_close(advantage, expected, rtol=1e-4, atol=1e-4)
    plain = _train(tmp_path / "plain", _tiny_config(lagrangian=False))
    assert [line["lagrange"] for line in plain] == [0.0] * 4
    penalised_actor = torch.load(tmp_path / "penalty" / "ckpt_000002000.pt", weights_only=True)["actor"]
    plain_actor = torch.load(tmp_path / "plain" / "ckpt_000002000.pt", weights_only=True)["actor"]
    assert any(not torch.equal(penalised_actor[k], plain_actor[k]) for k in plain_actor)
    assert json.loads((tmp_path / "penalty" / "config.json").read_text())["cost_penalty"] == beta


def test_ppo_config_refuses_a_bad_cost_penalty():
    with pytest.raises(ValueError, match="cost_penalty = -1.0: expected a finite number >= 0"):
        PPOConfig(cost_penalty=-1.0)
    with pytest.raises(ValueError, match="cost_penalty = 'high'"):
        PPOConfig(cost_penalty="high")
    with pytest.raises(ValueError, match="needs ppo.lagrangian=false"):
        PPOConfig(cost_penalty=1.0, lagrangian=True)
    assert PPOConfig(cost_penalty=1).cost_penalty == 1


@needs_safety_gymnasium
def test_an_expert_can_train_against_one_constraints_own_cost():
    """ppo.cost_component: the batches' cost is that wall's (the same trajectories, never above the task's
    cost, which is the union of the walls'); bad choices are named."""
    from spoil_torchrl.experts.lockstep import LockstepCollector
    from spoil_torchrl.modules import make_actor

    actor = make_actor(28, 2, hidden_cells=(8,), distribution="tanh_normal", return_log_prob=True)
    batches = {}
    for component in (None, "x_wall"):
        collector = LockstepCollector("SafetyPointCircle2-v0", num_envs=2, cost_component=component)
        torch.manual_seed(0)
        batches[component] = collector.batch(actor, frames=1000, seed=3)
        collector.close()
    assert torch.equal(batches[None]["observation"], batches["x_wall"]["observation"])
    assert bool((batches["x_wall"]["next", "cost"] <= batches[None]["next", "cost"]).all())
    with pytest.raises(ValueError, match="needs ppo.num_envs > 1"):
        PPOConfig(cost_component="x_wall")
    with pytest.raises(ValueError, match="SafetyPointCircle1-v0 has no per-constraint costs"):
        LockstepCollector("SafetyPointCircle1-v0", num_envs=2, cost_component="x_wall")
    collector = LockstepCollector("SafetyPointCircle2-v0", num_envs=2, cost_component="z_wall")
    with pytest.raises(ValueError, match=r"constraints are \['x_wall', 'y_wall'\]"):
        collector.batch(actor, frames=10, seed=0)
    collector.close()


@needs_safety_gymnasium
def test_init_actor_starts_the_training_from_a_policy_and_refuses_another_shape(tmp_path):
    """ppo.init_actor: the first batch is collected by the given policy's weights (its checkpoint holds them);
    a policy of another width, or a missing one, is refused with the setting's name."""
    from spoil_torchrl.envs import make_env

    make = functools.partial(make_env, "SafetyPointCircle1-v0", seed=0)
    tiny = dict(frames_per_batch=500, epochs=1, minibatch_size=250, checkpoint_every=1, hidden_cells=(8,))
    train_ppo(make, 28, 2, PPOConfig(total_frames=1000, **tiny), tmp_path / "a", progress=False)
    source = tmp_path / "a" / "ckpt_000001000.pt"  # trained for a batch: not what a fresh seed-1 actor is
    config = PPOConfig(total_frames=500, seed=1, init_actor=str(source), **tiny)
    train_ppo(make, 28, 2, config, tmp_path / "b", progress=False)
    started = torch.load(tmp_path / "b" / "ckpt_000000500.pt", weights_only=True)["actor"]
    given = torch.load(source, weights_only=True)["actor"]
    assert all(torch.equal(started[k], given[k]) for k in given)
    fresh = PPOConfig(total_frames=500, seed=1, **tiny)
    train_ppo(make, 28, 2, fresh, tmp_path / "c", progress=False)
    other = torch.load(tmp_path / "c" / "ckpt_000000500.pt", weights_only=True)["actor"]
    assert not all(torch.equal(other[k], given[k]) for k in given)
    wide = PPOConfig(total_frames=500, init_actor=str(source), **(tiny | {"hidden_cells": (16,)}))
    with pytest.raises(ValueError, match=r"is a tanh_normal policy with hidden cells \[8\]"):
        train_ppo(make, 28, 2, wide, tmp_path / "d", progress=False)
    with pytest.raises(ValueError, match="ppo.init_actor with ppo.normalize_observations=true"):
        PPOConfig(total_frames=500, init_actor=str(source), normalize_observations=True, **tiny)
    missing = PPOConfig(total_frames=500, init_actor="zoo:no-such-policy", **tiny)
    with pytest.raises(ValueError, match="ppo.init_actor = 'zoo:no-such-policy'"):
        train_ppo(make, 28, 2, missing, tmp_path / "e", progress=False, env_id="SafetyPointCircle1-v0")
