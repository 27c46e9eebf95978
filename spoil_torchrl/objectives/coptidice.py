"""COptiDICE (Lee et al., 2022): offline constrained RL by stationary distribution correction estimation, the
baseline COptiDICE of section 5 (with the dataset's true reward and cost)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from tensordict import TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import nn

from spoil_torchrl.objectives.dice import DICELoss, state_terms
from spoil_torchrl.objectives.functional import (
    bellman_backup,
    dice_advantage,
    effective_sample_size,
    log_mean_exp,
    self_normalized_weights,
)
from spoil_torchrl.objectives.keys import get_role
from spoil_torchrl.objectives.pure import Tensors

#: Smallest temperature of the cost upper bound (the official code's ``exp(tau) + 1e-6``).
TAU_MIN = 1e-6


def per_step_cost_limit(episode_limit: float, horizon: int, gamma: float) -> float:
    """The per-step limit :math:`\\hat c` on :math:`E_d[c]` that matches an episode-cost threshold :math:`L` over
    a horizon :math:`T`: :math:`\\hat c = (1-\\gamma^T)\\, L / T`.

    COptiDICE constrains :math:`E_d[c] = \\sum_{s,a} d(s,a) c(s,a)` with :math:`d` the *normalised* discounted
    occupancy :math:`(1-\\gamma)\\sum_t \\gamma^t \\Pr(s_t, a_t)` (it sums to 1: that is the
    :math:`(1-\\gamma) E_{\\rho_0}[\\nu]` term of the dual). A policy that spends its budget :math:`L` evenly over the
    :math:`T` steps of an episode, :math:`L/T` per step, then has
    :math:`E_d[c] = (1-\\gamma)\\sum_{t<T}\\gamma^t L/T = (1-\\gamma^T) L/T`.

    OSRL converts with :math:`L (1-\\gamma^T) / ((1-\\gamma) T)`, the *unnormalised* discounted sum
    :math:`\\sum_{t<T}\\gamma^t L/T`, which is :math:`1/(1-\\gamma)` (100 at :math:`\\gamma = 0.99`) times too large
    for the normalised estimate it is compared with, so its constraint hardly binds (OSRL issue #28). Viewing
    the episode as continuing past :math:`T` (a time limit bootstraps, as everywhere in this library) gives
    :math:`L/T` instead; the two differ by the factor :math:`1-\\gamma^T` (0.993 for :math:`T = 500`,
    :math:`\\gamma = 0.99`) and we take the :math:`T`-step value, which is never looser.

    Examples:
        >>> round(per_step_cost_limit(40.0, 500, 0.99), 6)  # PointCircle1: threshold 40 over 500 steps
        0.079474
        >>> per_step_cost_limit(0.0, 500, 0.99)
        0.0
    """
    if not (episode_limit >= 0 and math.isfinite(episode_limit)):
        raise ValueError(f"episode_limit must be a finite number >= 0, got {episode_limit}")
    if int(horizon) != horizon or horizon < 1:
        raise ValueError(f"horizon must be a positive integer, got {horizon}")
    if not 0.0 < gamma < 1.0:
        raise ValueError(f"gamma must lie in (0, 1), got {gamma}")
    return float(episode_limit) * (1.0 - float(gamma) ** int(horizon)) / int(horizon)


def soft_chi2(x: torch.Tensor) -> torch.Tensor:
    """The soft-:math:`\\chi^2` generator of COptiDICE's f-divergence: :math:`f(x) = x \\log x - x + 1` for
    :math:`x < 1`, :math:`\\tfrac12 (x-1)^2` for :math:`x \\ge 1` (the log's argument is floored at
    :math:`10^{-10}` as in the references, so :math:`f(0) = 1` with a finite gradient).

    Examples:
        >>> [round(v, 4) for v in soft_chi2(torch.tensor([0.0, 1.0, 3.0])).tolist()]
        [1.0, 0.0, 2.0]
    """
    return torch.where(x < 1, x * (torch.log(x + 1e-10) - 1) + 1, 0.5 * (x - 1) ** 2)


def coptidice_weight(advantage: torch.Tensor, alpha: float) -> torch.Tensor:
    """The closed-form correction :math:`w^* = \\max(0, (f')^{-1}(e_{\\nu,\\lambda}/\\alpha))` (Lee et al., 2022,
    Proposition 1; the lemma quoted in the paper's appendix C) for soft-:math:`\\chi^2`:
    :math:`(f')^{-1}(y) = e^y` for :math:`y < 0` and :math:`y + 1` otherwise (always positive).

    It maximises :math:`w e - \\alpha f(w)` over :math:`w \\ge 0` for each sample.

    Examples:
        >>> [round(v, 4) for v in coptidice_weight(torch.tensor([-0.01, 0.0, 0.02]), alpha=0.01).tolist()]
        [0.3679, 1.0, 3.0]
    """
    y = advantage / alpha
    return F.relu(torch.where(y < 0, torch.exp(y.clamp(max=0.0)), y + 1))


def coptidice_log_weight(advantage: torch.Tensor, alpha: float) -> torch.Tensor:
    """:math:`\\log w^*` of :func:`coptidice_weight`: :math:`y` for :math:`y < 0`, :math:`\\log(1+y)` otherwise
    (:math:`y = e/\\alpha`); finite where :math:`w^*` underflows, so the weights can be normalised in log space.

    Examples:
        >>> torch.allclose(coptidice_log_weight(torch.tensor([-0.5, 0.3]), 0.1).exp(),
        ...                coptidice_weight(torch.tensor([-0.5, 0.3]), 0.1))
        True
    """
    y = advantage / alpha
    return torch.where(y < 0, y, torch.log1p(y.clamp(min=0.0)))


def coptidice_dual(
    init_nu: torch.Tensor, advantage: torch.Tensor, weight: torch.Tensor, alpha: float, gamma: float
) -> torch.Tensor:
    """COptiDICE's :math:`\\nu` objective at the closed-form :math:`w^*` (Lee et al., 2022):
    :math:`(1-\\gamma) E_{\\rho_0}[\\nu(s_0)] + E_D[w^* e_{\\nu,\\lambda} - \\alpha f(w^*)]`, with
    :math:`e_{\\nu,\\lambda} = r - \\lambda c + \\gamma \\nu(s')(1-d) - \\nu(s)` and :math:`f` :func:`soft_chi2`.

    Examples:
        >>> round(coptidice_dual(torch.ones(2), torch.zeros(3), torch.ones(3), alpha=0.01, gamma=0.9).item(), 6)
        0.1
    """
    return (1.0 - gamma) * init_nu.mean() + (weight * advantage - alpha * soft_chi2(weight)).mean()


def cost_flow_residual(
    init_chi: torch.Tensor,
    weight: torch.Tensor,
    cost: torch.Tensor,
    chi: torch.Tensor,
    backup: torch.Tensor,
    gamma: float,
) -> torch.Tensor:
    """COptiDICE's per-sample cost term :math:`\\ell_\\chi = (1-\\gamma) E_{\\rho_0}[\\chi(s_0)] + w(s,a)\\,(c(s,a) +
    \\gamma \\chi(s')(1-d) - \\chi(s))` (``backup`` is :math:`\\gamma\\chi(s')(1-d)`; :math:`w` detached).

    Its mean over :math:`D` is the cost of :math:`d = w\\,d_D` corrected by a cost "value" :math:`\\chi`. The
    official code pairs each transition with one initial state; here the batch mean of
    :math:`\\chi(s_0)` stands in for it (the two roles have their own batch sizes), so the worst-case reweighting
    of :func:`worst_case_weights` acts on the transitions only.

    Examples:
        >>> cost_flow_residual(torch.zeros(2), torch.tensor([2.0]), torch.tensor([1.0]), torch.tensor([0.5]),
        ...                    torch.tensor([0.25]), gamma=0.5).item()  # 2 * (1 + 0.25 - 0.5)
        1.5
    """
    return (1.0 - gamma) * init_chi.mean() + weight * (cost + backup - chi)


def cost_bound_objective(residual: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
    """:math:`\\chi`'s objective, the KL-robust cost bound at a fixed temperature :math:`\\tau`:
    :math:`\\tau \\log E_D[\\exp(\\ell_\\chi/\\tau)]`, minimised over :math:`\\chi` (Lee et al., 2022:
    :math:`\\max_{\\tilde p:\\, KL(\\tilde p \\| p_D) \\le \\epsilon} E_{\\tilde p}[\\ell_\\chi]
    = \\min_{\\tau \\ge 0} \\tau\\epsilon + \\tau \\log E_D[e^{\\ell_\\chi/\\tau}]`).

    Its gradient in :math:`\\chi` is :math:`E_{\\tilde p}[\\nabla \\ell_\\chi]` with :math:`\\tilde p` the worst-case
    weights (:func:`worst_case_weights`). The references minimise :math:`E_D[\\tilde p\\, \\ell_\\chi]` and
    differentiate through :math:`\\tilde p` as well, which adds a covariance term that is not the bound's.

    Examples:
        >>> round(cost_bound_objective(torch.tensor([0.0, 0.0]), torch.tensor(0.5)).item(), 6)
        0.0
    """
    return tau * log_mean_exp(residual / tau)


def worst_case_weights(residual: torch.Tensor, tau: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The worst-case reweighting :math:`\\tilde p \\propto \\exp(\\ell_\\chi/\\tau)` of the transitions (batch mean
    1) and :math:`KL(\\tilde p \\| p_D) = E_D[\\tilde p \\log \\tilde p]` (Lee et al., 2022, the cost upper bound).

    Examples:
        >>> p, kl = worst_case_weights(torch.tensor([0.0, 0.0, 0.0, 0.0]), torch.tensor(1.0))
        >>> p.tolist(), kl.item()
        ([1.0, 1.0, 1.0, 1.0], 0.0)
    """
    weights = self_normalized_weights(residual / tau)
    return weights, torch.xlogy(weights, weights).mean()


def lagrange_loss(lagrange: torch.Tensor, cost_estimate: torch.Tensor, cost_limit: float) -> torch.Tensor:
    """:math:`\\lambda (\\hat c - \\hat C_{ub})` (estimate detached): gradient descent raises :math:`\\lambda` while
    the cost upper bound exceeds the limit and lowers it otherwise.

    Examples:
        >>> lam = torch.tensor(1.0, requires_grad=True)
        >>> lagrange_loss(lam, torch.tensor(0.3), cost_limit=0.1).backward()
        >>> round(lam.grad.item(), 4)  # negative: a descent step increases lambda
        -0.2
    """
    return lagrange * (cost_limit - cost_estimate.detach())


def temperature_loss(tau: torch.Tensor, kl: torch.Tensor, epsilon: float) -> torch.Tensor:
    """:math:`\\tau (\\epsilon - KL(\\tilde p \\| p_D))` (KL detached): the :math:`\\tau`-gradient of the bound
    :math:`\\tau\\epsilon + \\tau \\log E_D[e^{\\ell/\\tau}]`, which is :math:`\\epsilon - KL`: :math:`\\tau` shrinks
    (the reweighting sharpens) while :math:`KL < \\epsilon` and grows while :math:`KL > \\epsilon`, so the worst
    case settles on the KL ball's boundary.

    Examples:
        >>> round(temperature_loss(torch.tensor(2.0), torch.tensor(0.03), epsilon=0.01).item(), 6)
        -0.04
    """
    return tau * (epsilon - kl.detach())


def lagrange_of(param: torch.Tensor) -> torch.Tensor:
    """COptiDICE's cost multiplier :math:`\\lambda = \\mathrm{softplus}(\\theta_\\lambda) \\ge 0`.

    Examples:
        >>> round(lagrange_of(torch.tensor(0.0)).item(), 4)
        0.6931
    """
    return F.softplus(param)


def tau_of(param: torch.Tensor) -> torch.Tensor:
    """COptiDICE's temperature :math:`\\tau = \\mathrm{softplus}(\\theta_\\tau) + 10^{-6} > 0`.

    Examples:
        >>> round(tau_of(torch.tensor(0.0)).item(), 4)
        0.6931
    """
    return F.softplus(param) + TAU_MIN


def _inverse_softplus(x: float) -> float:
    return x + math.log(-math.expm1(-x))


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
        return out | {"reward": data.get(keys.reward).reshape(n), "cost": data.get(keys.cost).reshape(n)}

    def terms(self, params: Tensors, x: Tensors, produced: dict) -> tuple[torch.Tensor, Tensors]:
        """The four losses and the diagnostics (:meth:`losses`); the self-normalised weights and the advantage
        go into ``produced``."""
        init_nu, nu, next_nu, nu_penalty = self.nu_terms(params, x)
        on = self.gradient_penalty > 0
        chi_values, chi_penalty = None, None
        if self.cost_ub_epsilon > 0:
            chi_params = {k.removeprefix("chi."): v for k, v in params.items() if k.startswith("chi.")}
            *chi_values, chi_penalty = state_terms(
                self.state_network("chi_network"), chi_params, x, x.get("chi_points"), self.gradient_penalty
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
