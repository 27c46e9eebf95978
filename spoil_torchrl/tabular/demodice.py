"""Exact distribution-level DemoDICE (Table B row "DemoDICE") on a finite CMDP.

Solves

.. math::
    \\min_d D_{KL}(d \\| d_P) + \\alpha D_{KL}(d \\| d_S) \\quad \\text{s.t.} \\quad d \\text{ satisfies Bellman flow},

the objective of DemoDICE (Kim et al., 2022) with the safe demonstrations as its regulariser (section 5's
DemoDICE-S). For :math:`\\alpha > 0` the two KL terms combine into one:

.. math::
    D_{KL}(d \\| d_P) + \\alpha D_{KL}(d \\| d_S) = (1+\\alpha) D_{KL}(d \\| m) - (1+\\alpha) \\log Z,
    \\qquad m = d_P^{1/(1+\\alpha)}\\, d_S^{\\alpha/(1+\\alpha)} / Z,

so the solution is the KL projection of the normalised geometric mixture :math:`m` onto the occupancies
(:func:`~spoil_torchrl.tabular.solve_kl_projection`). Any ``d`` with mass where :math:`d_P = 0` or
:math:`d_S = 0` has infinite objective, so **for every** :math:`\\alpha > 0` **the solution lives on**
:math:`supp(d_P) \\cap supp(d_S)`. As :math:`\\alpha \\to 0` it therefore tends to the KL projection of
:math:`d_P` onto that intersection, which is BC (``d = d_P``) only when :math:`supp(d_P) \\subseteq
supp(d_S)`, e.g. when ``d_S`` has full support and ``d_P`` is an occupancy; at :math:`\\alpha = 0` exactly the
problem is the projection of ``d_P`` with no support restriction. As :math:`\\alpha \\to \\infty`, :math:`m`
tends to ``d_S`` restricted to :math:`supp(d_P)` and renormalised.
"""

from __future__ import annotations

import numpy as np

from spoil_torchrl.tabular.cmdp import TabularCMDP, check_distribution
from spoil_torchrl.tabular.spoildice import solve_kl_projection


def geometric_mixture(d_P, d_S, alpha: float) -> np.ndarray:
    """:math:`m \\propto d_P^{1/(1+\\alpha)} d_S^{\\alpha/(1+\\alpha)}`, normalised; computed in log space so that
    tiny probabilities do not underflow. Zero wherever either distribution is zero (for ``alpha > 0``).

    Examples:
        >>> geometric_mixture(np.array([[0.5, 0.5, 0.0]]), np.array([[0.8, 0.2, 0.0]]), 1.0).round(4).tolist()
        [[0.6667, 0.3333, 0.0]]
    """
    if not np.isfinite(alpha) or alpha < 0:
        raise ValueError(f"alpha must be a finite number >= 0, got {alpha}")
    d_P, d_S = np.asarray(d_P, dtype=np.float64), np.asarray(d_S, dtype=np.float64)
    if alpha == 0:
        return d_P / d_P.sum()
    with np.errstate(divide="ignore"):
        log_m = (np.log(d_P) + alpha * np.log(d_S)) / (1.0 + alpha)
    finite = np.isfinite(log_m)
    if not finite.any():
        raise ValueError("d_P and d_S have disjoint supports: their geometric mixture is empty")
    log_m = np.where(finite, log_m - log_m[finite].max(), -np.inf)
    m = np.exp(log_m)
    return m / m.sum()


def demodice_objective(d, d_P, d_S, alpha: float) -> float:
    """:math:`D_{KL}(d \\| d_P) + \\alpha D_{KL}(d \\| d_S)` (``inf`` where ``d`` leaves a support).

    Examples:
        >>> demodice_objective(np.array([[0.5, 0.5]]), np.array([[0.5, 0.5]]), np.array([[1.0, 0.0]]), 0.0)
        0.0
    """
    d, d_P, d_S = (np.asarray(x, dtype=np.float64) for x in (d, d_P, d_S))
    mass = d > 0
    with np.errstate(divide="ignore"):
        kl_p = float((d[mass] * (np.log(d[mass]) - np.log(d_P[mass]))).sum())
        kl_s = float((d[mass] * (np.log(d[mass]) - np.log(d_S[mass]))).sum()) if alpha > 0 else 0.0
    return kl_p + alpha * kl_s


def solve_demodice(mdp: TabularCMDP, d_P, d_S, alpha: float, *, max_iter: int = 500) -> np.ndarray:
    """Exact DemoDICE occupancy (Table B row "DemoDICE"): :math:`\\arg\\min_d D_{KL}(d \\| d_P) + \\alpha
    D_{KL}(d \\| d_S)` over the occupancies of ``mdp``.

    Args:
        mdp: the CMDP (its reward and cost are not used).
        d_P: ``[S, A]`` performant distribution.
        d_S: ``[S, A]`` safe distribution, DemoDICE's regulariser.
        alpha: regularisation weight (appendix E.2: ``[1e-2, 1e2]``); for ``alpha > 0`` the solution lives on
            ``supp(d_P) ∩ supp(d_S)`` (module docstring).

    Returns:
        ``d`` ``[S, A]`` satisfying the flow constraint to 1e-9.

    Raises:
        InfeasibleProblemError: no occupancy lives on ``supp(d_P) ∩ supp(d_S)`` (or on ``supp(d_P)`` for
            ``alpha = 0``).

    Examples:
        >>> # one state, so the flow constraint only asks for sum 1 and d is the mixture m itself
        >>> mdp = TabularCMDP(np.ones((1, 2, 1)), np.zeros((1, 2)), np.zeros((1, 2)), [1.0], 0.9)
        >>> solve_demodice(mdp, [[0.5, 0.5]], [[0.8, 0.2]], alpha=1.0).round(4).tolist()
        [[0.6667, 0.3333]]
    """
    d_P = check_distribution(mdp, d_P, "d_P")
    d_S = check_distribution(mdp, d_S, "d_S")
    m = geometric_mixture(d_P, d_S, alpha)
    return solve_kl_projection(mdp, m, np.ones_like(m, dtype=bool), max_iter=max_iter)
