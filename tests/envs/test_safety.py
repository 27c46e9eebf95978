"""Safety-Gymnasium environments: the Python >= 3.11 import fix, specs, the cost key and the tasks' cost rules."""

from __future__ import annotations

import importlib.util
import sys

import numpy as np
import pytest
import torch

pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("safety_gymnasium") is None, reason="safety-gymnasium not installed (EXTRAS=dev)"
)


def test_import_fix_makes_colours_hashable_and_keeps_their_values():
    from spoil_torchrl.envs import import_safety_gymnasium
    from spoil_torchrl.envs.compat import COLOR_MODULE, HashableArray

    sg = import_safety_gymnasium()
    colors = sys.modules[COLOR_MODULE].COLOR
    assert all(isinstance(v, HashableArray) and hash(v) for v in colors.values())
    np.testing.assert_array_equal(np.asarray(colors["hazard"]), [0, 0, 1, 0.25])
    assert hasattr(sg, "make")


@pytest.mark.parametrize("env_id", ["SafetyPointCircle1-v0", "SafetyHalfCheetahVelocity-v1"])
def test_specs_and_cost_key(env_id):
    from torchrl.envs.utils import check_env_specs

    from spoil_torchrl.envs import make_env
    from spoil_torchrl.tasks import get_env_task

    env = make_env(env_id, seed=0)
    check_env_specs(env)
    td = env.rollout(20)
    assert td["next", "cost"].shape == (20, 1) and td["next", "cost"].dtype == torch.float32
    assert td["observation"].dtype == torch.float32
    assert td["observation"].shape[-1] == get_env_task(env_id).observation_dim
    env.close()


def test_point_circle1_cost_is_leaving_the_band():
    from spoil_torchrl.envs import make_safety_gymnasium

    env = make_safety_gymnasium("SafetyPointCircle1-v0")
    env.reset(seed=0)
    agent = env.unwrapped.task.agent
    xs, costs = [], []
    for _ in range(300):  # full thrust: the agent leaves the |x| <= 1.125 band
        _, _, _, _, info = env.step(np.array([1.0, 0.0]))
        xs.append(agent.pos[0])
        costs.append(float(info["cost"][0]))
    outside = np.abs(np.array(xs)) > 1.125
    assert outside.any() and (~outside).any()
    np.testing.assert_array_equal(outside, np.array(costs) > 0)


def test_velocity_cost_is_speeding():
    from spoil_torchrl.envs import make_safety_gymnasium
    from spoil_torchrl.tasks import get_env_task

    threshold = get_env_task("SafetyHalfCheetahVelocity-v1").velocity_threshold
    env = make_safety_gymnasium("SafetyHalfCheetahVelocity-v1")
    env.reset(seed=0)
    sim = env.unwrapped
    rng = np.random.default_rng(0)
    velocity, costs = [], []
    for t in range(60):
        if t % 10 == 0:  # push the body forward at a random speed on either side of the limit
            qvel = sim.data.qvel.copy()
            qvel[0] = rng.uniform(0.0, 2.0 * threshold)
            sim.set_state(sim.data.qpos.copy(), qvel)
        _, _, _, _, info = env.step(rng.uniform(-1, 1, 6))
        velocity.append(info["x_velocity"])
        costs.append(float(info["cost"][0]))
    speeding = np.array(velocity) > threshold
    assert speeding.any() and (~speeding).any()
    np.testing.assert_array_equal(speeding, np.array(costs) > 0)


def test_fast_reset_changes_no_physics():
    from spoil_torchrl.envs import make_safety_gymnasium
    from spoil_torchrl.envs.compat import fast_reset_enabled

    def trajectory(fast: bool):
        env = make_safety_gymnasium("SafetyPointCircle1-v0", fast_reset=fast)
        obs, _ = env.reset(seed=3)
        rng = np.random.default_rng(0)
        out = [obs]
        for _ in range(100):
            obs, reward, _, _, info = env.step(rng.uniform(-1, 1, 2))
            out.append(np.concatenate([obs, [reward, info["cost"][0]]]))
        return out

    slow = trajectory(False)
    assert not fast_reset_enabled()
    fast = trajectory(True)
    assert fast_reset_enabled()
    for a, b in zip(slow, fast, strict=True):
        np.testing.assert_array_equal(a, b)
