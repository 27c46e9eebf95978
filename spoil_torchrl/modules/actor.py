"""The stochastic policy pi(a|s): a TorchRL :class:`~torchrl.modules.ProbabilisticActor`.

Three distributions are offered, picked by name in :func:`make_actor`:

* ``"tanh_normal"`` -- a tanh-squashed Gaussian rescaled to the action bounds. Its mean is clipped to
  +/- atanh(1 - eps) and its log-std to [-5, 2] (the ranges of DemoDICE's reference actor), and dataset actions
  are clipped to +/-(1 - eps) of the range before scoring, so that an action logged exactly on the bound gets a
  finite log-probability (DemoDICE's reference actor does the same).
* ``"normal"`` -- a plain diagonal Gaussian with the same log-std clipping (the paper's Table J "Normal").
* ``"categorical"`` -- one-hot categorical actions, used by the tabular checks.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import MLP, IndependentNormal, OneHotCategorical, ProbabilisticActor, TanhNormal

#: Clip fraction for dataset actions scored by :class:`ClippedTanhNormal` (actions are mapped into
#: [low + eps * half_range, high - eps * half_range]).
ACTION_CLIP_EPS = 1e-6
LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0
#: atanh(1 - ACTION_CLIP_EPS): a pre-tanh mean beyond this cannot be told apart from the bound in float32.
TANH_MEAN_BOUND = math.atanh(1.0 - ACTION_CLIP_EPS)

#: The distributions of continuous actions (a box); ``"categorical"`` is of discrete (one-hot) actions.
CONTINUOUS_DISTRIBUTIONS = ("tanh_normal", "normal")
DISTRIBUTIONS = (*CONTINUOUS_DISTRIBUTIONS, "categorical")


class NormalParams(nn.Module):
    """Split the last dimension into ``(loc, scale)`` with a clipped mean and a clipped log-std.

    Args:
        loc_bound: clip the mean to ``[-loc_bound, loc_bound]``; ``None`` leaves it free.
        log_std_min, log_std_max: clip range of the log standard deviation.

    Examples:
        >>> params = NormalParams(loc_bound=1.0)
        >>> loc, scale = params(torch.tensor([[3.0, -10.0]]))
        >>> loc.item(), round(scale.item(), 4)
        (1.0, 0.0067)
    """

    def __init__(
        self,
        loc_bound: float | None = None,
        log_std_min: float = LOG_STD_MIN,
        log_std_max: float = LOG_STD_MAX,
    ) -> None:
        super().__init__()
        if log_std_min >= log_std_max:
            raise ValueError(f"log_std_min ({log_std_min}) must be smaller than log_std_max ({log_std_max})")
        self.loc_bound = loc_bound
        self.log_std_min = log_std_min
        self.log_std_max = log_std_max

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        loc, log_std = x.chunk(2, dim=-1)
        if self.loc_bound is not None:
            loc = loc.clamp(-self.loc_bound, self.loc_bound)
        return loc, log_std.clamp(self.log_std_min, self.log_std_max).exp()


class ClippedTanhNormal(TanhNormal):
    """:class:`~torchrl.modules.TanhNormal` whose ``log_prob`` clips its argument inside the open range.

    ``atanh(+/-1)`` is infinite, so a logged action on the bound would otherwise give an infinite (or, with the
    safe tanh, a huge and meaningless) log-likelihood. The clip is ``ACTION_CLIP_EPS`` of the half-range.

    Examples:
        >>> dist = ClippedTanhNormal(torch.zeros(2), torch.ones(2), low=-2.0, high=2.0)
        >>> bool(torch.isfinite(dist.log_prob(torch.tensor([2.0, -2.0]))))
        True
    """

    def log_prob(self, value: torch.Tensor) -> torch.Tensor:
        mid = (self.high + self.low) / 2
        half = (self.high - self.low) / 2
        unit = ((value - mid) / half).clamp(-1.0 + ACTION_CLIP_EPS, 1.0 - ACTION_CLIP_EPS)
        return super().log_prob(mid + unit * half)


def make_actor(
    observation_dim: int,
    action_dim: int,
    *,
    hidden_cells: Sequence[int] = (256, 256),
    distribution: str = "tanh_normal",
    action_low: float | torch.Tensor = -1.0,
    action_high: float | torch.Tensor = 1.0,
    observation_key: str = "observation",
    action_key: str = "action",
    return_log_prob: bool = False,
) -> ProbabilisticActor:
    """Build the policy network pi(a|s).

    Args:
        observation_dim: size of the (flat) observation.
        action_dim: size of the action; for ``"categorical"`` the number of discrete actions (one-hot).
        hidden_cells: hidden layer sizes of the ReLU MLP; ``()`` gives a linear (tabular) policy.
        distribution: one of ``"tanh_normal"``, ``"normal"``, ``"categorical"``.
        action_low, action_high: action bounds of the tanh-squashed distribution.
        observation_key, action_key: tensordict keys read and written by the actor.
        return_log_prob: also write the sampled action's log-probability (on-policy learners such as PPO).

    Returns:
        a :class:`~torchrl.modules.ProbabilisticActor`; ``actor.get_dist(td)`` gives pi(.|s).

    Examples:
        >>> from tensordict import TensorDict
        >>> actor = make_actor(3, 2, hidden_cells=(8,))
        >>> td = actor(TensorDict({"observation": torch.randn(4, 3)}, [4]))
        >>> td["action"].shape, bool(td["action"].abs().max() <= 1)
        (torch.Size([4, 2]), True)
        >>> actor.get_dist(td).log_prob(torch.ones(4, 2)).shape
        torch.Size([4])
    """
    if distribution not in DISTRIBUTIONS:
        raise ValueError(f"unknown distribution {distribution!r}; choose one of {DISTRIBUTIONS}")
    if observation_dim <= 0 or action_dim <= 0:
        raise ValueError(
            f"observation_dim and action_dim must be positive, got {observation_dim}, {action_dim}"
        )
    if distribution == "categorical":
        net = MLP(
            in_features=observation_dim,
            out_features=action_dim,
            num_cells=list(hidden_cells),
            activation_class=nn.ReLU,
        )
        module = TensorDictModule(net, in_keys=[observation_key], out_keys=["logits"])
        return ProbabilisticActor(
            module,
            in_keys=["logits"],
            out_keys=[action_key],
            distribution_class=OneHotCategorical,
            return_log_prob=return_log_prob,
        )
    net = MLP(
        in_features=observation_dim,
        out_features=2 * action_dim,
        num_cells=list(hidden_cells),
        activation_class=nn.ReLU,
    )
    if distribution == "tanh_normal":
        params = NormalParams(loc_bound=TANH_MEAN_BOUND)
        dist_class, dist_kwargs = ClippedTanhNormal, {"low": action_low, "high": action_high}
    else:
        params = NormalParams(loc_bound=None)
        dist_class, dist_kwargs = IndependentNormal, {}
    module = TensorDictModule(
        nn.Sequential(net, params), in_keys=[observation_key], out_keys=["loc", "scale"]
    )
    return ProbabilisticActor(
        module,
        in_keys=["loc", "scale"],
        out_keys=[action_key],
        distribution_class=dist_class,
        distribution_kwargs=dist_kwargs,
        return_log_prob=return_log_prob,
    )
