"""What the expert-training tests share: a tiny PPO configuration, its training on PointCircle1, and the skip
without Safety-Gymnasium."""

from __future__ import annotations

import functools
import importlib.util
import json

import pytest

from spoil_torchrl.experts.ppo import PPOConfig, train_ppo

needs_safety_gymnasium = pytest.mark.skipif(
    importlib.util.find_spec("safety_gymnasium") is None, reason="safety-gymnasium not installed"
)


def tiny_config(**changes):
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


def train(run_dir, config, resume=False):
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


def without_times(path):
    return [
        {k: v for k, v in json.loads(line).items() if k != "seconds"}
        for line in path.read_text().splitlines()
    ]
