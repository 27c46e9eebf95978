"""Networks as plain functions of ``(parameters, tensors)``: what the compiled update step evaluates in place of
a LossModule's TensorDictModules (see :mod:`spoil_torchrl.trainers.compiled`)."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import nn
from torch.func import functional_call

Tensors = dict[str, torch.Tensor]


class NotCompilable(Exception):
    """The stepper's losses (or their networks) have no compiled form; the message says which and why."""


class PlainNetwork:
    """A :class:`~tensordict.nn.TensorDictModule` as a function of ``(parameters, *input tensors)``.

    ``params`` are the LossModule's own parameters (the ones its optimiser steps), named as
    :func:`torch.func.functional_call` expects them for ``module``; the inputs are passed in ``in_keys`` order.
    """

    def __init__(self, network: nn.Module, params: TensorDictBase, what: str) -> None:
        if not isinstance(network, TensorDictModule) or not network.in_keys:
            raise NotCompilable(f"{what} is not a TensorDictModule")
        flat = params.flatten_keys(".")
        if any(not key.startswith("module.") for key in flat.keys()):
            raise NotCompilable(f"{what}'s parameters are not those of its inner module")
        self.what = what
        self.module = network.module
        self.in_keys = list(network.in_keys)
        self.out_keys = list(network.out_keys)
        self.params = {key.removeprefix("module."): value for key, value in flat.items()}

    @property
    def in_key(self) -> NestedKey:
        """The one input of a network of states (nu, the policy)."""
        if len(self.in_keys) != 1:
            raise NotCompilable(f"{self.what} reads {len(self.in_keys)} inputs, not one")
        return self.in_keys[0]

    def __call__(self, params: Tensors, *xs: torch.Tensor):
        return functional_call(self.module, params, xs)


class PlainPolicy:
    """A policy of :func:`~spoil_torchrl.modules.make_actor` whose distribution takes ``loc`` and ``scale``
    (``normal``, ``tanh_normal``) as :meth:`log_prob` of ``(parameters, states, actions)``, as the LossModules
    score it (``actor.get_dist(states).log_prob(actions)``)."""

    def __init__(self, actor: nn.Module, params: TensorDictBase, what: str) -> None:
        modules = list(getattr(actor, "module", ()))
        dist_module = modules[-1] if modules else None
        if len(modules) != 2 or sorted(getattr(dist_module, "in_keys", [])) != ["loc", "scale"]:
            raise NotCompilable(f"{what} is not a network followed by a loc/scale distribution")
        self.net = PlainNetwork(modules[0], params.get(("module", "0")), what)
        self.in_key = self.net.in_key  # raises NotCompilable unless the policy reads one input
        if self.net.out_keys != ["loc", "scale"]:
            raise NotCompilable(f"{what}'s network does not write loc and scale")
        self.distribution = dist_module.distribution_class
        self.distribution_kwargs = dict(dist_module.distribution_kwargs)
        self.params = self.net.params

    def log_prob(self, params: Tensors, states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        loc, scale = self.net(params, states)
        dist = self.distribution(loc=loc, scale=scale, **self.distribution_kwargs)
        return dist.log_prob(actions).reshape(-1)


def flat_rows(role: TensorDictBase, key: NestedKey) -> torch.Tensor:
    """``role[key]`` with the role's batch dimensions flattened into one."""
    value = role.get(key)
    return value.reshape(-1, *value.shape[role.batch_dims :])
