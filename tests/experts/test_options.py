"""The expert trainer's options: running observation statistics, environments in lockstep, OmniSafe's
PPO-Lagrangian settings, a fixed cost penalty, one constraint's own cost and a policy to start from."""

from __future__ import annotations

import functools
import json

import pytest
import torch

from spoil_torchrl.experts.ppo import EpisodeTracker, PPOConfig, train_ppo
from tests.experts.helpers import needs_safety_gymnasium, tiny_config, train


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
        train(tmp_path / "run", config)
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
    config = tiny_config(
        epochs=20, actor_lr=3e-2, target_kl=1e-6, lr_decay=True, advantage_standardization="separate"
    )
    log = train(tmp_path / "run", config)
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
    log = train(tmp_path / "penalty", tiny_config(lagrangian=False, cost_penalty=beta))
    # cost limit 0 and a random policy that leaves the band: a Lagrangian multiplier would have moved
    assert [line["lagrange"] for line in log] == [beta] * 4
    for reward_advantage, cost_advantage, advantage in seen:
        assert cost_advantage.abs().max() > 0  # the penalty has something to act on
        penalised = reward_advantage - beta * cost_advantage  # the advantage of reward - beta * cost
        expected = (penalised - penalised.mean()) / (penalised.std() + 1e-8)
        torch.testing.assert_close(advantage, expected, rtol=1e-4, atol=1e-4)
    plain = train(tmp_path / "plain", tiny_config(lagrangian=False))
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
