"""The compiled forms of the DICE duals (SpoilDICE, DemoDICE, SafeDICE, COptiDICE): each loss's update as a
pure function of plain tensors (see :mod:`spoil_torchrl.trainers.compiled_forms`)."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import nn
from torch.func import grad
from torchrl.objectives import LossModule

from spoil_torchrl.objectives.coptidice import COptiDICELoss, lagrange_of, tau_of
from spoil_torchrl.objectives.demodice import (
    DemoDICELoss,
    demodice_diagnostics,
    demodice_dual,
    demodice_log_weight,
)
from spoil_torchrl.objectives.functional import (
    bellman_backup,
    dice_advantage,
    gradient_penalty,
    penalty_points,
    self_normalized_weights,
)
from spoil_torchrl.objectives.keys import get_role, role_key
from spoil_torchrl.objectives.safedice import SafeDICELoss, safedice_dual, safedice_log_weight
from spoil_torchrl.objectives.spoildice import (
    SpoilDICELoss,
    check_support_indicator,
    closed_form_log_weight,
    spoildice_diagnostics,
    spoildice_losses,
)
from spoil_torchrl.trainers.plain import PlainNetwork, Tensors


class CompiledDual:
    """What the compiled forms of the DICE duals share: nu's parameters, the role's states read as the
    LossModule reads them, the penalty's random points drawn outside the graph in the eager step's order, and nu
    on the initial, current and next states plus the gradient penalty (:meth:`nu_terms`)."""

    role: NestedKey
    #: the inputs holding each penalised state network's points, in the order the LossModule draws them
    penalised: tuple[str, ...] = ("points",)

    def __init__(self, loss: LossModule) -> None:
        self.loss = loss
        self.nu = PlainNetwork(loss.nu_network, loss.nu_network_params, f"{type(loss).__name__}'s nu_network")
        self.nu.in_key  # noqa: B018 (raises NotCompilable unless nu reads one input)
        self.produces = {role_key(self.role, loss.tensor_keys.weight)}

    def parameters(self) -> dict[str, nn.Parameter]:
        return {f"nu.{k}": v for k, v in self.nu.params.items()}

    def inputs(self, batch: TensorDictBase) -> Tensors:
        """The role's states, ``terminated`` and, when the penalty is on, the points of each penalised network
        (random, drawn here)."""
        t = self.loss._transitions(batch, self.role)
        key = self.nu.in_key
        out = {
            "init": t.init[key],
            "current": t.current[key],
            "following": t.following[key],
            "terminated": t.terminated,
        }
        if self.loss.gradient_penalty != 0:
            for name in self.penalised:
                out[name] = penalty_points(t.init, t.current, t.following)[key]
        return out

    def nu_terms(self, params: Tensors, x: Tensors) -> tuple[torch.Tensor, ...]:
        """nu at the initial, current and next states, and the weighted gradient penalty (0 when off)."""
        nu_params = {k.removeprefix("nu."): v for k, v in params.items() if k.startswith("nu.")}
        return state_terms(self.nu, nu_params, x, x.get("points"), self.loss.gradient_penalty)


def state_terms(
    network: PlainNetwork, params: Tensors, x: Tensors, points: torch.Tensor | None, coefficient: float
) -> tuple[torch.Tensor, ...]:
    """A state network (nu, COptiDICE's chi) at the initial, current and next states of ``x``, and its weighted
    gradient penalty on ``points`` (0 when ``points`` is ``None``). With the penalty on, the network runs once on
    the points, whose first rows are the current states: their values and the input gradient come from that one
    pass."""

    def values(states: torch.Tensor) -> torch.Tensor:
        return network(params, states).reshape(states.shape[0])

    def values_with_sum(states: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        out = values(states)
        return out.sum(), out

    n, n0 = x["current"].shape[0], x["init"].shape[0]
    init_v, next_v = values(torch.cat([x["init"], x["following"]])).split([n0, n])
    if points is None:
        return init_v, values(x["current"]), next_v, init_v.new_zeros(())
    grads, on_points = grad(values_with_sum, has_aux=True)(points)
    norms = grads.reshape(grads.shape[0], -1).norm(dim=-1)
    return init_v, on_points[:n], next_v, coefficient * gradient_penalty(norms, target=None)


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
            log_weights = closed_form_log_weight(advantage.detach())
            weights = self_normalized_weights(log_weights)
        produced[next(iter(self.produces))] = weights
        outputs = {"loss_nu": loss_nu, "loss_lambda": loss_lambda}
        outputs |= spoildice_diagnostics(
            init_nu, advantage, log_weights, weights, support, params["lagrange"]
        )
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
            log_weights = demodice_log_weight(advantage.detach(), loss.alpha)
            weights = self_normalized_weights(log_weights)
        produced[next(iter(self.produces))] = weights
        diagnostics = demodice_diagnostics(init_nu, advantage, log_weights, weights, reward)
        return loss_nu, {"loss_nu": loss_nu, **diagnostics}


class CompiledSafeDICE(CompiledDual):
    """The compiled form of :class:`~spoil_torchrl.objectives.SafeDICELoss`: ``loss_nu`` (with the gradient
    penalty), its diagnostics, and the self-normalised weights of D_U. The reward (a function of the data and of
    alpha and the standardisation, which the recipe derives from each seed's discriminator) is computed with the
    inputs, so seeds with different values share one vectorised step (``per_seed``)."""

    per_seed = ("alpha", "reward_mean", "reward_std")

    def __init__(self, loss: SafeDICELoss) -> None:
        self.role = loss.tensor_keys.unlabeled
        super().__init__(loss)

    def inputs(self, batch: TensorDictBase) -> Tensors:
        data = get_role(batch, self.role)
        logit = data.get(self.loss.tensor_keys.logit).reshape(data.batch_size.numel())
        dtype = next(iter(self.nu.params.values())).dtype
        probability, reward = self.loss.reward(logit.detach().to(dtype))
        alpha = torch.tensor(self.loss.alpha, dtype=dtype, device=logit.device)
        return {**super().inputs(batch), "probability": probability, "reward": reward, "alpha": alpha}

    def __call__(
        self, params: Tensors, x: Tensors, produced: dict
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        init_nu, current_nu, next_nu, penalty = self.nu_terms(params, x)
        loss = self.loss
        probability, reward = x["probability"], x["reward"]
        advantage = dice_advantage(reward, current_nu, bellman_backup(next_nu, x["terminated"], loss.gamma))
        loss_nu = safedice_dual(init_nu, advantage, loss.gamma) + penalty
        with torch.no_grad():
            log_weights = safedice_log_weight(advantage.detach())
            weights = self_normalized_weights(log_weights)
        produced[next(iter(self.produces))] = weights
        diagnostics = loss.diagnostics(
            init_nu, advantage, log_weights, weights, probability, reward, alpha=x["alpha"]
        )
        return loss_nu, {"loss_nu": loss_nu, **diagnostics}


class CompiledCOptiDICE(CompiledDual):
    """The compiled form of :class:`~spoil_torchrl.objectives.COptiDICELoss`: nu, chi, tau and lambda's losses
    and diagnostics (:meth:`~spoil_torchrl.objectives.COptiDICELoss.losses`) and the self-normalised weights of
    D_U. The penalty points are drawn for nu, then for chi, as the LossModule draws them."""

    def __init__(self, loss: COptiDICELoss) -> None:
        self.role = loss.tensor_keys.unlabeled
        super().__init__(loss)
        self.chi = PlainNetwork(loss.chi_network, loss.chi_network_params, "COptiDICELoss's chi_network")
        if loss.cost_ub_epsilon > 0:  # chi is trained and penalised after nu
            self.penalised = ("points", "chi_points")

    def parameters(self) -> dict[str, nn.Parameter]:
        return {
            **super().parameters(),
            **{f"chi.{k}": v for k, v in self.chi.params.items()},
            "lagrange_param": self.loss.lagrange_param,
            "tau_param": self.loss.tau_param,
        }

    def inputs(self, batch: TensorDictBase) -> Tensors:
        keys = self.loss.tensor_keys
        out = super().inputs(batch)
        data = get_role(batch, self.role)
        n = data.batch_size.numel()
        return out | {"reward": data.get(keys.reward).reshape(n), "cost": data.get(keys.cost).reshape(n)}

    def __call__(
        self, params: Tensors, x: Tensors, produced: dict
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        loss = self.loss
        init_nu, nu, next_nu, nu_penalty = self.nu_terms(params, x)
        on = loss.gradient_penalty > 0
        chi_values, chi_penalty = None, None
        if loss.cost_ub_epsilon > 0:
            chi_params = {k.removeprefix("chi."): v for k, v in params.items() if k.startswith("chi.")}
            *chi_values, chi_penalty = state_terms(
                self.chi, chi_params, x, x.get("chi_points"), loss.gradient_penalty
            )
            chi_penalty = chi_penalty if on else None
        dtype = nu.dtype
        outputs, _, weights = loss.losses(
            (init_nu, nu, next_nu),
            nu_penalty if on else None,
            None if chi_values is None else tuple(chi_values),
            chi_penalty,
            x["reward"].detach().to(dtype),
            x["cost"].detach().to(dtype),
            x["terminated"],
            lagrange_of(params["lagrange_param"]),
            tau_of(params["tau_param"]),
        )
        produced[next(iter(self.produces))] = weights
        total = sum(value for key, value in outputs.items() if key.startswith("loss_"))
        return total, outputs
