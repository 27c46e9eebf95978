"""Safety-Gymnasium environments: the six controlled tasks, specs, the cost key and the tasks' cost rules."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("safety_gymnasium") is None, reason="safety-gymnasium not installed (EXTRAS=dev)"
)


#: The six tasks of the paper's controlled experiments.
CONTROLLED_TASKS = (
    "SafetyPointCircle1-v0",
    "SafetyPointCircle2-v0",
    "SafetyHopperVelocity-v1",
    "SafetyHalfCheetahVelocity-v1",
    "SafetyWalker2dVelocity-v1",
    "SafetyAntVelocity-v1",
)


@pytest.mark.parametrize("env_id", CONTROLLED_TASKS)
def test_the_controlled_tasks_reset_step_and_render(env_id):
    from spoil_torchrl.eval.env_scene import make_render_env
    from spoil_torchrl.tasks import get_env_task

    try:
        env = make_render_env(env_id, 48)  # resets and renders once, or says why it cannot
    except RuntimeError as err:
        if "OpenGL" in str(err) and "TypeError" not in str(err):
            pytest.skip(f"no OpenGL context here: {err}")
        raise
    try:
        task = get_env_task(env_id)
        obs, _ = env.reset(seed=1)
        assert obs.shape == (task.observation_dim,)
        rng = np.random.default_rng(0)
        first = env.render()
        for _ in range(20):
            obs, reward, terminated, truncated, info = env.step(rng.uniform(-1, 1, task.action_dim))
            assert np.isfinite(obs).all() and np.isfinite(reward) and info["cost"].shape == (1,)
        frame = env.render()
        assert frame.shape == (48, 48, 3) and frame.dtype == np.uint8 and frame.std() > 0
        assert not np.array_equal(frame, first)  # the scene moved
    finally:
        env.close()


def test_navigation_frames_without_the_offscreen_size_patch_fail(tmp_path):
    from spoil_torchrl.envs.compat import PATCHES

    if not next(p for p in PATCHES if p.name == "offscreen-size").needed():
        pytest.skip("offscreen-size not needed here (gymnasium < 1.0)")
    code = (
        "from spoil_torchrl.eval.env_scene import make_render_env\n"
        "make_render_env('SafetyPointCircle1-v0', 32)\n"
    )
    root = str(Path(__file__).resolve().parents[2])
    env = dict(os.environ, SPOIL_TORCHRL_SKIP_PATCHES="offscreen-size", PYTHONPATH=root)
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=300, cwd=tmp_path
    )
    assert proc.returncode != 0 and "TypeError" in proc.stderr and "width" in proc.stderr


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
    from spoil_torchrl.envs.fast_reset import fast_reset_enabled

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
