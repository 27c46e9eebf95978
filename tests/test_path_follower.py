"""The scripted ellipse follower (spoil_torchrl/zoo/path_follower.py): the pose it reads off the observation is
the simulator's, and on SafetyPointCircle2 it keeps one pair of walls and crosses the other, lap after lap."""

from __future__ import annotations

import importlib.util
import math

import numpy as np
import pytest
import torch

from spoil_torchrl.zoo.path_follower import EllipseFollower, circle_pose, ellipse_policy

needs_safety_gymnasium = pytest.mark.skipif(
    importlib.util.find_spec("safety_gymnasium") is None, reason="safety-gymnasium not installed (EXTRAS=dev)"
)
ENV_ID = "SafetyPointCircle2-v0"


def _episodes(spec: str, episodes: int = 2) -> dict[str, np.ndarray]:
    from spoil_torchrl.envs.cost_components import cost_components
    from spoil_torchrl.envs.rollout import rollout
    from spoil_torchrl.eval.env_scene import agent_pose

    return rollout(
        ENV_ID,
        ellipse_policy(spec),
        episodes,
        seed=3,
        num_envs=episodes,
        progress=False,
        record=agent_pose,
        components=cost_components(ENV_ID),
    )


@needs_safety_gymnasium
@pytest.mark.parametrize(
    "spec, kept, crossed", [("ellipse:0.9,1.6", "x", "y"), ("ellipse:1.6,0.9", "y", "x")]
)
def test_the_follower_keeps_one_pair_of_walls_and_crosses_the_other(spec, kept, crossed):
    data = _episodes(spec)
    # the pose read off every observation is the simulator's (position and heading)
    pose = data["recorded"]
    x, y, heading = circle_pose(torch.as_tensor(data["observations"], dtype=torch.float64))
    assert np.allclose(x.numpy(), pose[:, 0], atol=1e-5) and np.allclose(y.numpy(), pose[:, 1], atol=1e-5)
    qz, qw = pose[:, 5], pose[:, 6]  # a turn about z: heading = 2 atan2(qz, qw)
    assert np.allclose(np.cos(heading.numpy() - 2 * np.arctan2(qz, qw)), 1.0, atol=1e-8)
    # per episode: never past its own walls (1.125), past the others' limit of 25 steps, and going round
    ends = np.flatnonzero(data["timeouts"] | data["terminals"]) + 1
    for part in np.split(np.arange(len(x)), ends[:-1]):
        assert data[f"cost_{kept}_wall"][part].sum() == 0
        assert data[f"cost_{crossed}_wall"][part].sum() > 100
        assert data["rewards"][part].sum() > 25  # safe-high's return is about 39, a standing robot's 0
    wall = 0 if kept == "x" else 1
    assert np.abs(pose[:, wall]).max() < 1.125 < np.abs(pose[:, 1 - wall]).max()


def test_pose_and_action_are_batched_and_the_spec_is_checked():
    obs = torch.zeros(3, 28)
    obs[:, 9:11] = torch.tensor([-0.5, 0.0])  # heading +90 degrees: the robot's x axis is the world's y
    obs[:, 12 + 4] = (
        1 - 1.0 / 6
    )  # the centre 1 away at +90 degrees in the robot's frame: behind it in world x
    x, y, heading = circle_pose(obs)
    assert torch.allclose(x, torch.ones(3), atol=1e-6) and torch.allclose(y, torch.zeros(3), atol=1e-6)
    assert torch.allclose(heading, torch.full((3,), math.pi / 2))
    action = EllipseFollower(1.0, 1.5)(obs)
    assert action.shape == (3, 2) and bool((action.abs() <= 1).all())
    with pytest.raises(ValueError, match="28 entries, got 27"):
        circle_pose(torch.zeros(27))
    with pytest.raises(ValueError, match="half-axes must be positive"):
        EllipseFollower(0.0, 1.5)
    with pytest.raises(ValueError, match="not an ellipse"):
        ellipse_policy("ellipse:a,b")


def test_collect_refuses_an_ellipse_outside_the_circle_tasks():
    from spoil_torchrl.data.collect import resolve_policy

    assert resolve_policy("ellipse:0.9,1.6", ENV_ID).module.half_axes.tolist() == pytest.approx([0.9, 1.6])
    with pytest.raises(ValueError, match="circle task"):
        resolve_policy("ellipse:0.9,1.6", "SafetyHopperVelocity-v1")
