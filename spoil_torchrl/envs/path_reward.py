"""The circle tasks' reward for an ellipse instead of the circle: a demonstrator that leaves one wall by design.

Safety-Gymnasium's circle tasks pay, after each step, the agent's speed along the circle of radius ``R``
(1.5) through its position, damped by its distance from that circle:

.. math::

    r = 0.1 \\, \\frac{(-u y + v x) / \\rho}{1 + |\\rho - R|}, \\qquad \\rho = \\sqrt{x^2 + y^2},

with ``(x, y)`` the agent's position and ``(u, v)`` its velocity. :func:`ellipse_reward` pays the same for an
axis-aligned ellipse with half-axes ``(a, b)``: the speed along the ellipse's tangent through the agent's
position (the counter-clockwise direction ``(-y / b^2, x / a^2)``, normalised), damped by
``sqrt(a b) |rho_e - 1|`` with ``rho_e = sqrt((x / a)^2 + (y / b)^2)``. With ``a = b = R`` both are the
task's reward exactly.

SafetyPointCircle2's walls stand at ``|x| = 1.125`` and ``|y| = 1.125``. An ellipse with half-axes ``(1.0, 1.5)``
stays inside the x walls and runs out to the circle beyond the y walls: PPO trained on its reward
(``ppo.track_ellipse``) was meant to give a demonstrator that keeps the x walls and crosses the y walls on every
lap. Measured, it does not: PPO learns a rounder path inside both walls (``docs/experts.md``, the one-wall
demonstrators). Datasets are always recorded with the task's own reward; this one only trains a demonstrator.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

#: Safety-Gymnasium's ``reward_factor`` of the circle tasks.
CIRCLE_REWARD_FACTOR = 0.1


def ellipse_reward(
    position: Sequence[float],
    velocity: Sequence[float],
    half_axes: Sequence[float],
    factor: float = CIRCLE_REWARD_FACTOR,
) -> float:
    """The circle tasks' reward for an axis-aligned ellipse with ``half_axes`` ``(a, b)`` (module docstring).

    Args:
        position: the agent's ``(x, y, ...)`` after the step.
        velocity: its ``(u, v, ...)``.
        half_axes: the ellipse's half-axes along x and y, both > 0.
        factor: the task's reward factor (:data:`CIRCLE_REWARD_FACTOR`).

    Examples:
        >>> round(ellipse_reward((1.5, 0.0), (0.0, 1.0), (1.5, 1.5)), 6)  # on the circle, moving along it
        0.1
        >>> round(ellipse_reward((0.0, 1.5), (-1.0, 0.0), (1.0, 1.5)), 6)  # on the ellipse's tip
        0.1
        >>> round(ellipse_reward((1.5, 0.0), (0.0, 1.0), (1.0, 1.5)), 6)  # beyond it, 0.5 x sqrt(1.5) out
        0.06202
    """
    x, y = float(position[0]), float(position[1])
    u, v = float(velocity[0]), float(velocity[1])
    a, b = float(half_axes[0]), float(half_axes[1])
    tangent_x, tangent_y = -y / b**2, x / a**2
    norm = math.hypot(tangent_x, tangent_y)
    along = (u * tangent_x + v * tangent_y) / norm if norm > 0 else 0.0
    distance = math.sqrt(a * b) * abs(math.hypot(x / a, y / b) - 1.0)
    return factor * along / (1.0 + distance)


def check_half_axes(half_axes, name: str = "ppo.track_ellipse") -> tuple[float, float]:
    """``half_axes`` as two finite numbers > 0, or a :class:`ValueError` naming ``name``.

    Examples:
        >>> check_half_axes([1.0, 1.5])
        (1.0, 1.5)
        >>> check_half_axes([1.0])
        Traceback (most recent call last):
        ...
        ValueError: ppo.track_ellipse = [1.0]: expected the ellipse's two half-axes [a, b], finite numbers > 0
    """
    ok = isinstance(half_axes, (list, tuple)) and len(half_axes) == 2
    ok = ok and all(
        not isinstance(h, bool) and isinstance(h, (int, float)) and math.isfinite(h) and h > 0
        for h in half_axes
    )
    if not ok:
        raise ValueError(
            f"{name} = {half_axes!r}: expected the ellipse's two half-axes [a, b], finite numbers > 0"
        )
    return float(half_axes[0]), float(half_axes[1])


def task_ellipse_reward(env, half_axes: Sequence[float]) -> float:
    """:func:`ellipse_reward` of the step ``env`` (a Safety-Gymnasium circle task) just took, read from its
    simulator with the task's own reward factor; a task without a circle raises."""
    task = getattr(env.unwrapped, "task", None)
    if not hasattr(task, "circle"):
        raise ValueError(
            f"ppo.track_ellipse needs a circle task (SafetyPointCircle*); {type(env.unwrapped).__name__} has no "
            "circle"
        )
    return ellipse_reward(task.agent.pos, task.agent.vel, half_axes, task.reward_factor)
