"""A scripted demonstrator for the circle tasks: it follows an axis-aligned ellipse, so that it keeps one pair of
SafetyPointCircle2's walls and crosses the other on every lap, by design.

PPO rewarded for such an ellipse learned paths inside both walls (``docs/experts.md``), so the one-wall
demonstrators of several constraints (``docs/several_constraints.md``) are written out instead: a feedback
controller on the policy's own observation, with nothing from the simulator that a learned policy would not see.

**The pose, from the observation.** A point robot's observation in the circle tasks is its accelerometer,
velocimeter, gyro and magnetometer readings (3 each, in the robot's frame) and 16 lidar bins that see the
circle's centre, in that order (:data:`CIRCLE_LAYOUT`). MuJoCo's magnetic field is ``(0, -0.5, 0)`` in the world,
so the magnetometer reads ``(-0.5 sin h, -0.5 cos h)`` for a heading ``h``. Safety-Gymnasium's pseudo-lidar puts
``1 - d / 6`` (``d`` the distance to the centre) in the bin of the centre's direction and splits it between that
bin's two neighbours in proportion to where in the bin the direction falls, so the strongest bin and its next
neighbour give the direction to within float rounding. Together they give the robot's position and heading
exactly (:func:`circle_pose`; tested against the simulator's own pose).

**The control** (:class:`EllipseFollower`): pure pursuit of the point ``lead`` radians of the ellipse's
parameter ahead of the robot's own (counter-clockwise, the direction the task rewards); the turn command is
``turn_gain`` times the heading error, corrected by ``drift_gain`` times the angle of the robot's sideways slip;
the forward command tracks ``speed * max(0, cos(error))`` with gain ``speed_gain`` on the velocimeter's forward
speed (the point robot's thrust saturates at small commands, so speed is a feedback, not a command).
"""

from __future__ import annotations

import math

import torch
from tensordict.nn import TensorDictModule
from torch import nn

#: Where the circle tasks' flat observation keeps each reading (start, stop): the point robot's sensors, then
#: the circle lidar.
CIRCLE_LAYOUT = {"velocimeter": (3, 6), "magnetometer": (9, 12), "circle_lidar": (12, 28)}
#: The circle tasks' lidar range (``lidar_conf.max_dist``) and bins.
LIDAR_MAX_DIST, LIDAR_BINS = 6.0, 16
#: The prefix of a segment policy that names an ellipse: ``"ellipse:<a>,<b>"`` (half-axes along x and y).
ELLIPSE_PREFIX = "ellipse:"


def circle_pose(observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The robot's position ``x``, ``y`` and heading (radians) from a circle task's flat observation ``[..., 28]``
    (NaN position where the centre is beyond the lidar's range of 6, which the circle tasks' start placements and
    the followed ellipses never reach).

    Examples:
        >>> obs = torch.zeros(28)
        >>> obs[9:11] = torch.tensor([-0.5, 0.0])  # heading 90 degrees: the robot's x axis is the world's y
        >>> obs[12 + 6] = 1 - 1.5 / 6  # the centre 1.5 away at 135 degrees in the robot's frame (bin 6 of 16)
        >>> [round(float(v), 4) for v in circle_pose(obs)]  # x, y = 1.5 (cos 45, sin 45); heading pi / 2
        [1.0607, 1.0607, 1.5708]
    """
    if observation.shape[-1] != CIRCLE_LAYOUT["circle_lidar"][1]:
        raise ValueError(
            f"a circle task's observation has {CIRCLE_LAYOUT['circle_lidar'][1]} entries, "
            f"got {observation.shape[-1]}"
        )
    m = observation[..., slice(*CIRCLE_LAYOUT["magnetometer"])]
    sin_h, cos_h = -2 * m[..., 0], -2 * m[..., 1]
    heading = torch.atan2(sin_h, cos_h)
    lidar = observation[..., slice(*CIRCLE_LAYOUT["circle_lidar"])]
    strength, index = lidar.max(-1)
    following = lidar.gather(-1, ((index + 1) % LIDAR_BINS).unsqueeze(-1)).squeeze(-1)
    share = torch.where(strength > 0, following / strength.clamp_min(1e-12), torch.zeros_like(strength))
    bearing = (index + share) * (2 * math.pi / LIDAR_BINS)  # the centre's direction in the robot's frame
    # beyond the lidar's range every bin reads 0 and no pose can be read: NaN, which a rollout refuses
    distance = torch.where(strength > 0, LIDAR_MAX_DIST * (1 - strength), torch.full_like(strength, math.nan))
    # the centre at distance * (cos, sin)(bearing) in the robot's frame: the robot at minus that in the world's
    world_bearing = bearing + heading
    return -distance * torch.cos(world_bearing), -distance * torch.sin(world_bearing), heading


def _wrap(angle: torch.Tensor) -> torch.Tensor:
    return torch.remainder(angle + math.pi, 2 * math.pi) - math.pi


class EllipseFollower(nn.Module):
    """Actions ``[forward, turn]`` in ``[-1, 1]`` that drive a circle task's point robot round the ellipse with
    half-axes ``a`` (along x) and ``b`` (along y), counter-clockwise (see the module's docstring).

    With ``a = 0.9, b = 1.6`` the robot stays inside SafetyPointCircle2's x walls (at 1.125) and crosses its y
    walls on every lap; ``a = 1.6, b = 0.9`` is the mirror image.

    Examples:
        >>> follower = EllipseFollower(0.9, 1.6)
        >>> obs = torch.zeros(2, 28)
        >>> obs[:, 9:11] = torch.tensor([0.0, -0.5])  # heading along the world's x axis
        >>> obs[:, 12 + 8] = 1 - 0.9 / 6  # at (0.9, 0), on the ellipse: the path ahead bends to the left
        >>> action = follower(obs)
        >>> action.shape, bool((action[:, 1] > 0).all())  # turning left
        (torch.Size([2, 2]), True)
    """

    def __init__(
        self,
        a: float,
        b: float,
        *,
        lead: float = 0.4,
        turn_gain: float = 3.0,
        drift_gain: float = 1.0,
        speed: float = 1.2,
        speed_gain: float = 5.0,
    ) -> None:
        super().__init__()
        if not (a > 0 and b > 0 and math.isfinite(a) and math.isfinite(b)):
            raise ValueError(f"the ellipse's half-axes must be positive numbers, got a={a}, b={b}")
        # a parameter (never trained) so that the module, like a learned policy, carries its device and dtype
        self.half_axes = nn.Parameter(torch.tensor([float(a), float(b)]), requires_grad=False)
        self.lead, self.turn_gain, self.drift_gain = float(lead), float(turn_gain), float(drift_gain)
        self.speed, self.speed_gain = float(speed), float(speed_gain)

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        x, y, heading = circle_pose(observation)
        a, b = self.half_axes[0], self.half_axes[1]
        ahead = torch.atan2(y / b, x / a) + self.lead  # the ellipse's parameter of the point pursued
        target = torch.atan2(b * torch.sin(ahead) - y, a * torch.cos(ahead) - x)
        velocity = observation[..., slice(*CIRCLE_LAYOUT["velocimeter"])]
        forward, sideways = velocity[..., 0], velocity[..., 1]
        moving = torch.hypot(forward, sideways) > 0.1
        slip = torch.where(moving, torch.atan2(sideways, forward), torch.zeros_like(forward))
        error = _wrap(target - heading - self.drift_gain * slip)
        wanted = self.speed * torch.cos(error).clamp_min(0)
        thrust = (self.speed_gain * (wanted - forward)).clamp(-1, 1)
        turn = (self.turn_gain * error).clamp(-1, 1)
        return torch.stack([thrust, turn], -1).to(observation.dtype)


def ellipse_policy(spec: str) -> TensorDictModule:
    """The :class:`EllipseFollower` a segment policy ``"ellipse:<a>,<b>"`` names, reading ``observation`` and
    writing ``action``.

    Examples:
        >>> policy = ellipse_policy("ellipse:0.9,1.6")
        >>> policy.module.half_axes.tolist()
        [0.8999999761581421, 1.600000023841858]
        >>> ellipse_policy("ellipse:0.9")
        Traceback (most recent call last):
        ...
        ValueError: 'ellipse:0.9' is not an ellipse: write ellipse:<a>,<b> (the half-axes along x and y)
    """
    try:
        a, b = (float(v) for v in spec.removeprefix(ELLIPSE_PREFIX).split(","))
    except ValueError:
        raise ValueError(
            f"{spec!r} is not an ellipse: write {ELLIPSE_PREFIX}<a>,<b> (the half-axes along x and y)"
        ) from None
    return TensorDictModule(EllipseFollower(a, b), in_keys=["observation"], out_keys=["action"])
