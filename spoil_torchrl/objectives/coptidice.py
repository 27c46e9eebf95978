"""COptiDICE (Lee et al., 2022): offline constrained RL by stationary distribution correction estimation, the
baseline COptiDICE of section 5 (with the dataset's true reward and cost)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import nn

from spoil_torchrl.objectives.coptidice_equations import (
    _inverse_softplus,
    coptidice_dual,
    coptidice_log_weight,
    coptidice_weight,
    cost_bound_objective,
    cost_flow_residual,
    lagrange_loss,
    lagrange_of,
    soft_chi2,
    tau_of,
    temperature_loss,
    worst_case_weights,
)
from spoil_torchrl.objectives.dice import DICELoss, state_terms
from spoil_torchrl.objectives.functional import (
    bellman_backup,
    dice_advantage,
    effective_sample_size,
    self_normalized_weights,
)
from spoil_torchrl.objectives.keys import get_role, role_entry
from spoil_torchrl.objectives.pure import Tensors

#: Where the reward and cost :class:`COptiDICELoss` reads come from, said when its role lacks them.
DATA_WRITER = "the dataset's per-step reward and cost, in TED layout under 'next'"


class COptiDICELoss(DICELoss):
    r"""COptiDICE (Lee et al., 2022): the constrained DICE dual over :math:`(\nu, \lambda)` and the cost upper bound
    over :math:`(\chi, \tau)`, on the unlabeled role's true reward and cost.

    COptiDICE (`official code <https://github.com/google-deepmind/constrained_optidice>`_, PyTorch port in OSRL)
    solves :math:`\max_d E_d[r] - \alpha D_f(d \| d_D)` s.t. :math:`E_d[c] \le \hat c` over stationary
    distributions, with :math:`f` soft-:math:`\chi^2` (:func:`soft_chi2`) and :math:`d_D` the data's
    distribution (the ``unlabeled`` role). The `SpoilDICE paper
    <https://anonymous.4open.science/r/iclr2026_spoildice-214C>`_ runs it with the dataset's true reward and cost
    (section 5) and :math:`\alpha = 0.01` (Table J). With
    :math:`e_{\nu,\lambda} = r - \lambda c + \gamma\nu(s')(1-d) - \nu(s)` (:math:`d` the *terminated* flag,
    :math:`\lambda` detached):

    * ``loss_nu``: :func:`coptidice_dual` at :math:`w^* =` :func:`coptidice_weight` :math:`(e_{\nu,\lambda})`, plus
      a gradient penalty :math:`c\,E[\lVert \nabla_s \nu \rVert^2]` (Table J: 10; the house form,
      :func:`~spoil_torchrl.objectives.dice.state_terms`, where the official code penalises
      :math:`\max(0, \lVert\nabla\nu\rVert - 5)^2` on init-data interpolations with :math:`10^{-5}`).
    * ``loss_chi``: the cost upper bound (``cost_ub_epsilon`` :math:`= \epsilon > 0`):
      :func:`cost_bound_objective` of :func:`cost_flow_residual` (:math:`w^*` detached, :math:`\tau` detached),
      plus the same gradient penalty on :math:`\chi` (the official code penalises :math:`\chi` like :math:`\nu`).
    * ``loss_tau``: :func:`temperature_loss`, :math:`\tau = \mathrm{softplus}(\theta_\tau) + 10^{-6}`.
    * ``loss_lagrange``: :func:`lagrange_loss` with the upper bound
      :math:`\hat C_{ub} = E_D[\tilde p\, w^* c]` (:func:`worst_case_weights`); with :math:`\epsilon = 0` the plain
      estimate :math:`E_D[w^* c]`, and ``loss_chi`` / ``loss_tau`` are 0. :math:`\lambda =
      \mathrm{softplus}(\theta_\lambda) \ge 0` (OSRL's parametrisation; the official code clips
      :math:`e^{\theta}` to :math:`[0, 10^3]`).

    Each term reaches only its own parameters (:math:`\nu`, :math:`\chi`, :math:`\theta_\tau`,
    :math:`\theta_\lambda`). ``cost_limit`` is the *per-step* limit on :math:`E_d[c]`; convert an episode threshold
    with :func:`per_step_cost_limit` (not with OSRL's formula, which is :math:`1/(1-\gamma)` too large).

    Policy extraction is weighted BC with :math:`w^*` (the references' ``wsa`` mode): the weights are written,
    detached and normalised to batch mean 1 (in log space, :func:`coptidice_log_weight`), at
    ``(unlabeled, weight)`` for ``WeightedBCLoss(actor, role="unlabeled", weight="dice_weight")``, as the other
    DICE baselines do; the references use the raw :math:`w^*`, i.e. the same direction with a per-batch scale.

    Args:
        nu_network (TensorDictModule): :math:`\nu(s)`, reading its ``in_keys`` inside a role, writing a scalar.
        chi_network (TensorDictModule): :math:`\chi(s)`, the cost counterpart of :math:`\nu` (same input keys).

    Keyword Args:
        cost_limit (float): per-step limit :math:`\hat c \ge 0` on :math:`E_d[c]` (:func:`per_step_cost_limit`).
        alpha (float): weight :math:`\alpha > 0` of :math:`D_f(d \| d_D)`. Default 0.01 (Table J).
        gamma (float): discount in (0, 1). Default 0.99 (Table J).
        cost_ub_epsilon (float): radius :math:`\epsilon \ge 0` of the KL ball of the cost upper bound; 0 uses the
            plain estimate. Default 0.01 (both references).
        gradient_penalty (float): coefficient of the :math:`\nu` and :math:`\chi` gradient penalties. Default 1e-4
            (on standardised states; see CONTRIBUTING.md).
        init_lagrange (float): initial :math:`\lambda > 0`. Default 1 (the official code's :math:`e^0`).
        init_tau (float): initial :math:`\tau > 0`. Default 1.
        reduction (str): only ``"mean"``: the terms couple the batch (log-sum-exp, initial and data roles).

    Output keys: ``loss_nu``, ``loss_chi``, ``loss_tau``, ``loss_lagrange`` and detached diagnostics ``lagrange``,
    ``tau``, ``cost_limit``, ``cost_ub`` (the upper bound), ``cost_estimate`` (:math:`E_D[w^* c]`), ``kl``,
    ``weight_mean`` (raw :math:`E_D[w^*]`, 1 at the optimum), ``weight_max`` and ``effective_sample_size`` (of the
    normalised weights), ``f_divergence`` (:math:`E_D[f(w^*)]`), ``reward_mean``, ``nu_init`` and
    ``advantage_mean``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from spoil_torchrl.modules import make_value_network
        >>> from spoil_torchrl.objectives import per_step_cost_limit
        >>> loss = COptiDICELoss(make_value_network(3, hidden_cells=(16,)),
        ...                      make_value_network(3, hidden_cells=(16,), out_key="chi"),
        ...                      cost_limit=per_step_cost_limit(40.0, horizon=500, gamma=0.99))
        >>> n = 8
        >>> unlabeled = TensorDict({
        ...     "observation": torch.randn(n, 3),
        ...     "next": {"observation": torch.randn(n, 3), "reward": torch.rand(n, 1), "cost": torch.rand(n, 1),
        ...              "terminated": torch.zeros(n, 1, dtype=torch.bool)},
        ... }, [n])
        >>> batch = TensorDict({"unlabeled": unlabeled, "init": TensorDict({"observation": torch.randn(4, 3)}, [4])}, [])
        >>> out = loss(batch)
        >>> sum(v for k, v in out.items() if k.startswith("loss_")).backward()
        >>> round(batch["unlabeled", "dice_weight"].mean().item(), 4), bool(out["lagrange"] > 0)
        (1.0, True)
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable tensordict keys.

        Attributes:
            unlabeled (NestedKey): sub-tensordict of the data transitions. Defaults to ``"unlabeled"``.
            init (NestedKey): sub-tensordict of initial states. Defaults to ``"init"``.
            next (NestedKey): inside ``unlabeled``, where the next state's entries live. Defaults to ``"next"``.
            terminated (NestedKey): inside ``unlabeled``. Defaults to ``("next", "terminated")``.
            reward (NestedKey): inside ``unlabeled``, the true reward. Defaults to ``("next", "reward")``.
            cost (NestedKey): inside ``unlabeled``, the true cost. Defaults to ``("next", "cost")``.
            weight (NestedKey): inside ``unlabeled``, where the detached weights are written. Defaults to
                ``"dice_weight"``.
            advantage (NestedKey): inside ``unlabeled``, where the detached advantage (the exponent of the
                weights) is written, for diagnostics. Defaults to ``"dice_advantage"``.
        """

        unlabeled: NestedKey = "unlabeled"
        init: NestedKey = "init"
        next: NestedKey = "next"
        terminated: NestedKey = ("next", "terminated")
        reward: NestedKey = ("next", "reward")
        cost: NestedKey = ("next", "cost")
        weight: NestedKey = "dice_weight"
        advantage: NestedKey = "dice_advantage"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys
    out_keys = [
        "loss_nu",
        "loss_chi",
        "loss_tau",
        "loss_lagrange",
        "lagrange",
        "tau",
        "cost_limit",
        "cost_ub",
        "cost_estimate",
        "kl",
        "weight_mean",
        "weight_max",
        "effective_sample_size",
        "f_divergence",
        "reward_mean",
        "nu_init",
        "advantage_mean",
    ]

    nu_network: TensorDictModule
    nu_network_params: TensorDictParams
    target_nu_network_params: TensorDictParams
    chi_network: TensorDictModule
    chi_network_params: TensorDictParams
    target_chi_network_params: TensorDictParams

    def __init__(
        self,
        nu_network: TensorDictModule,
        chi_network: TensorDictModule,
        *,
        cost_limit: float,
        alpha: float = 0.01,
        gamma: float = 0.99,
        cost_ub_epsilon: float = 0.01,
        gradient_penalty: float = 1e-4,
        init_lagrange: float = 1.0,
        init_tau: float = 1.0,
        reduction: str | None = None,
    ) -> None:
        super().__init__()
        self._setup_dual(nu_network, gamma=gamma, gradient_penalty=gradient_penalty, reduction=reduction)
        if not alpha > 0.0:  # also rejects NaN
            raise ValueError(f"alpha must be > 0, got {alpha}")
        if not (cost_limit >= 0.0 and math.isfinite(cost_limit)):
            raise ValueError(f"cost_limit must be a finite number >= 0, got {cost_limit}")
        if not cost_ub_epsilon >= 0.0:
            raise ValueError(f"cost_ub_epsilon must be >= 0, got {cost_ub_epsilon}")
        for name, value in (("init_lagrange", init_lagrange), ("init_tau", init_tau)):
            if not (value > 0.0 and math.isfinite(value)):
                raise ValueError(f"{name} must be a positive number, got {value}")
        if list(chi_network.in_keys) != list(nu_network.in_keys):
            raise ValueError(
                f"chi reads {chi_network.in_keys} but nu reads {nu_network.in_keys}: use the same"
            )
        self.convert_to_functional(chi_network, "chi_network")
        self.lagrange_param = nn.Parameter(torch.tensor(_inverse_softplus(float(init_lagrange))))
        self.tau_param = nn.Parameter(torch.tensor(_inverse_softplus(float(init_tau))))
        self.cost_limit = float(cost_limit)
        self.alpha = float(alpha)
        self.cost_ub_epsilon = float(cost_ub_epsilon)
        if self.cost_ub_epsilon > 0:  # chi is trained and penalised after nu
            self.penalised = ("points", "chi_points")
            self.penalised_networks = ("nu_network", "chi_network")

    @property
    def lagrange(self) -> torch.Tensor:
        """:math:`\\lambda = \\mathrm{softplus}(\\theta_\\lambda) \\ge 0` (differentiable in ``lagrange_param``)."""
        return lagrange_of(self.lagrange_param)

    @property
    def tau(self) -> torch.Tensor:
        """:math:`\\tau = \\mathrm{softplus}(\\theta_\\tau) + 10^{-6}` (differentiable in ``tau_param``)."""
        return tau_of(self.tau_param)

    functional_params = ("nu_network_params", "chi_network_params")

    @property
    def dual_role(self) -> NestedKey:
        return self.tensor_keys.unlabeled

    @property
    def in_keys(self) -> list[NestedKey]:
        return self._role_in_keys(self.tensor_keys.unlabeled, self.tensor_keys.reward, self.tensor_keys.cost)

    def term_parameters(self) -> dict[str, nn.Parameter]:
        chi = self.state_network("chi_network").parameters(self.chi_network_params)
        return {
            **super().term_parameters(),
            **{f"chi.{k}": v for k, v in chi.items()},
            "lagrange_param": self.lagrange_param,
            "tau_param": self.tau_param,
        }

    def check_compilable(self) -> None:
        super().check_compilable()
        self.state_network("chi_network").check_compilable()

    def losses(
        self,
        nu_values: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
        nu_penalty: torch.Tensor | None,
        chi_values: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None,
        chi_penalty: torch.Tensor | None,
        reward: torch.Tensor,
        cost: torch.Tensor,
        terminated: torch.Tensor,
        lagrange: torch.Tensor,
        tau: torch.Tensor,
    ) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor]:
        """The four losses and the diagnostics (the output keys), the advantage and the self-normalised weights
        of the policy extraction, from nu's (and chi's) values
        at the initial, current and next states and their weighted gradient penalties (``None``: off; chi's
        values ``None`` when ``cost_ub_epsilon`` is 0). :meth:`terms` calls it."""
        init_nu, nu, next_nu = nu_values
        advantage = dice_advantage(
            reward - lagrange.detach() * cost, nu, bellman_backup(next_nu, terminated, self.gamma)
        )
        weight = coptidice_weight(advantage, self.alpha)
        loss_nu = coptidice_dual(init_nu, advantage, weight, self.alpha, self.gamma)
        if nu_penalty is not None:
            loss_nu = loss_nu + nu_penalty

        w = weight.detach()
        cost_estimate = (w * cost).mean()
        if chi_values is not None:
            init_chi, chi, next_chi = chi_values
            residual = cost_flow_residual(
                init_chi, w, cost, chi, bellman_backup(next_chi, terminated, self.gamma), self.gamma
            )
            loss_chi = cost_bound_objective(residual, tau.detach())
            if chi_penalty is not None:
                loss_chi = loss_chi + chi_penalty
            tilt, kl = worst_case_weights(residual.detach(), tau.detach())
            cost_ub = (tilt * w * cost).mean()
            loss_tau = temperature_loss(tau, kl, self.cost_ub_epsilon)
        else:
            zero = torch.zeros((), dtype=nu.dtype, device=nu.device)
            loss_chi, loss_tau, kl, cost_ub = zero, zero.clone(), zero.clone(), cost_estimate
        loss_lagrange = lagrange_loss(lagrange, cost_ub, self.cost_limit)

        with torch.no_grad():
            normalized = self_normalized_weights(coptidice_log_weight(advantage.detach(), self.alpha))
            outputs = {
                "loss_nu": loss_nu,
                "loss_chi": loss_chi,
                "loss_tau": loss_tau,
                "loss_lagrange": loss_lagrange,
                "lagrange": lagrange.detach(),
                "tau": tau.detach(),
                "cost_limit": torch.tensor(self.cost_limit, dtype=nu.dtype, device=nu.device),
                "cost_ub": cost_ub.detach(),
                "cost_estimate": cost_estimate,
                "kl": kl.detach(),
                "weight_mean": w.mean(),
                "weight_max": normalized.max(),
                "effective_sample_size": effective_sample_size(normalized),
                "f_divergence": soft_chi2(w).mean(),
                "reward_mean": reward.mean(),
                "nu_init": init_nu.detach().mean(),
                "advantage_mean": advantage.detach().mean(),
            }
        return outputs, advantage, normalized

    def inputs(self, tensordict: TensorDictBase, produced: frozenset = frozenset()) -> Tensors:
        """The dual's inputs (:meth:`DICELoss.inputs`; the penalty points drawn for nu, then for chi) and the
        true reward and cost of the unlabeled transitions."""
        keys = self.tensor_keys
        out = super().inputs(tensordict)
        data = get_role(tensordict, self.dual_role)
        n = data.batch_size.numel()
        reward = role_entry(data, self.dual_role, keys.reward, DATA_WRITER)
        cost = role_entry(data, self.dual_role, keys.cost, DATA_WRITER)
        return out | {"reward": reward.reshape(n), "cost": cost.reshape(n)}

    def terms(self, params: Tensors, x: Tensors, produced: dict) -> tuple[torch.Tensor, Tensors]:
        """The four losses and the diagnostics (:meth:`losses`); the self-normalised weights and the advantage
        go into ``produced``."""
        init_nu, nu, next_nu, nu_penalty = self.nu_terms(params, x)
        on = self.gradient_penalty > 0
        chi_values, chi_penalty = None, None
        if self.cost_ub_epsilon > 0:
            chi_params = {k.removeprefix("chi."): v for k, v in params.items() if k.startswith("chi.")}
            *chi_values, chi_penalty = state_terms(
                self.state_network("chi_network"),
                chi_params,
                x,
                x.get("chi_points"),
                self.gradient_penalty,
                self.penalty_layers("chi_network"),
            )
            chi_penalty = chi_penalty if on else None
        dtype = nu.dtype
        outputs, advantage, weights = self.losses(
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
        self._produce(produced, weights, advantage)
        total = sum(value for key, value in outputs.items() if key.startswith("loss_"))
        return total, outputs
