"""The SpoilDICE dual over (nu, lambda): Eq. (7), (11), (12) and (19) of the paper."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import nn

from spoil_torchrl.objectives.dice import DICELoss
from spoil_torchrl.objectives.functional import (
    bellman_backup,
    log_mean_exp,
    self_normalized_weights,
    weight_diagnostics,
)
from spoil_torchrl.objectives.keys import get_role, role_entry, role_key
from spoil_torchrl.objectives.pure import Tensors
from spoil_torchrl.objectives.support import check_support_indicator


def support_term(lagrange: torch.Tensor, support: torch.Tensor) -> torch.Tensor:
    """The support term of Eq. (7): :math:`\\lambda \\mathbb 1_S(s,a)`, or with several constraints (``lagrange``
    of shape ``[K]``, ``support`` ``[n, K]``) :math:`\\sum_k \\lambda_k \\mathbb 1_k(s,a)`
    (``docs/several_constraints.md``).

    Examples:
        >>> support_term(torch.tensor(2.0), torch.tensor([1.0, 0.0])).tolist()
        [2.0, 0.0]
        >>> support_term(torch.tensor([2.0, 3.0]), torch.tensor([[1.0, 1.0], [0.0, 1.0]])).tolist()
        [5.0, 3.0]
    """
    return lagrange * support if lagrange.ndim == 0 else (support * lagrange).sum(-1)


def spoildice_advantage(
    log_ratio: torch.Tensor,
    support: torch.Tensor,
    lagrange: torch.Tensor,
    nu: torch.Tensor,
    backup: torch.Tensor,
) -> torch.Tensor:
    """Eq. (7): :math:`A_{\\nu,\\lambda}(s,a) = \\log r_P(s,a) + \\lambda \\mathbb 1_S(s,a) + \\gamma(T\\nu)(s,a) - \\nu(s)`
    (with several constraints, :math:`\\sum_k \\lambda_k \\mathbb 1_k` in place of :math:`\\lambda \\mathbb 1_S`:
    :func:`support_term`).

    (The :math:`-\\log w` term of Eq. (7) cancels in the closed form, Eq. (11).)

    Examples:
        >>> spoildice_advantage(torch.tensor([1.0]), torch.tensor([1.0]), torch.tensor(2.0),
        ...                     torch.tensor([0.5]), torch.tensor([0.25])).item()
        2.75
    """
    return log_ratio + support_term(lagrange, support) + backup - nu


def closed_form_log_weight(advantage: torch.Tensor) -> torch.Tensor:
    """Eq. (11): :math:`\\log w^*_{\\nu,\\lambda}(s,a) = A_{\\nu,\\lambda}(s,a) - 1`, kept in log space.

    Examples:
        >>> closed_form_log_weight(torch.tensor([1.0])).exp().item()
        1.0
    """
    return advantage - 1.0


def spoildice_dual(
    init_nu: torch.Tensor, advantage: torch.Tensor, lagrange: torch.Tensor, gamma: float
) -> torch.Tensor:
    """Eq. (19): :math:`\\tilde L(\\nu,\\lambda) = (1-\\gamma) E_{\\rho_0}[\\nu(s_0)] + \\log E_U[\\exp A] - \\lambda`.

    This log-sum-exp form has the same minimiser in :math:`\\nu` as Eq. (12) (Proposition 3). Its gradient in
    :math:`\\lambda` is :math:`E_U[\\tilde w \\mathbb 1_S] - 1` with :math:`\\tilde w` the self-normalised
    closed-form weights, i.e. Eq. (12)'s :math:`\\lambda`-gradient :math:`E_U[w^* \\mathbb 1_S] - 1` evaluated
    at the normalisation :math:`E_U[w^*] = 1` that holds at the optimum.

    With several constraints (``lagrange`` of shape ``[K]``) the last term is :math:`\\sum_k \\lambda_k`, and the
    gradient in :math:`\\lambda_k` is :math:`E_U[\\tilde w \\mathbb 1_k] - 1` (``docs/several_constraints.md``).

    Examples:
        >>> spoildice_dual(torch.zeros(3), torch.zeros(4), torch.tensor(0.5), gamma=0.9).item()
        -0.5
    """
    multipliers = lagrange if lagrange.ndim == 0 else lagrange.sum()
    return (1.0 - gamma) * init_nu.mean() + log_mean_exp(advantage) - multipliers


def spoildice_losses(
    init_nu: torch.Tensor,
    nu: torch.Tensor,
    next_nu: torch.Tensor,
    terminated: torch.Tensor,
    log_ratio: torch.Tensor,
    support: torch.Tensor,
    lagrange: torch.Tensor,
    gamma: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(loss_nu, loss_lambda, advantage)`` of :class:`SpoilDICELoss` from nu's values (no gradient penalty).

    ``loss_nu`` is Eq. (19) with :math:`\\lambda` detached, ``loss_lambda`` Eq. (19) with :math:`\\nu` detached,
    and ``advantage`` Eq. (7) with :math:`\\lambda` detached (the exponent of the weights). :meth:`SpoilDICELoss.terms`
    calls it, in the eager and the compiled step alike.

    Examples:
        >>> z = torch.zeros(2)
        >>> loss_nu, loss_lambda, adv = spoildice_losses(z, z, z, z, z, torch.ones(2), torch.tensor(1.0), 0.9)
        >>> loss_nu.item(), loss_lambda.item(), adv.tolist()
        (0.0, 0.0, [1.0, 1.0])
    """
    backup = bellman_backup(next_nu, terminated, gamma)
    adv_nu = spoildice_advantage(log_ratio, support, lagrange.detach(), nu, backup)
    adv_lambda = adv_nu.detach() + support_term(lagrange - lagrange.detach(), support)
    loss_nu = spoildice_dual(init_nu, adv_nu, lagrange.detach(), gamma)
    loss_lambda = spoildice_dual(init_nu.detach(), adv_lambda, lagrange, gamma)
    return loss_nu, loss_lambda, adv_nu


def spoildice_diagnostics(
    init_nu: torch.Tensor,
    advantage: torch.Tensor,
    log_weights: torch.Tensor,
    weights: torch.Tensor,
    support: torch.Tensor,
    lagrange: torch.Tensor,
) -> dict[str, torch.Tensor]:
    """The detached diagnostics :class:`SpoilDICELoss` outputs beside its losses (see its docstring), from nu,
    the advantage, its closed-form log weights (Eq. 11) and their self-normalised weights.

    Examples:
        >>> z, one = torch.zeros(2), torch.ones(2)
        >>> out = spoildice_diagnostics(z, z, z - 1, one, one, torch.tensor(0.5))
        >>> out["support_weight"].item(), out["effective_sample_size"].item()
        (1.0, 1.0)

    With several constraints ``lagrange`` is :math:`\\sum_k \\lambda_k`, ``support_fraction`` and
    ``support_weight`` are of the intersection (a transition inside every support), and ``lagrange_<k>``,
    ``support_fraction_<k>`` and ``support_weight_<k>`` give each constraint's.
    """
    with torch.no_grad():
        if lagrange.ndim == 0:
            inside, per_constraint = support, {"lagrange": lagrange.detach().clone()}
        else:
            inside = support.prod(-1)
            per_constraint = {"lagrange": lagrange.detach().sum()}
            for k in range(lagrange.shape[-1]):
                per_constraint |= {
                    f"lagrange_{k}": lagrange.detach()[k].clone(),
                    f"support_fraction_{k}": support[:, k].mean(),
                    f"support_weight_{k}": (weights * support[:, k]).mean(),
                }
        return {
            **per_constraint,
            **weight_diagnostics(log_weights, weights),
            "support_fraction": inside.mean(),
            "support_weight": (weights * inside).mean(),
            "nu_init": init_nu.detach().mean(),
            "advantage_mean": advantage.detach().mean(),
        }


#: What writes the annotations :class:`SpoilDICELoss` reads, said when D_U lacks them.
LOG_RATIO_WRITER = (
    "C_P's log-ratio, written by PUDiscriminatorLoss.log_ratio_module('log_ratio_performant') in the "
    "pre-training (buffers.annotate)"
)
SUPPORT_WRITER = "the support indicator of Eq. 13, written by a fitted SupportEstimator in the pre-training"


class SpoilDICELoss(DICELoss):
    r"""SpoilDICE's dual objective over :math:`\nu` and the support multiplier :math:`\lambda`.

    From the `SpoilDICE paper <https://anonymous.4open.science/r/iclr2026_spoildice-214C>`_ (section 4,
    Algorithm 1). For unlabeled transitions :math:`(s, a, s')` the advantage (Eq. 7)

    .. math:: A_{\nu,\lambda}(s,a) = \log \hat r_P(s,a) + \lambda \hat{\mathbb 1}_S(s,a) + \gamma \nu(s')(1 - d) - \nu(s)

    (with :math:`d` the *terminated* flag) gives the closed-form correction :math:`w^* = \exp(A - 1)` (Eq. 11).

    * ``loss_nu`` is the log-sum-exp dual of Eq. (19) (with :math:`\lambda` detached) plus a gradient penalty
      :math:`c\,E[\lVert \nabla_s \nu(\tilde s) \rVert^2]` on unlabeled states, on states interpolated between
      initial and unlabeled states and between :math:`s` and :math:`s'` (DemoDICE's reference form).
    * ``loss_lambda`` is Eq. (19) with :math:`\nu` detached; its gradient :math:`E_U[\tilde w \hat{\mathbb 1}_S] - 1`
      is Eq. (12)'s at normalised weights (see :func:`spoildice_dual`). Using the raw :math:`E_U[w^*]` of Eq. (12)
      together with Eq. (19) would be inconsistent: Eq. (19) leaves the constant offset of :math:`\nu` free, and
      that offset would then drive :math:`\lambda` instead of the support constraint. :math:`\lambda` is a free
      real (equality constraint). When :math:`d_P` puts mass off the safe support the constraint can only be met
      in the limit, so :math:`\lambda` keeps growing (with Adam by up to about one learning rate per step);
      this is expected, and it is why :math:`\hat{\mathbb 1}_S` should not be all zero in a batch.

    The self-normalised weights :math:`\tilde w = w^*/\overline{w^*}` (batch mean 1, computed after subtracting
    the batch max, so they never overflow) are written, detached, into the *input* tensordict at
    ``(unlabeled, weight)`` for :class:`~spoil_torchrl.objectives.WeightedBCLoss` (Eq. 20).

    The input holds two roles: ``unlabeled`` transitions with the annotations ``log_ratio_performant``
    (:math:`\log \hat r_P`, Eq. 18) and ``safe_support`` (:math:`\hat{\mathbb 1}_S`, Eq. 13), and ``init`` states
    (:math:`\rho_0`). All keys can be changed with :meth:`set_keys`.

    Args:
        nu_network (TensorDictModule): :math:`\nu(s)`, reading its ``in_keys`` inside a role and writing a scalar.

    Keyword Args:
        gamma (float): discount in (0, 1). Default 0.99 (Table J).
        gradient_penalty (float): coefficient of the :math:`\nu` gradient penalty; 0 disables.
            Default 1e-4 (on standardised states; see CONTRIBUTING.md).
        init_lagrange (float): initial :math:`\lambda` (of every :math:`\lambda_k`). Default 0.
        constraints (int): the number K of safety constraints, one support indicator and one multiplier
            :math:`\lambda_k` each (``docs/several_constraints.md``): ``support`` then holds ``[n, K]``
            indicators, the advantage has :math:`\sum_k \lambda_k \hat{\mathbb 1}_k` in place of
            :math:`\lambda \hat{\mathbb 1}_S`, and the diagnostics come per constraint too. Default 1, the
            paper's single constraint (a scalar :math:`\lambda`, exactly as with one).
        reduction (str): only ``"mean"``: the log-sum-exp couples the samples of a batch, so the objective has no
            per-sample form.

    Output keys: ``loss_nu``, ``loss_lambda``, and detached diagnostics ``lagrange``, ``log_weight_mean``
    (:math:`\log E_U[w^*]`; Eq. (19) leaves :math:`\nu`'s constant offset free, so only its changes are
    informative), ``weight_max`` (largest :math:`\tilde w`),
    ``effective_sample_size`` (Kish ESS of :math:`\tilde w` as a fraction of the batch), ``support_fraction``
    (:math:`E_U[\hat{\mathbb 1}_S]`), ``support_weight`` (:math:`E_U[\tilde w \hat{\mathbb 1}_S]`, 1 when the
    support constraint holds), ``nu_init`` and ``advantage_mean``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from spoil_torchrl.modules import make_value_network
        >>> loss = SpoilDICELoss(make_value_network(3, hidden_cells=(16,)), gamma=0.99)
        >>> n = 8
        >>> unlabeled = TensorDict({
        ...     "observation": torch.randn(n, 3),
        ...     "next": {"observation": torch.randn(n, 3), "terminated": torch.zeros(n, 1, dtype=torch.bool)},
        ...     "log_ratio_performant": torch.randn(n, 1),
        ...     "safe_support": torch.randint(0, 2, (n, 1)).float(),
        ... }, [n])
        >>> init = TensorDict({"observation": torch.randn(4, 3)}, [4])
        >>> batch = TensorDict({"unlabeled": unlabeled, "init": init}, [])
        >>> out = loss(batch)
        >>> (out["loss_nu"] + out["loss_lambda"]).backward()
        >>> batch["unlabeled", "dice_weight"].shape, round(batch["unlabeled", "dice_weight"].mean().item(), 4)
        (torch.Size([8, 1]), 1.0)
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys.

        Attributes:
            unlabeled (NestedKey): sub-tensordict of unlabeled transitions. Defaults to ``"unlabeled"``.
            init (NestedKey): sub-tensordict of initial states. Defaults to ``"init"``.
            next (NestedKey): inside ``unlabeled``, where the next state's entries live. Defaults to ``"next"``.
            terminated (NestedKey): inside ``unlabeled``. Defaults to ``("next", "terminated")``.
            log_ratio (NestedKey): inside ``unlabeled``, :math:`\\log \\hat r_P`. Defaults to
                ``"log_ratio_performant"``.
            support (NestedKey): inside ``unlabeled``, :math:`\\hat{\\mathbb 1}_S`. Defaults to ``"safe_support"``.
            weight (NestedKey): inside ``unlabeled``, where the detached weights are written. Defaults to
                ``"dice_weight"``.
            advantage (NestedKey): inside ``unlabeled``, where the detached advantage (the exponent of the
                weights) is written, for diagnostics. Defaults to ``"dice_advantage"``.
        """

        unlabeled: NestedKey = "unlabeled"
        init: NestedKey = "init"
        next: NestedKey = "next"
        terminated: NestedKey = ("next", "terminated")
        log_ratio: NestedKey = "log_ratio_performant"
        support: NestedKey = "safe_support"
        weight: NestedKey = "dice_weight"
        advantage: NestedKey = "dice_advantage"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    out_keys = [
        "loss_nu",
        "loss_lambda",
        "lagrange",
        "log_weight_mean",
        "weight_max",
        "effective_sample_size",
        "support_fraction",
        "support_weight",
        "nu_init",
        "advantage_mean",
    ]

    _PER_CONSTRAINT = ("lagrange", "support_fraction", "support_weight")

    nu_network: TensorDictModule
    nu_network_params: TensorDictParams
    target_nu_network_params: TensorDictParams

    def __init__(
        self,
        nu_network: TensorDictModule,
        *,
        gamma: float = 0.99,
        gradient_penalty: float = 1e-4,
        init_lagrange: float = 0.0,
        constraints: int = 1,
        reduction: str | None = None,
    ) -> None:
        super().__init__()
        if isinstance(constraints, bool) or not isinstance(constraints, int) or constraints < 1:
            raise ValueError(f"constraints must be an integer >= 1, got {constraints!r}")
        self._setup_dual(nu_network, gamma=gamma, gradient_penalty=gradient_penalty, reduction=reduction)
        self.constraints = constraints
        initial = torch.tensor(float(init_lagrange))
        self.lagrange = nn.Parameter(initial if constraints == 1 else initial.repeat(constraints))
        if constraints > 1:  # each constraint's diagnostics too
            per = [f"{name}_{k}" for k in range(constraints) for name in self._PER_CONSTRAINT]
            self.out_keys = [*self.out_keys, *per]

    @property
    def dual_role(self) -> NestedKey:
        return self.tensor_keys.unlabeled

    @property
    def in_keys(self) -> list[NestedKey]:
        return self._role_in_keys(
            self.tensor_keys.unlabeled, self.tensor_keys.log_ratio, self.tensor_keys.support
        )

    def term_parameters(self) -> dict[str, nn.Parameter]:
        return {**super().term_parameters(), "lagrange": self.lagrange}

    def inputs(self, tensordict: TensorDictBase, produced: frozenset = frozenset()) -> Tensors:
        """The dual's inputs (:meth:`DICELoss.inputs`), :math:`\\log \\hat r_P` and the checked support
        indicator of the unlabeled transitions."""
        keys = self.tensor_keys
        unlabeled = get_role(tensordict, keys.unlabeled)
        n = unlabeled.batch_size.numel()
        support = role_entry(unlabeled, keys.unlabeled, keys.support, SUPPORT_WRITER)
        if self.constraints == 1:
            support = support.reshape(n)
        else:
            if support.shape[-1] != self.constraints or support.numel() != n * self.constraints:
                raise ValueError(
                    f"{role_key(keys.unlabeled, keys.support)} has shape {tuple(support.shape)}; with "
                    f"constraints={self.constraints} it holds one indicator per constraint, [{n}, {self.constraints}]"
                )
            support = support.reshape(n, self.constraints)
        check_support_indicator(support, role_key(keys.unlabeled, keys.support))
        return {
            **super().inputs(tensordict),
            "log_ratio": role_entry(unlabeled, keys.unlabeled, keys.log_ratio, LOG_RATIO_WRITER).reshape(n),
            "support": support,
        }

    def terms(self, params: Tensors, x: Tensors, produced: dict) -> tuple[torch.Tensor, Tensors]:
        """``loss_nu`` (with the gradient penalty), ``loss_lambda`` and the diagnostics; the self-normalised
        weights (Eq. 11) and the advantage go into ``produced``."""
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
            self.gamma,
        )
        loss_nu = loss_nu + penalty
        with torch.no_grad():
            log_weights = closed_form_log_weight(advantage.detach())
            weights = self_normalized_weights(log_weights)
        self._produce(produced, weights, advantage)
        outputs = {"loss_nu": loss_nu, "loss_lambda": loss_lambda}
        outputs |= spoildice_diagnostics(
            init_nu, advantage, log_weights, weights, support, params["lagrange"]
        )
        return loss_nu + loss_lambda, outputs
