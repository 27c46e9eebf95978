"""The circle tasks' reward for an ellipse (``ppo.track_ellipse``): the task's own reward when the ellipse is the
task's circle, a lap of the ellipse paid where the circle's is not, and the settings refused with their names."""

from __future__ import annotations

import importlib.util
import math

import numpy as np
import pytest
import torch

from spoil_torchrl.envs.path_reward import check_half_axes, ellipse_reward
from spoil_torchrl.experts import PPOConfig

needs_safety_gymnasium = pytest.mark.skipif(
    importlib.util.find_spec("safety_gymnasium") is None, reason="safety-gymnasium not installed (EXTRAS=dev)"
)


def _lap(a: float, b: float, speed: float = 1.0, n: int = 64):
    """Positions and velocities of a counter-clockwise lap of the ellipse (a, b) at ``speed``."""
    for t in np.linspace(0.0, 2 * math.pi, n, endpoint=False):
        position = (a * math.cos(t), b * math.sin(t))
        tangent = np.array([-a * math.sin(t), b * math.cos(t)])
        yield position, tuple(speed * tangent / np.linalg.norm(tangent))


def test_an_ellipse_pays_its_own_lap_in_full_and_the_circle_less():
    """On the ellipse, moving along it, every step earns the full factor; the same lap scored against the task's
    circle (radius 1.5) earns less, and the reverse lap is paid negatively."""
    for position, velocity in _lap(1.0, 1.5):
        assert ellipse_reward(position, velocity, (1.0, 1.5)) == pytest.approx(0.1)
        assert ellipse_reward(position, tuple(-v for v in velocity), (1.0, 1.5)) == pytest.approx(-0.1)
    on_circle = [ellipse_reward(p, v, (1.5, 1.5)) for p, v in _lap(1.0, 1.5)]
    assert max(on_circle) == pytest.approx(0.1) and np.mean(on_circle) < 0.09
    assert ellipse_reward((0.0, 0.0), (1.0, 0.0), (1.0, 1.5)) == 0.0  # the centre: no tangent


def test_with_equal_half_axes_it_is_the_circle_tasks_formula():
    """a = b = R: Safety-Gymnasium's circle reward, written out, at random states."""
    rng = np.random.default_rng(0)
    for _ in range(200):
        x, y, u, v = rng.uniform(-2, 2, size=4)
        radius = math.hypot(x, y)
        task = 0.1 * ((-u * y + v * x) / radius) / (1 + abs(radius - 1.5))
        assert ellipse_reward((x, y, 0.0), (u, v, 0.0), (1.5, 1.5)) == pytest.approx(
            task, rel=1e-12, abs=1e-15
        )


@pytest.mark.parametrize(
    "bad", [[1.0], [1.0, 0.0], [1.0, -2.0], [1.0, float("nan")], [True, 1.0], "1.0,1.5", 1.5]
)
def test_bad_half_axes_are_refused_with_the_settings_name(bad):
    with pytest.raises(ValueError, match=r"ppo.track_ellipse = .*expected the ellipse's two half-axes"):
        check_half_axes(bad)
    with pytest.raises(ValueError, match=r"ppo.track_ellipse = .*expected the ellipse's two half-axes"):
        PPOConfig(track_ellipse=bad, num_envs=2, frames_per_batch=1000, minibatch_size=500)


def test_the_setting_needs_the_lockstep_collector():
    with pytest.raises(ValueError, match=r"ppo.track_ellipse = \[1.0, 1.5\] needs ppo.num_envs > 1"):
        PPOConfig(track_ellipse=[1.0, 1.5])
    assert PPOConfig(track_ellipse=[1, 1.5], num_envs=2).track_ellipse == (1.0, 1.5)  # Hydra gives a list


@needs_safety_gymnasium
def test_the_collector_pays_the_ellipse_and_leaves_the_trajectories_alone():
    """The same seeds give the same trajectories and costs with and without an ellipse; with the task's circle as
    the ellipse, the rewards are the task's (to float32); with another, they differ. A task without a circle is
    refused when the collector is made."""
    from spoil_torchrl.experts.lockstep import LockstepCollector
    from spoil_torchrl.modules import make_actor

    actor = make_actor(28, 2, hidden_cells=(8,), distribution="tanh_normal", return_log_prob=True)
    batches = {}
    for axes in (None, (1.5, 1.5), (1.0, 1.5)):
        collector = LockstepCollector("SafetyPointCircle2-v0", num_envs=2, track_ellipse=axes)
        torch.manual_seed(0)
        batches[axes] = collector.batch(actor, frames=1000, seed=3)
        collector.close()
    task, circle, ellipse = batches[None], batches[(1.5, 1.5)], batches[(1.0, 1.5)]
    for other in (circle, ellipse):
        assert torch.equal(task["observation"], other["observation"])
        assert torch.equal(task["next", "cost"], other["next", "cost"])
    torch.testing.assert_close(circle["next", "reward"], task["next", "reward"], rtol=1e-6, atol=1e-7)
    assert not torch.allclose(ellipse["next", "reward"], task["next", "reward"])
    with pytest.raises(ValueError, match="ppo.track_ellipse needs a circle task"):
        LockstepCollector("SafetyHalfCheetahVelocity-v1", num_envs=2, track_ellipse=(1.0, 1.5))
