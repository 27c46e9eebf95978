"""Nested-key helpers: roles are sub-tensordicts, so a role's entry is ``(role, *key)``."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import NamedTuple

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey, unravel_key


def role_key(role: NestedKey, key: NestedKey) -> NestedKey:
    """The nested key of ``key`` inside the sub-tensordict ``role``.

    Examples:
        >>> role_key("safe", "observation")
        ('safe', 'observation')
        >>> role_key(("data", "unlabeled"), ("next", "observation"))
        ('data', 'unlabeled', 'next', 'observation')
    """
    return unravel_key((role, key))


def roles_read(losses: Iterable, roles: Sequence[str]) -> list[str] | None:
    """The roles among ``roles`` whose entries some loss of ``losses`` reads (the first part of its nested
    ``in_keys``), in ``roles``' order; ``None`` when a loss has no ``in_keys`` or none of them inside a role
    (a loss that reads the batch its own way: then every role is drawn).

    Examples:
        >>> class Loss:
        ...     in_keys = [("unlabeled", "observation"), ("init", "observation")]
        >>> roles_read([Loss()], ["safe", "performant", "unlabeled", "init"])
        ['unlabeled', 'init']
    """
    read: set[str] = set()
    for loss in losses:
        keys = [unravel_key(k) for k in getattr(loss, "in_keys", None) or ()]
        in_roles = {k[0] for k in keys if isinstance(k, tuple) and k[0] in roles}
        if not in_roles:
            return None
        read |= in_roles
    return [role for role in roles if role in read]


def get_role(tensordict: TensorDictBase, role: NestedKey) -> TensorDictBase:
    """The sub-tensordict of ``role``, checked to exist and to carry a batch dimension.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> batch = TensorDict({"safe": TensorDict({"observation": torch.zeros(4, 2)}, [4])}, [])
        >>> get_role(batch, "safe").shape
        torch.Size([4])
    """
    try:
        sub = tensordict.get(role)
    except KeyError:
        sub = None
    if not isinstance(sub, TensorDictBase):
        raise KeyError(
            f"the batch has no role {role!r} (a sub-tensordict); "
            f"its top-level keys are {sorted(map(str, tensordict.keys()))}"
        )
    if sub.batch_dims == 0:
        raise ValueError(
            f"role {role!r} has no batch dimension: build it as TensorDict(..., batch_size=[n]) so that its rows "
            "are samples"
        )
    return sub


def role_entry(data: TensorDictBase, role: NestedKey, key: NestedKey, written_by: str) -> torch.Tensor:
    """Entry ``key`` of ``data``, the sub-tensordict of ``role`` (:func:`get_role`), checked to be there: an
    annotation a loss reads (a log-ratio, a support indicator, a DICE weight) that nothing has written yet is
    named with its role and with ``written_by``, what writes it, instead of failing later on ``None``.

    The check is one Python ``None`` test, made in a loss's eager
    :meth:`~spoil_torchrl.objectives.pure.PureLoss.inputs` (never in the traced ``terms``), so the compiled
    and vectorised steps do not pay for it.

    Raises:
        KeyError: ``data`` has no entry ``key``.

    Examples:
        >>> from tensordict import TensorDict
        >>> data = TensorDict({"observation": torch.zeros(4, 2)}, [4])
        >>> role_entry(data, "unlabeled", "observation", "the dataset").shape
        torch.Size([4, 2])
        >>> role_entry(data, "unlabeled", "dice_weight", "a DICE loss writes it")
        Traceback (most recent call last):
        ...
        KeyError: "role 'unlabeled' has no entry 'dice_weight' (a DICE loss writes it); its entries are \
['observation']"
    """
    value = data.get(key, None)
    if value is None:
        raise KeyError(
            f"role {role!r} has no entry {key!r} ({written_by}); "
            f"its entries are {sorted(map(str, data.keys()))}"
        )
    return value


class DICETransitions(NamedTuple):
    """A role's transitions and the initial states, flattened for a DICE dual (see :func:`dice_transitions`)."""

    batch_shape: torch.Size  # the role's batch shape (weights are written back in it)
    init: dict[NestedKey, torch.Tensor]  # network input key -> [n0, *event] initial states
    current: dict[NestedKey, torch.Tensor]  # -> [n, *event] states s
    following: dict[NestedKey, torch.Tensor]  # -> [n, *event] next states s'
    terminated: torch.Tensor  # [n]


def dice_transitions(
    tensordict: TensorDictBase,
    *,
    role: NestedKey,
    init: NestedKey,
    state_keys: Sequence[NestedKey],
    next_key: NestedKey,
    terminated_key: NestedKey,
    loss_name: str,
) -> DICETransitions:
    """Read the transitions of ``tensordict[role]`` and the states of ``tensordict[init]`` for a nu network.

    The TED ``terminated`` entry is ``[*B, 1]``: it fixes the role's batch shape, and with it each state's
    event shape (initial states live in the same space, whatever batch shape their role was given). Raises a
    clear error for a flat ``terminated`` or an empty role.

    Examples:
        >>> from tensordict import TensorDict
        >>> role = TensorDict({"observation": torch.zeros(4, 3), "next": TensorDict({
        ...     "observation": torch.ones(4, 3), "terminated": torch.zeros(4, 1, dtype=torch.bool)}, [4])}, [4])
        >>> batch = TensorDict({"unlabeled": role, "init": TensorDict({"observation": torch.zeros(2, 3)}, [2])}, [])
        >>> t = dice_transitions(batch, role="unlabeled", init="init", state_keys=["observation"],
        ...                      next_key="next", terminated_key=("next", "terminated"), loss_name="a loss")
        >>> t.batch_shape, t.current["observation"].shape, t.init["observation"].shape, t.terminated.shape
        (torch.Size([4]), torch.Size([4, 3]), torch.Size([2, 3]), torch.Size([4]))
    """
    data = get_role(tensordict, role)
    terminated = data.get(terminated_key)
    if terminated.ndim < 2 or terminated.shape[-1] != 1:
        raise ValueError(
            f"{role_key(role, terminated_key)} must have a trailing dimension of 1 (TED layout), "
            f"got shape {tuple(terminated.shape)}"
        )
    batch_shape = terminated.shape[:-1]
    n = batch_shape.numel()
    events = {k: data.get(k).shape[len(batch_shape) :] for k in state_keys}
    init_role = get_role(tensordict, init)
    init_states = {k: init_role.get(k).reshape(-1, *events[k]) for k in state_keys}
    current = {k: data.get(k).reshape(n, *events[k]) for k in state_keys}
    following = {k: data.get(role_key(next_key, k)).reshape(n, *events[k]) for k in state_keys}
    if n == 0 or init_states[state_keys[0]].shape[0] == 0:
        raise ValueError(f"{loss_name} needs at least one transition in {role!r} and one initial state")
    return DICETransitions(batch_shape, init_states, current, following, terminated.reshape(n))
