"""Every setting a user can get wrong is refused with its name, the value given and what it must be: the main
recipe's (``check_settings``) and the expert trainer's (``PPOConfig``)."""

from __future__ import annotations

import pytest

from spoil_torchrl.runs.settings import SettingsError, check_settings

SETTING_CASES = [
    ({"algo": {"kappa": 1.5}}, "algo.kappa = 1.5"),
    ({"algo": {"init_lagrange": float("nan")}}, "algo.init_lagrange = nan: expected a finite number"),
    (
        {"algo": {"name": "coptidice", "init_lagrange": 0.0}},
        "algo.init_lagrange = 0.0: COptiDICE learns its logarithm; expected a finite number > 0",
    ),
    (
        {"seed": 3, "seeds": [0, 1]},
        "seed = 3 with seeds = [0, 1]: a seeds=[...] run trains exactly those seeds",
    ),
    ({"algo": {"kappa": 0.0}}, "algo.kappa = 0.0"),
    ({"algo": {"gamma": 1.0}}, "algo.gamma = 1.0"),
    ({"algo": {"nu_lr": -1e-3}}, "algo.nu_lr = -0.001"),
    ({"algo": {"discriminator": {"lr": 0.0}}}, "algo.discriminator.lr = 0.0"),
    (
        {"algo": {"discriminator": {"gradient_penalty": {"safe": -1.0}}}},
        "algo.discriminator.gradient_penalty",
    ),
    ({"algo": {"hidden_cells": [256, 0]}}, "algo.hidden_cells"),
    ({"algo": {"alpha": "big"}}, "algo.alpha = 'big'"),
    ({"algo": {"eta": 1.2}}, "algo.eta = 1.2"),
    ({"train": {"discriminator_steps": 0}}, "train.discriminator_steps = 0"),
    ({"train": {"lr": float("nan")}}, "train.lr = nan"),
    ({"train": {"batch_size": 12.5}}, "train.batch_size = 12.5"),
    (
        {"train": {"matmul_precision": "bf16"}},
        "train.matmul_precision = 'bf16': expected highest | high | medium",
    ),
    (
        {"train": {"penalty_form": "fast"}},
        "train.penalty_form = 'fast': expected autograd | relu_chain",
    ),
    ({"threads": 0}, "threads = 0"),
    ({"device": "gpu"}, "device = 'gpu': expected cpu or cuda"),
    ({"dataset": {"n_safe": 0}}, "dataset.n_safe = 0"),
    ({"dataset": {"safeness": 1.5}}, "dataset.safeness = 1.5"),
    ({"dataset": {"n_unlabeled": -5}}, "dataset.n_unlabeled = -5"),
    ({"dataset": {"cost_threshold": -1.0}}, "dataset.cost_threshold = -1.0"),
    ({"dataset": {"scheme": "magic"}}, "dataset.scheme = 'magic'"),
    (
        {"algo": {"name": "spoildice"}, "dataset": {"constraints": ["x_wall", "all"]}},
        "dataset.constraints = ['x_wall', 'all']: expected null or a list of distinct constraint names",
    ),
    ({"seed": -1}, "seed = -1"),
    ({"normalize_observations": "no"}, "normalize_observations = 'no': expected true or false"),
    ({"progress": 0}, "progress = 0: expected true or false"),
    ({"eval": {"frames": "off"}}, "eval.frames = 'off'"),
    ({"train": {"checkpoint": "no"}}, "train.checkpoint = 'no'"),
    ({"train": {"compile": 1}}, "train.compile = 1"),
    ({"dataset": {"generate": "yes"}}, "dataset.generate = 'yes'"),
    ({"threads": 999}, "threads = 999: expected an integer from 1 to"),
    ({"task": {"eval_num_envs": 0}}, "task.eval_num_envs = 0"),
    ({"dataset": {"return_range": [0, 40, -7]}}, "dataset.return_range = [0, 40, -7]"),
    ({"dataset": {"return_range": "abc"}}, "dataset.return_range = 'abc'"),
    ({"dataset": {"return_range": [40, 0]}}, "dataset.return_range = [40, 0]"),
    ({"dataset": {"return_range": [0, float("inf")]}}, "dataset.return_range = [0, inf]"),
    ({"dataset": {"performance": "half"}}, "dataset.performance = 'half'"),
    ({"dataset": {"return_quantile": 2}}, "dataset.return_quantile = 2"),
    ({"dataset": {"n_performant": 2.5}}, "dataset.n_performant = 2.5"),
    ({"seeds": [0, 0]}, "seeds = [0, 0]"),
    ({"seeds": []}, "seeds = []"),
    ({"threads": "two"}, "threads = 'two'"),
    ({"train": {"eval_interval": 0}}, "train.eval_interval = 0"),
    ({"train": {"steps": 1.5}}, "train.steps = 1.5"),
    ({"train": {"log_interval": -1}}, "train.log_interval = -1"),
    ({"algo": {"hidden_cells": "256"}}, "algo.hidden_cells = '256'"),
    ({"algo": {"standardize_reward": "yes"}}, "algo.standardize_reward = 'yes'"),
    ({"algo": {"distribution": "gaussian"}}, "algo.distribution = 'gaussian': expected tanh_normal"),
    (
        {"task": {"env_id": "SafetyPointCircle1-v0"}, "algo": {"distribution": "categorical"}},
        "algo.distribution = 'categorical': SafetyPointCircle1-v0's actions are continuous",
    ),
]


@pytest.mark.parametrize("settings, match", SETTING_CASES)
def test_a_bad_setting_is_named(settings, match):
    with pytest.raises(SettingsError, match=match.replace("[", r"\[").replace(".", r"\.")):
        check_settings({"seed": 0, "threads": 1, **settings})


@pytest.mark.parametrize("distribution", ["tanh_normal", "normal"])
def test_a_distribution_of_continuous_actions_is_taken_for_a_task(distribution):
    task = {"env_id": "SafetyHopperVelocity-v1", "eval_num_envs": 1}
    check_settings({"seed": 0, "threads": 1, "task": task, "algo": {"distribution": distribution}})


@pytest.mark.parametrize(
    "change, match",
    [
        ({"lagrangian": "no"}, "ppo.lagrangian = 'no'"),
        ({"actor_lr": -1.0}, "ppo.actor_lr = -1.0"),
        ({"gamma": float("nan")}, "ppo.gamma = nan"),
        ({"epochs": 0}, "ppo.epochs = 0"),
    ],
)
def test_expert_settings_are_checked(change, match):
    from spoil_torchrl.experts import PPOConfig

    with pytest.raises(ValueError, match=match.replace(".", r"\.")):
        PPOConfig(**change)
