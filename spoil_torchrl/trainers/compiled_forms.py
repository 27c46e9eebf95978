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
from torch import nn
from torch.func import grad
from torchrl.objectives import LossModule

from spoil_torchrl.objectives import (
    COptiDICELoss,
    DemoDICELoss,
    DWBCLoss,
    PUDiscriminatorLoss,
    SafeDICELoss,
    SpoilDICELoss,
    WeightedBCLoss,
)
from spoil_torchrl.objectives.discriminator import discriminator_outputs, discriminator_penalty_points
from spoil_torchrl.objectives.dwbc import dwbc_outputs, log_prob_feature
from spoil_torchrl.objectives.functional import gradient_penalty
from spoil_torchrl.objectives.keys import get_role, role_key
from spoil_torchrl.objectives.weighted_bc import weighted_bc_outputs
from spoil_torchrl.trainers.compiled_duals import (
    CompiledCOptiDICE,
    CompiledDemoDICE,
    CompiledSafeDICE,
    CompiledSpoilDICE,
)
from spoil_torchrl.trainers.plain import NotCompilable, PlainNetwork, PlainPolicy, Tensors, flat_rows


class CompiledWeightedBC:
    """The compiled form of :class:`~spoil_torchrl.objectives.WeightedBCLoss` (a :class:`PlainPolicy`). Its
    weight is read from the batch, or taken from an earlier loss of the step that produces it (the DICE
    weights)."""

    def __init__(self, loss: WeightedBCLoss, produced_earlier: set) -> None:
        self.loss = loss
        self.policy = PlainPolicy(loss.actor_network, loss.actor_network_params, "WeightedBCLoss's actor")
        keys = loss.tensor_keys
        self.weight_key = None if keys.weight is None else role_key(keys.role, keys.weight)
        self.weight_produced = self.weight_key in produced_earlier
        self.produces: set = set()

    def parameters(self) -> dict[str, nn.Parameter]:
        return {f"policy.{k}": v for k, v in self.policy.params.items()}

    def inputs(self, batch: TensorDictBase) -> Tensors:
        keys = self.loss.tensor_keys
        role = get_role(batch, keys.role)
        out = {"state": flat_rows(role, self.policy.in_key), "action": flat_rows(role, keys.action)}
        if keys.weight is not None and not self.weight_produced:
            out["weight"] = role.get(keys.weight).reshape(-1)
        return out

    def __call__(
        self, params: Tensors, x: Tensors, produced: dict
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        policy_params = {k.removeprefix("policy."): v for k, v in params.items()}
        log_prob = self.policy.log_prob(policy_params, x["state"], x["action"])
        weight = produced[self.weight_key] if self.weight_produced else x.get("weight")
        outputs = weighted_bc_outputs(log_prob, weight, self.loss.reduction)
        return outputs["loss_actor"], outputs


class CompiledDWBC:
    """The compiled form of :class:`~spoil_torchrl.objectives.DWBCLoss`: the policy and the discriminator
    D(s, a, log pi) of DWBC, trained jointly (the recipe's :class:`~spoil_torchrl.trainers.StepEvery` still
    decides when the discriminator's optimiser steps)."""

    def __init__(self, loss: DWBCLoss) -> None:
        self.loss = loss
        self.policy = PlainPolicy(loss.actor_network, loss.actor_network_params, "DWBCLoss's actor")
        self.net = PlainNetwork(
            loss.discriminator_network, loss.discriminator_network_params, "DWBCLoss's discriminator"
        )
        self.data_keys = loss._discriminator_inputs()  # the discriminator's inputs read from the data
        self.produces: set = set()

    def parameters(self) -> dict[str, nn.Parameter]:
        return {
            **{f"policy.{k}": v for k, v in self.policy.params.items()},
            **{f"net.{k}": v for k, v in self.net.params.items()},
        }

    def inputs(self, batch: TensorDictBase) -> Tensors:
        keys, out = self.loss.tensor_keys, {}
        for name, role_name in (("expert", keys.expert), ("unlabeled", keys.unlabeled)):
            role = get_role(batch, role_name)
            out[f"{name}.state"] = flat_rows(role, self.policy.in_key)
            out[f"{name}.action"] = flat_rows(role, keys.action)
            out |= {f"{name}.{i}": flat_rows(role, k) for i, k in enumerate(self.data_keys)}
        return out

    def __call__(
        self, params: Tensors, x: Tensors, produced: dict
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        policy_params = {k.removeprefix("policy."): v for k, v in params.items() if k.startswith("policy.")}
        net_params = {k.removeprefix("net."): v for k, v in params.items() if k.startswith("net.")}
        n_expert = x["expert.action"].shape[0]
        action = torch.cat([x["expert.action"], x["unlabeled.action"]])
        states = torch.cat([x["expert.state"], x["unlabeled.state"]])
        log_prob = self.policy.log_prob(policy_params, states, action)
        data = {k: torch.cat([x[f"expert.{i}"], x[f"unlabeled.{i}"]]) for i, k in enumerate(self.data_keys)}
        data[self.loss.tensor_keys.log_prob_input] = log_prob_feature(log_prob, action[0].numel()).unsqueeze(
            -1
        )
        logit = self.net(net_params, *(data[k] for k in self.net.in_keys)).reshape(-1)
        loss = self.loss
        outputs = dwbc_outputs(log_prob, logit, n_expert, loss.alpha, loss.eta, loss.offset)
        return outputs["loss_discriminator"] + outputs["loss_actor"], outputs


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
        penalty = both.new_zeros(())
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
    SafeDICELoss: lambda loss, produced: CompiledSafeDICE(loss),
    WeightedBCLoss: CompiledWeightedBC,
    PUDiscriminatorLoss: lambda loss, produced: CompiledDiscriminator(loss),
    DWBCLoss: lambda loss, produced: CompiledDWBC(loss),
    COptiDICELoss: lambda loss, produced: CompiledCOptiDICE(loss),
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
