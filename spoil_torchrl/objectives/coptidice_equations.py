"""COptiDICE's equations (Lee et al., 2022) as functions of plain tensors: the per-step cost limit, the soft
chi-square f-divergence and its closed-form weights, the dual of nu, and the cost upper bound (the flow residual
of chi, its temperature tau and worst-case weights), with the losses of lambda and tau.
:class:`~spoil_torchrl.objectives.coptidice.COptiDICELoss` composes them."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from spoil_torchrl.objectives.functional import log_mean_exp, self_normalized_weights

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
