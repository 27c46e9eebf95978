"""Weighted behavioural cloning, Eq. (20): one loss for BC, filtered BC and DICE policy extraction."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase, TensorDictParams
from tensordict.nn import ProbabilisticTensorDictSequential
from tensordict.utils import NestedKey
from torch import nn

from spoil_torchrl.objectives.functional import check_reduction, reduce
from spoil_torchrl.objectives.keys import get_role, role_entry, role_key
from spoil_torchrl.objectives.pure import PureLoss, PurePolicy, Tensors, flat_rows


def weighted_nll(log_prob: torch.Tensor, weight: torch.Tensor | None) -> torch.Tensor:
    """Per-sample terms of Eq. (20): :math:`-w(s,a) \\log \\pi(a|s)` (``weight=None`` means :math:`w = 1`).

    Examples:
        >>> weighted_nll(torch.tensor([-1.0, -2.0]), torch.tensor([0.0, 2.0])).tolist()
        [0.0, 4.0]
    """
    nll = -log_prob
    return nll if weight is None else weight.detach().to(nll.dtype) * nll


def weighted_bc_outputs(
    log_prob: torch.Tensor, weight: torch.Tensor | None, reduction: str
) -> dict[str, torch.Tensor]:
    """What :class:`WeightedBCLoss` outputs from the batch's log-likelihoods and weights: ``loss_actor``
    (Eq. 20, reduced) and the detached ``log_prob`` and ``weight_mean``. :meth:`WeightedBCLoss.terms` calls it.

    Examples:
        >>> out = weighted_bc_outputs(torch.tensor([-1.0, -2.0]), torch.tensor([0.0, 2.0]), "mean")
        >>> out["loss_actor"].item(), out["log_prob"].item(), out["weight_mean"].item()
        (2.0, -1.5, 1.0)
    """
    return {
        "loss_actor": reduce(weighted_nll(log_prob, weight), reduction),
        "log_prob": log_prob.detach().mean(),
        "weight_mean": torch.ones((), device=log_prob.device)
        if weight is None
        else weight.detach().float().mean(),
    }


#: What writes the weight :class:`WeightedBCLoss` reads, said when its role lacks it.
WEIGHT_WRITERS = (
    "a DICE loss (SpoilDICELoss, DemoDICELoss, SafeDICELoss, COptiDICELoss) writes 'dice_weight' into its "
    "role when it runs before WeightedBCLoss in the step; a pre-training annotates the others, e.g. FBC's "
    "'safe_support', JFBC's 'jfbc_weight'"
)


class WeightedBCLoss(PureLoss):
    r"""Weighted behavioural cloning :math:`E_{(s,a)\sim D}[-w(s,a) \log \pi(a|s)]` (Eq. 20).

    From the `SpoilDICE paper <https://anonymous.4open.science/r/iclr2026_spoildice-214C>`_, appendix D.3.
    The weight is read (and detached) from a key of the role's sub-tensordict, so one loss covers:

    * BC: ``role="performant"``, ``weight=None`` (:math:`w = 1`);
    * filtered BC: ``role="performant"``, ``weight="safe_support"`` (:math:`w = \hat{\mathbb 1}_S`);
    * DICE policy extraction: ``role="unlabeled"``, ``weight="dice_weight"`` (written by
      :class:`~spoil_torchrl.objectives.SpoilDICELoss`).

    ``"mean"`` reduction is the plain sample mean of Eq. (20), not a self-normalised one; DICE weights are
    already normalised to batch mean 1.

    Args:
        actor_network (ProbabilisticTensorDictSequential): the policy; ``get_dist`` must give :math:`\pi(\cdot|s)`.

    Keyword Args:
        role (NestedKey): sub-tensordict holding the transitions. Default ``"performant"``.
        weight (NestedKey, optional): weight entry inside the role; ``None`` for plain BC.
        reduction (str): ``"mean"`` (default), ``"sum"`` or ``"none"``.

    Output keys: ``loss_actor`` and the detached diagnostics ``log_prob`` (mean log-likelihood of the batch
    actions) and ``weight_mean``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from spoil_torchrl.modules import make_actor
        >>> actor = make_actor(3, 2, hidden_cells=(16,))
        >>> loss = WeightedBCLoss(actor, role="unlabeled", weight="dice_weight")
        >>> unlabeled = TensorDict({"observation": torch.randn(8, 3), "action": torch.rand(8, 2) * 2 - 1,
        ...                         "dice_weight": torch.rand(8, 1)}, [8])
        >>> batch = TensorDict({"unlabeled": unlabeled}, [])
        >>> out = loss(batch)
        >>> out["loss_actor"].backward()
        >>> loss.set_keys(weight=None)  # plain BC on the same role
        >>> bool(loss(batch)["weight_mean"] == 1)
        True
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys.

        Attributes:
            role (NestedKey): sub-tensordict of the cloned transitions. Defaults to ``"performant"``.
            action (NestedKey): inside ``role``, the demonstrated action. Defaults to ``"action"``.
            weight (NestedKey, optional): inside ``role``, the per-sample weight; ``None`` means 1.
        """

        role: NestedKey = "performant"
        action: NestedKey = "action"
        weight: NestedKey | None = None

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    out_keys = ["loss_actor", "log_prob", "weight_mean"]

    actor_network: ProbabilisticTensorDictSequential
    actor_network_params: TensorDictParams
    target_actor_network_params: TensorDictParams

    def __init__(
        self,
        actor_network: ProbabilisticTensorDictSequential,
        *,
        role: NestedKey = "performant",
        weight: NestedKey | None = None,
        reduction: str | None = None,
    ) -> None:
        super().__init__()
        if not hasattr(actor_network, "get_dist"):
            raise TypeError("actor_network must be a probabilistic actor with a get_dist method")
        self.convert_to_functional(actor_network, "actor_network")
        self.reduction = check_reduction(reduction)
        self.set_keys(role=role, weight=weight)

    def set_keys(self, **kwargs) -> None:
        # ``weight=None`` is meaningful (plain BC), so it is stored instead of restoring the default.
        weight_given = "weight" in kwargs
        weight = kwargs.pop("weight", None)
        super().set_keys(**kwargs)
        if weight_given:
            self.tensor_keys.weight = weight

    functional_params = ("actor_network_params",)

    @property
    def in_keys(self) -> list[NestedKey]:
        keys = self.tensor_keys
        inner = [*self.actor_network.in_keys, keys.action]
        if keys.weight is not None:
            inner.append(keys.weight)
        return [role_key(keys.role, k) for k in inner]

    @property
    def policy(self) -> PurePolicy:
        """The actor as a function of its parameters (:class:`~spoil_torchrl.objectives.pure.PurePolicy`)."""
        return self._pure(
            "actor",
            lambda: PurePolicy(self.actor_network, self.actor_network_params, "WeightedBCLoss's actor"),
        )

    def term_parameters(self) -> dict[str, nn.Parameter]:
        return {f"policy.{k}": v for k, v in self.policy.parameters(self.actor_network_params).items()}

    def check_compilable(self) -> None:
        self.policy.check_compilable()

    @property
    def weight_key(self) -> NestedKey | None:
        """The weight's entry, ``(role, weight)`` (``None`` for plain BC)."""
        keys = self.tensor_keys
        return None if keys.weight is None else role_key(keys.role, keys.weight)

    def inputs(self, tensordict: TensorDictBase, produced: frozenset = frozenset()) -> Tensors:
        """The role's states and actions, and its weights unless an earlier loss of the step produces them."""
        keys = self.tensor_keys
        role = get_role(tensordict, keys.role)
        out = {"state": self.policy.states(role), "action": flat_rows(role, keys.action)}
        if keys.weight is not None and self.weight_key not in produced:
            out["weight"] = role_entry(role, keys.role, keys.weight, WEIGHT_WRITERS).reshape(-1)
        return out

    def terms(self, params: Tensors, x: Tensors, produced: dict) -> tuple[torch.Tensor, Tensors]:
        """``loss_actor`` (Eq. 20) and the diagnostics; the weight is an input, or an earlier loss's product."""
        policy_params = {k.removeprefix("policy."): v for k, v in params.items()}
        log_prob = self.policy.log_prob(policy_params, x["state"], x["action"])
        weight = produced[self.weight_key] if self.weight_key in produced else x.get("weight")
        outputs = weighted_bc_outputs(log_prob, weight, self.reduction)
        return outputs["loss_actor"], outputs
