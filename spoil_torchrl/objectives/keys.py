"""Nested-key helpers: roles are sub-tensordicts, so a role's entry is ``(role, *key)``."""

from __future__ import annotations

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
