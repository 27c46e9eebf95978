"""Density-ratio discriminators C_P (performant vs unlabeled) and C_S (safe vs unlabeled), Eq. (16)-(18)."""

from __future__ import annotations

import copy
import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from tensordict import TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torch.func import grad

from spoil_torchrl.objectives.functional import check_reduction, gradient_penalty, interpolate, reduce
from spoil_torchrl.objectives.keys import get_role, role_key
from spoil_torchrl.objectives.pure import PureLoss, PureNetwork, Tensors


def logistic_ratio_losses(
    positive_logits: torch.Tensor, unlabeled_logits: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-sample terms of Eq. (16)/(17): ``-log C`` on positives and ``-log(1 - C)`` on unlabeled samples.

    With ``C = sigmoid(logit)`` the maximiser is ``C* = d_pos / (d_pos + d_U)``, so ``logit = log(d_pos / d_U)``
    (Eq. 18): the logit is the log density ratio ``log r_hat``.

    Examples:
        >>> pos, unl = logistic_ratio_losses(torch.zeros(2), torch.zeros(3))
        >>> round(pos.mean().item(), 4), round(unl.mean().item(), 4)  # log 2 each
        (0.6931, 0.6931)
    """
    return F.softplus(-positive_logits), F.softplus(unlabeled_logits)


def nnpu_risks(
    positive_logits: torch.Tensor, unlabeled_logits: torch.Tensor, class_prior: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """The two parts of the non-negative PU risk (section 4.3; Kiryo et al., 2017), as batch means.

    Treating the unlabeled distribution as the mixture ``d_U = eta d_pos + (1 - eta) d_neg``, the
    positive-negative logistic risk ``eta E_pos[-log C] + (1 - eta) E_neg[-log(1 - C)]`` is estimated without
    negatives: the positive part is ``eta E_pos[-log C]`` and the negative part
    ``E_U[-log(1 - C)] - eta E_pos[-log(1 - C)]``, clamped at 0. Without the clamp (the unbiased PU risk of du
    Plessis et al., 2015) the risk is unbounded below once ``eta d_pos > d_U`` somewhere, and a flexible
    discriminator diverges there. The minimiser is the class posterior ``C = eta d_pos / d_U``; convert its logit
    with :func:`pu_log_ratio`.

    Examples:
        >>> positive, negative = nnpu_risks(torch.zeros(2), torch.zeros(2), class_prior=0.5)
        >>> round(positive.item(), 4), round(negative.item(), 4)
        (0.3466, 0.3466)
    """
    positive = class_prior * F.softplus(-positive_logits).mean()
    negative = F.softplus(unlabeled_logits).mean() - class_prior * F.softplus(positive_logits).mean()
    return positive, negative.clamp_min(0.0)


def pu_log_ratio(logit: torch.Tensor, class_prior: float) -> torch.Tensor:
    """``log(d_pos / d_U) = log C - log eta`` for a discriminator trained with :func:`nnpu_risks`.

    Examples:
        >>> round(pu_log_ratio(torch.tensor(0.0), 0.5).item(), 6)  # C = 1/2, eta = 1/2 -> ratio 1
        0.0
    """
    return F.logsigmoid(logit) - math.log(class_prior)


def discriminator_outputs(
    pos_logits: torch.Tensor, unl_logits: torch.Tensor, class_prior: float | None, reduction: str
) -> dict[str, torch.Tensor]:
    """:class:`PUDiscriminatorLoss`'s outputs from the logits, gradient penalty aside: ``loss_positive`` and
    ``loss_unlabeled`` (Eq. 16/17, or the non-negative PU risk with ``class_prior``) and the detached
    ``logit_positive``, ``logit_unlabeled`` and ``accuracy``. :meth:`PUDiscriminatorLoss.terms` calls it.

    Examples:
        >>> out = discriminator_outputs(torch.ones(2), -torch.ones(2), None, "mean")
        >>> round(out["loss_positive"].item(), 4), out["accuracy"].item()
        (0.3133, 1.0)
    """
    if class_prior is None:
        loss_pos, loss_unl = (reduce(x, reduction) for x in logistic_ratio_losses(pos_logits, unl_logits))
        pos_ratio, unl_ratio = pos_logits, unl_logits
    else:
        loss_pos, loss_unl = nnpu_risks(pos_logits, unl_logits, class_prior)
        pos_ratio, unl_ratio = pu_log_ratio(pos_logits, class_prior), pu_log_ratio(unl_logits, class_prior)
    accuracy = 0.5 * ((pos_ratio > 0).float().mean() + (unl_ratio <= 0).float().mean())
    return {
        "loss_positive": loss_pos,
        "loss_unlabeled": loss_unl,
        "logit_positive": pos_logits.detach().mean(),
        "logit_unlabeled": unl_logits.detach().mean(),
        "accuracy": accuracy.detach(),
    }


def discriminator_penalty_points(
    positive: TensorDictBase, unlabeled: TensorDictBase, keys: list[NestedKey]
) -> list[torch.Tensor]:
    """The inputs :class:`PUDiscriminatorLoss`'s gradient penalty is taken at, one tensor per input key: points
    between positive and unlabeled rows, then between shuffled and unlabeled rows (DemoDICE's reference form).
    Random: one permutation, then per key one uniform draw per row for each kind.

    Examples:
        >>> from tensordict import TensorDict
        >>> role = TensorDict({"observation": torch.zeros(4, 3)}, [4])
        >>> [p.shape for p in discriminator_penalty_points(role[:2], role, ["observation"])]
        [torch.Size([6, 3])]
    """
    n = min(positive.shape[0], unlabeled.shape[0])
    shuffled = unlabeled[torch.randperm(unlabeled.shape[0], device=unlabeled.device)]
    return [
        torch.cat(
            [
                interpolate(positive.get(k)[:n], unlabeled.get(k)[:n]),
                interpolate(shuffled.get(k), unlabeled.get(k)),
            ]
        )
        for k in keys
    ]


class LogRatio(TensorDictModuleBase):
    """A frozen view of a discriminator that writes :math:`\\log \\hat r` (Eq. 18) at ``out_key``.

    The logit of a discriminator trained on Eq. (16)/(17) is :math:`\\log \\hat r`; pass ``log_ratio_fn``
    (e.g. ``functools.partial(pu_log_ratio, class_prior=eta)``) for a PU-trained one. Use it with
    :func:`~spoil_torchrl.objectives.annotate` to store :math:`\\log \\hat r_P` next to the unlabeled
    transitions before training :class:`~spoil_torchrl.objectives.SpoilDICELoss`.

    Examples:
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> disc = TensorDictModule(lambda obs: 2 * obs, in_keys=["observation"], out_keys=["logit"])
        >>> td = TensorDict({"observation": torch.ones(2, 1)}, [2])
        >>> LogRatio(disc)(td)["log_ratio_performant"].squeeze(-1).tolist()
        [2.0, 2.0]
    """

    def __init__(
        self,
        discriminator: TensorDictModule,
        *,
        out_key: NestedKey = "log_ratio_performant",
        log_ratio_fn: Callable[[torch.Tensor], torch.Tensor] | None = None,
    ) -> None:
        super().__init__()
        self.discriminator = discriminator
        self.log_ratio_fn = log_ratio_fn
        self.in_keys = list(discriminator.in_keys)
        self.out_keys = [out_key]

    @torch.no_grad()
    def log_ratio(self, tensordict: TensorDictBase) -> torch.Tensor:
        """:math:`\\log \\hat r` for every row of ``tensordict`` (shape ``[*B, 1]``), without gradients."""
        out = self.discriminator(tensordict.select(*self.in_keys).clone()).get(self.discriminator.out_keys[0])
        return out if self.log_ratio_fn is None else self.log_ratio_fn(out)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict.set(self.out_keys[0], self.log_ratio(tensordict))
        return tensordict


class PUDiscriminatorLoss(PureLoss):
    r"""Trains a discriminator separating a positive role (performant or safe) from the unlabeled role.

    Implements Eq. (16) (``positive="performant"``, giving :math:`\hat C_P`) and Eq. (17)
    (``positive="safe"``, giving :math:`\hat C_S`) of the
    `SpoilDICE paper <https://anonymous.4open.science/r/iclr2026_spoildice-214C>`_, with a WGAN-style
    gradient penalty :math:`c\,E[(\lVert\nabla_x f(\tilde x)\rVert - 1)^2]` on points interpolated
    between positive and unlabeled inputs and between pairs of unlabeled inputs (as DemoDICE's reference code
    does). The discriminator's output is a logit, so by Eq. (18) it is directly :math:`\log \hat r`.

    With ``class_prior=eta`` the non-negative PU risk of section 4.3 is used instead (:func:`nnpu_risks`, batch
    level, so only ``"mean"`` reduction); then the logit estimates the class posterior and :func:`pu_log_ratio`
    converts it to :math:`\log \hat r`. :meth:`log_ratio_module` returns the right conversion in both cases.

    Roles are sub-tensordicts of one batch: the discriminator's ``in_keys`` (e.g. ``"observation"``,
    ``"action"``) are read inside ``tensordict[positive]`` and ``tensordict[unlabeled]``. Both role keys are
    ordinary tensordict keys, overridable with :meth:`set_keys`.

    Args:
        discriminator (TensorDictModule): maps its ``in_keys`` to a logit written at its first ``out_key``.

    Keyword Args:
        positive (NestedKey): the positive role. Default ``"performant"``.
        unlabeled (NestedKey): the unlabeled role. Default ``"unlabeled"``.
        gradient_penalty (float): coefficient of the gradient penalty; 0 disables it. Default 10 (Table J).
        class_prior (float, optional): PU class prior eta in (0, 1); ``None`` (default) is Eq. (16)/(17).
        reduction (str): ``"mean"`` (default), ``"sum"`` or ``"none"`` for the per-sample terms.

    Output keys: ``loss_positive`` and ``loss_unlabeled`` (the two expectations of the objective; their sum
    is Eq. (16)/(17) negated), ``loss_gradient_penalty``, and the detached diagnostics ``logit_positive``,
    ``logit_unlabeled`` (mean logits) and ``accuracy`` (balanced, positive where :math:`\hat r > 1`).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from spoil_torchrl.modules import make_discriminator
        >>> disc = make_discriminator(3, 2, hidden_cells=(16,))
        >>> loss = PUDiscriminatorLoss(disc, positive="safe")
        >>> def role(n):
        ...     return TensorDict({"observation": torch.randn(n, 3), "action": torch.rand(n, 2)}, [n])
        >>> batch = TensorDict({"safe": role(8), "unlabeled": role(16)}, [])
        >>> out = loss(batch)
        >>> sorted(k for k in out.keys() if k.startswith("loss_"))
        ['loss_gradient_penalty', 'loss_positive', 'loss_unlabeled']
        >>> sum(v for k, v in out.items() if k.startswith("loss_")).backward()
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys.

        Attributes:
            positive (NestedKey): sub-tensordict of the positive role. Defaults to ``"performant"``.
            unlabeled (NestedKey): sub-tensordict of the unlabeled role. Defaults to ``"unlabeled"``.
        """

        positive: NestedKey = "performant"
        unlabeled: NestedKey = "unlabeled"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    out_keys = [
        "loss_positive",
        "loss_unlabeled",
        "loss_gradient_penalty",
        "logit_positive",
        "logit_unlabeled",
        "accuracy",
    ]

    discriminator_network: TensorDictModule
    discriminator_network_params: TensorDictParams
    target_discriminator_network_params: TensorDictParams

    def __init__(
        self,
        discriminator: TensorDictModule,
        *,
        positive: NestedKey = "performant",
        unlabeled: NestedKey = "unlabeled",
        gradient_penalty: float = 10.0,
        class_prior: float | None = None,
        reduction: str | None = None,
    ) -> None:
        super().__init__()
        if gradient_penalty < 0:
            raise ValueError(f"gradient_penalty must be >= 0, got {gradient_penalty}")
        if class_prior is not None and not 0.0 < class_prior < 1.0:
            raise ValueError(f"class_prior must lie in (0, 1), got {class_prior}")
        if class_prior is not None and reduction not in (None, "mean"):
            raise ValueError(
                "the non-negative PU risk (class_prior set) is a batch-level risk: use reduction='mean'"
            )
        if len(discriminator.out_keys) < 1:
            raise ValueError("the discriminator must write its logit to an out_key")
        self.convert_to_functional(discriminator, "discriminator_network")
        self.gradient_penalty = float(gradient_penalty)
        self.class_prior = class_prior
        self.reduction = check_reduction(reduction)
        self.set_keys(positive=positive, unlabeled=unlabeled)

    def frozen_network(self) -> TensorDictModule:
        """A copy of the discriminator with its current weights, detached from this loss: training the loss
        further does not change it. (TorchRL's ``get_stateful_net(copy=True)`` copies the module but puts the
        loss's own parameters into it, so it would follow the training.)"""
        net = copy.deepcopy(self.get_stateful_net("discriminator_network", copy=True))
        return net.requires_grad_(False)

    def log_ratio_module(self, out_key: NestedKey = "log_ratio_performant") -> LogRatio:
        """A frozen copy of the trained discriminator (:meth:`frozen_network`) writing :math:`\\log \\hat r`
        (Eq. 18) at ``out_key``, with the PU conversion applied when ``class_prior`` is set."""
        net = self.frozen_network()
        fn = (
            None
            if self.class_prior is None
            else functools.partial(pu_log_ratio, class_prior=self.class_prior)
        )
        return LogRatio(net, out_key=out_key, log_ratio_fn=fn)

    @property
    def in_keys(self) -> list[NestedKey]:
        keys = self.discriminator_network.in_keys
        roles = (self.tensor_keys.positive, self.tensor_keys.unlabeled)
        return [role_key(role, key) for role in roles for key in keys]

    functional_params = ("discriminator_network_params",)

    @property
    def discriminator(self) -> PureNetwork:
        """The discriminator as a function of its parameters."""
        return self._pure(
            "discriminator",
            lambda: PureNetwork(
                self.discriminator_network,
                self.discriminator_network_params,
                "PUDiscriminatorLoss's discriminator",
            ),
        )

    def term_parameters(self) -> dict[str, nn.Parameter]:
        net = self.discriminator.parameters(self.discriminator_network_params)
        return {f"net.{k}": v for k, v in net.items()}

    def check_compilable(self) -> None:
        self.discriminator.check_compilable()

    def inputs(self, tensordict: TensorDictBase, produced: frozenset = frozenset()) -> Tensors:
        """The discriminator's inputs on both roles (``positive.<i>``, ``unlabeled.<i>`` in ``in_keys`` order)
        and, when the penalty is on, its points (:func:`discriminator_penalty_points`, random, drawn here)."""
        keys, roles = self.discriminator.in_keys, self.tensor_keys
        positive = get_role(tensordict, roles.positive).select(*keys).reshape(-1)
        unlabeled = get_role(tensordict, roles.unlabeled).select(*keys).reshape(-1)
        out = {f"positive.{i}": positive.get(k) for i, k in enumerate(keys)}
        out |= {f"unlabeled.{i}": unlabeled.get(k) for i, k in enumerate(keys)}
        if self.gradient_penalty != 0:
            points = discriminator_penalty_points(positive, unlabeled, keys)
            out |= {f"points.{i}": p for i, p in enumerate(points)}
        return out

    def terms(self, params: Tensors, x: Tensors, produced: dict) -> tuple[torch.Tensor, Tensors]:
        """``loss_positive``, ``loss_unlabeled`` (:func:`discriminator_outputs`), the WGAN-style gradient
        penalty :math:`c\\,E[(\\lVert \\nabla_x C(x) \\rVert - 1)^2]` on the points, and the diagnostics."""
        net_params = {k.removeprefix("net."): v for k, v in params.items()}
        inputs = range(len(self.discriminator.in_keys))

        def logits(*xs: torch.Tensor) -> torch.Tensor:
            return self.discriminator(net_params, *xs).reshape(-1)

        n_pos = x["positive.0"].shape[0]
        both = logits(*(torch.cat([x[f"positive.{i}"], x[f"unlabeled.{i}"]]) for i in inputs))
        outputs = discriminator_outputs(both[:n_pos], both[n_pos:], self.class_prior, self.reduction)
        penalty = both.new_zeros(())
        if "points.0" in x:
            grads = grad(lambda *xs: logits(*xs).sum(), argnums=tuple(inputs))(
                *(x[f"points.{i}"] for i in inputs)
            )
            norms = torch.cat([g.reshape(g.shape[0], -1) for g in grads], dim=-1).norm(dim=-1)
            penalty = self.gradient_penalty * gradient_penalty(norms, target=1.0)
        if self.reduction == "none":  # per-sample losses of two roles: their sums are what a step descends
            total = outputs["loss_positive"].sum() + outputs["loss_unlabeled"].sum() + penalty
        else:
            total = outputs["loss_positive"] + outputs["loss_unlabeled"] + penalty
        return total, {**outputs, "loss_gradient_penalty": penalty}
