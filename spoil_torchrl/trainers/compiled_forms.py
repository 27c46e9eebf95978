"""The compiled forms of the losses: each loss's update as a pure function of plain tensors, for
:class:`~spoil_torchrl.trainers.compiled.CompiledStepper`.

A compiled form reads the loss's networks and parameters (:class:`PlainNetwork`), takes one batch's plain
tensors out of the tensordict (``inputs``, eager: it also draws the gradient penalty's random points, in the
eager step's order), and computes the loss's ``loss_*`` terms and outputs from parameters and inputs
(``__call__``) with the same equation functions the LossModule calls. ``COMPILED_FORMS`` maps a LossModule
class to its form; a loss without one is stepped eagerly.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import nn
from torch.func import functional_call, grad
from torchrl.objectives import LossModule

from spoil_torchrl.objectives.demodice import (
    DemoDICELoss,
    demodice_diagnostics,
    demodice_dual,
    demodice_log_weight,
)
from spoil_torchrl.objectives.discriminator import (
    PUDiscriminatorLoss,
    discriminator_outputs,
    discriminator_penalty_points,
)
from spoil_torchrl.objectives.functional import (
    bellman_backup,
    dice_advantage,
    gradient_penalty,
    penalty_points,
    self_normalized_weights,
)
from spoil_torchrl.objectives.keys import get_role, role_key
from spoil_torchrl.objectives.spoildice import (
    SpoilDICELoss,
    check_support_indicator,
    closed_form_log_weight,
    spoildice_diagnostics,
    spoildice_losses,
)
from spoil_torchrl.objectives.weighted_bc import WeightedBCLoss, weighted_bc_outputs

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


class CompiledDual:
    """What the compiled forms of the DICE duals share: nu's parameters, the role's states read as the
    LossModule reads them, the penalty's random points drawn outside the graph in the eager step's order, and nu
    on the initial, current and next states plus the gradient penalty (:meth:`nu_terms`)."""

    role: NestedKey

    def __init__(self, loss: LossModule) -> None:
        self.loss = loss
        self.nu = PlainNetwork(loss.nu_network, loss.nu_network_params, f"{type(loss).__name__}'s nu_network")
        self.nu.in_key  # noqa: B018 (raises NotCompilable unless nu reads one input)
        self.produces = {role_key(self.role, loss.tensor_keys.weight)}

    def parameters(self) -> dict[str, nn.Parameter]:
        return {f"nu.{k}": v for k, v in self.nu.params.items()}

    def inputs(self, batch: TensorDictBase) -> Tensors:
        """The role's states, ``terminated`` and, when the penalty is on, its points (random, drawn here)."""
        t = self.loss._transitions(batch, self.role)
        key = self.nu.in_key
        out = {
            "init": t.init[key],
            "current": t.current[key],
            "following": t.following[key],
            "terminated": t.terminated,
        }
        if self.loss.gradient_penalty != 0:
            out["points"] = penalty_points(t.init, t.current, t.following)[key]
        return out

    def nu_terms(self, params: Tensors, x: Tensors) -> tuple[torch.Tensor, ...]:
        """nu at the initial, current and next states, and the weighted gradient penalty. With the penalty on,
        nu runs once on its points, whose first rows are the current states: their values and the input
        gradient come from that one pass."""
        nu_params = {k.removeprefix("nu."): v for k, v in params.items() if k.startswith("nu.")}

        def nu(states: torch.Tensor) -> torch.Tensor:
            return self.nu(nu_params, states).reshape(states.shape[0])

        def nu_with_sum(states: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            values = nu(states)
            return values.sum(), values

        n, n0 = x["current"].shape[0], x["init"].shape[0]
        init_nu, next_nu = nu(torch.cat([x["init"], x["following"]])).split([n0, n])
        if "points" not in x:
            return init_nu, nu(x["current"]), next_nu, torch.zeros(())
        grads, values = grad(nu_with_sum, has_aux=True)(x["points"])
        norms = grads.reshape(grads.shape[0], -1).norm(dim=-1)
        penalty = self.loss.gradient_penalty * gradient_penalty(norms, target=None)
        return init_nu, values[:n], next_nu, penalty


class CompiledSpoilDICE(CompiledDual):
    """The compiled form of :class:`~spoil_torchrl.objectives.SpoilDICELoss`: its ``loss_nu`` (with the
    gradient penalty), ``loss_lambda`` and diagnostics, and the self-normalised weights it writes for the policy
    extraction."""

    def __init__(self, loss: SpoilDICELoss) -> None:
        self.role = loss.tensor_keys.unlabeled
        super().__init__(loss)

    def parameters(self) -> dict[str, nn.Parameter]:
        return {**super().parameters(), "lagrange": self.loss.lagrange}

    def inputs(self, batch: TensorDictBase) -> Tensors:
        keys = self.loss.tensor_keys
        unlabeled = get_role(batch, keys.unlabeled)
        n = unlabeled.batch_size.numel()
        support = unlabeled.get(keys.support).reshape(n)
        check_support_indicator(support, role_key(keys.unlabeled, keys.support))
        return {
            **super().inputs(batch),
            "log_ratio": unlabeled.get(keys.log_ratio).reshape(n),
            "support": support,
        }

    def __call__(
        self, params: Tensors, x: Tensors, produced: dict
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        init_nu, current_nu, next_nu, penalty = self.nu_terms(params, x)
        dtype = current_nu.dtype
        support = x["support"].to(dtype)
        loss_nu, loss_lambda, advantage = spoildice_losses(
            init_nu,
            current_nu,
            next_nu,
            x["terminated"],
            x["log_ratio"].to(dtype),
            support,
            params["lagrange"],
            self.loss.gamma,
        )
        loss_nu = loss_nu + penalty
        with torch.no_grad():
            weights = self_normalized_weights(closed_form_log_weight(advantage.detach()))
        produced[next(iter(self.produces))] = weights
        outputs = {"loss_nu": loss_nu, "loss_lambda": loss_lambda}
        outputs |= spoildice_diagnostics(init_nu, advantage, support, params["lagrange"])
        return loss_nu + loss_lambda, outputs


class CompiledDemoDICE(CompiledDual):
    """The compiled form of :class:`~spoil_torchrl.objectives.DemoDICELoss` (DemoDICE-S and -U): ``loss_nu``
    (with the gradient penalty), its diagnostics, and the self-normalised weights of its role."""

    def __init__(self, loss: DemoDICELoss) -> None:
        self.role = loss.tensor_keys.regularization
        super().__init__(loss)

    def inputs(self, batch: TensorDictBase) -> Tensors:
        data = get_role(batch, self.role)
        reward = data.get(self.loss.tensor_keys.reward).reshape(data.batch_size.numel())
        return {**super().inputs(batch), "reward": reward}

    def __call__(
        self, params: Tensors, x: Tensors, produced: dict
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        init_nu, current_nu, next_nu, penalty = self.nu_terms(params, x)
        loss, reward = self.loss, x["reward"].detach().to(current_nu.dtype)
        advantage = dice_advantage(reward, current_nu, bellman_backup(next_nu, x["terminated"], loss.gamma))
        loss_nu = demodice_dual(init_nu, advantage, loss.alpha, loss.gamma) + penalty
        with torch.no_grad():
            weights = self_normalized_weights(demodice_log_weight(advantage.detach(), loss.alpha))
        produced[next(iter(self.produces))] = weights
        return loss_nu, {"loss_nu": loss_nu, **demodice_diagnostics(init_nu, advantage, reward, loss.alpha)}


class CompiledWeightedBC:
    """The compiled form of :class:`~spoil_torchrl.objectives.WeightedBCLoss` for a policy whose distribution
    takes ``loc`` and ``scale`` (``normal`` and ``tanh_normal`` of :func:`~spoil_torchrl.modules.make_actor`).
    Its weight is read from the batch, or taken from an earlier loss of the step that produces it (SpoilDICE's
    weights)."""

    def __init__(self, loss: WeightedBCLoss, produced_earlier: set) -> None:
        actor = loss.actor_network
        modules = list(getattr(actor, "module", ()))
        dist_module = modules[-1] if modules else None
        if len(modules) != 2 or sorted(getattr(dist_module, "in_keys", [])) != ["loc", "scale"]:
            raise NotCompilable(
                "WeightedBCLoss's actor is not a network followed by a loc/scale distribution"
            )
        self.loss = loss
        self.policy = PlainNetwork(
            modules[0], loss.actor_network_params.get(("module", "0")), "WeightedBCLoss's actor"
        )
        self.policy.in_key  # noqa: B018 (raises NotCompilable unless the policy reads one input)
        if self.policy.out_keys != ["loc", "scale"]:
            raise NotCompilable("WeightedBCLoss's actor network does not write loc and scale")
        self.distribution = dist_module.distribution_class
        self.distribution_kwargs = dict(dist_module.distribution_kwargs)
        keys = loss.tensor_keys
        self.weight_key = None if keys.weight is None else role_key(keys.role, keys.weight)
        self.weight_produced = self.weight_key in produced_earlier
        self.produces: set = set()

    def parameters(self) -> dict[str, nn.Parameter]:
        return {f"policy.{k}": v for k, v in self.policy.params.items()}

    def inputs(self, batch: TensorDictBase) -> Tensors:
        keys = self.loss.tensor_keys
        role = get_role(batch, keys.role)
        state = role.get(self.policy.in_key)
        action = role.get(keys.action)
        out = {
            "state": state.reshape(-1, *state.shape[role.batch_dims :]),
            "action": action.reshape(-1, *action.shape[role.batch_dims :]),
        }
        if keys.weight is not None and not self.weight_produced:
            out["weight"] = role.get(keys.weight).reshape(-1)
        return out

    def __call__(
        self, params: Tensors, x: Tensors, produced: dict
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        policy_params = {k.removeprefix("policy."): v for k, v in params.items()}
        loc, scale = self.policy(policy_params, x["state"])
        dist = self.distribution(loc=loc, scale=scale, **self.distribution_kwargs)
        log_prob = dist.log_prob(x["action"]).reshape(-1)
        weight = produced[self.weight_key] if self.weight_produced else x.get("weight")
        outputs = weighted_bc_outputs(log_prob, weight, self.loss.reduction)
        return outputs["loss_actor"], outputs


class CompiledDiscriminator:
    """The compiled form of :class:`~spoil_torchrl.objectives.PUDiscriminatorLoss` (Eq. 16/17 or the
    non-negative PU risk, and the WGAN-style gradient penalty): the discriminators' pre-training."""

    def __init__(self, loss: PUDiscriminatorLoss) -> None:
        self.loss = loss
        self.net = PlainNetwork(
            loss.discriminator_network,
            loss.discriminator_network_params,
            "PUDiscriminatorLoss's discriminator",
        )
        self.produces: set = set()

    def parameters(self) -> dict[str, nn.Parameter]:
        return {f"net.{k}": v for k, v in self.net.params.items()}

    def inputs(self, batch: TensorDictBase) -> Tensors:
        keys, roles = self.net.in_keys, self.loss.tensor_keys
        positive = get_role(batch, roles.positive).select(*keys).reshape(-1)
        unlabeled = get_role(batch, roles.unlabeled).select(*keys).reshape(-1)
        out = {f"positive.{i}": positive.get(k) for i, k in enumerate(keys)}
        out |= {f"unlabeled.{i}": unlabeled.get(k) for i, k in enumerate(keys)}
        if self.loss.gradient_penalty != 0:
            points = discriminator_penalty_points(positive, unlabeled, keys)
            out |= {f"points.{i}": p for i, p in enumerate(points)}
        return out

    def __call__(
        self, params: Tensors, x: Tensors, produced: dict
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        net_params = {k.removeprefix("net."): v for k, v in params.items()}
        inputs = range(len(self.net.in_keys))

        def logits(*xs: torch.Tensor) -> torch.Tensor:
            return self.net(net_params, *xs).reshape(-1)

        n_pos = x["positive.0"].shape[0]
        both = logits(*(torch.cat([x[f"positive.{i}"], x[f"unlabeled.{i}"]]) for i in inputs))
        outputs = discriminator_outputs(
            both[:n_pos], both[n_pos:], self.loss.class_prior, self.loss.reduction
        )
        penalty = torch.zeros(())
        if "points.0" in x:
            grads = grad(lambda *xs: logits(*xs).sum(), argnums=tuple(inputs))(
                *(x[f"points.{i}"] for i in inputs)
            )
            norms = torch.cat([g.reshape(g.shape[0], -1) for g in grads], dim=-1).norm(dim=-1)
            penalty = self.loss.gradient_penalty * gradient_penalty(norms, target=1.0)
        total = outputs["loss_positive"] + outputs["loss_unlabeled"] + penalty
        return total, {**outputs, "loss_gradient_penalty": penalty}


#: LossModule class -> its compiled form (built from the loss and the entries earlier losses of the step produce).
COMPILED_FORMS: dict[type, Callable[[LossModule, set], Any]] = {
    SpoilDICELoss: lambda loss, produced: CompiledSpoilDICE(loss),
    DemoDICELoss: lambda loss, produced: CompiledDemoDICE(loss),
    WeightedBCLoss: CompiledWeightedBC,
    PUDiscriminatorLoss: lambda loss, produced: CompiledDiscriminator(loss),
}


def compiled_forms(losses: Mapping[str, LossModule]) -> dict[str, Any]:
    """The compiled form of every loss (in order), or :class:`NotCompilable` naming the first that has none."""
    forms, produced = {}, set()
    for name, loss in losses.items():
        make = COMPILED_FORMS.get(type(loss))
        if make is None:
            raise NotCompilable(f"{type(loss).__name__} has no compiled form")
        forms[name] = make(loss, produced)
        produced |= forms[name].produces
    return forms
