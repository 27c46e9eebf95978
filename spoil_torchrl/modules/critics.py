"""Scalar networks: the state value nu(s) and the state-action discriminator logit."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import MLP


def make_value_network(
    observation_dim: int,
    *,
    hidden_cells: Sequence[int] = (256, 256),
    observation_key: str = "observation",
    out_key: str = "nu",
    activation_class: type[nn.Module] = nn.ReLU,
) -> TensorDictModule:
    """A state-value MLP with one output: the dual variable nu(s) of the Bellman flow constraints by default,
    or any critic V(s) (``out_key="state_value"``, e.g. PPO's with ``activation_class=nn.Tanh``).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> nu = make_value_network(3, hidden_cells=(8,))
        >>> nu(TensorDict({"observation": torch.randn(5, 3)}, [5]))["nu"].shape
        torch.Size([5, 1])
    """
    if observation_dim <= 0:
        raise ValueError(f"observation_dim must be positive, got {observation_dim}")
    net = MLP(
        in_features=observation_dim,
        out_features=1,
        num_cells=list(hidden_cells),
        activation_class=activation_class,
    )
    return TensorDictModule(net, in_keys=[observation_key], out_keys=[out_key])


def make_discriminator(
    observation_dim: int,
    action_dim: int,
    *,
    hidden_cells: Sequence[int] = (256, 256),
    observation_key: str = "observation",
    action_key: str = "action",
    out_key: str = "logit",
    extra_inputs: Mapping[str, int] | None = None,
) -> TensorDictModule:
    """A state-action discriminator returning the logit of C(s, a).

    With the logistic objective of Eq. (16)/(17), ``logit = log C / (1 - C) = log r_hat`` (Eq. 18), so the
    output *is* the estimated log density ratio. The MLP concatenates observation and action, then the
    ``extra_inputs`` (key -> size, in order; e.g. DWBC's ``{"policy_log_prob": 1}``, see
    :class:`~spoil_torchrl.objectives.DWBCLoss`).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> disc = make_discriminator(3, 2, hidden_cells=(8,))
        >>> td = TensorDict({"observation": torch.randn(5, 3), "action": torch.randn(5, 2)}, [5])
        >>> disc(td)["logit"].shape
        torch.Size([5, 1])
        >>> dwbc = make_discriminator(3, 2, hidden_cells=(8,), extra_inputs={"policy_log_prob": 1})
        >>> dwbc.in_keys
        ['observation', 'action', 'policy_log_prob']
    """
    if observation_dim <= 0 or action_dim <= 0:
        raise ValueError(
            f"observation_dim and action_dim must be positive, got {observation_dim}, {action_dim}"
        )
    extra = dict(extra_inputs or {})
    if any(size <= 0 for size in extra.values()):
        raise ValueError(f"extra_inputs sizes must be positive, got {extra}")
    net = MLP(
        in_features=observation_dim + action_dim + sum(extra.values()),
        out_features=1,
        num_cells=list(hidden_cells),
        activation_class=nn.ReLU,
    )
    return TensorDictModule(net, in_keys=[observation_key, action_key, *extra], out_keys=[out_key])
