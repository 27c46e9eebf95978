"""Exact distribution-level SpoilDICE (Eq. 4 / Table B) on a finite CMDP.

Solves

.. math::
    \\min_d D_{KL}(d \\| d_P) \\quad \\text{s.t.} \\quad d \\text{ satisfies Bellman flow}, \\;
    d(s,a) = 0 \\text{ where } d_S(s,a) \\le \\text{threshold}.

Method: the support constraint is applied by removing the excluded pairs from the variables (and the pairs
where :math:`d_P = 0`, on which the KL is infinite). Pairs that lead with positive probability into a state
left without any admissible action are removed too, repeatedly, since mass there would break the flow; and
states that no admissible path reaches from :math:`\\rho_0` are dropped. If :math:`\\rho_0` then puts mass on a
state with no admissible action, no occupancy exists (the feasibility assumption Eq. 14 fails) and
:class:`~spoil_torchrl.tabular.InfeasibleProblemError` is raised. On what remains a strictly positive feasible
occupancy exists, so the convex dual

.. math::
    \\min_\\nu (1-\\gamma)\\rho_0^\\top\\nu + \\sum_{(s,a)} d_P(s,a) \\exp\\big(\\gamma (T\\nu)(s,a) - \\nu(s) - 1\\big)

is attained; it is minimised by damped Newton steps, and :math:`d = d_P \\exp(\\gamma T\\nu - \\nu - 1)`. The
dual gradient is minus the flow residual, so convergence is checked on the residual itself.
"""

from __future__ import annotations

import numpy as np

from spoil_torchrl.tabular.cmdp import (
    InfeasibleProblemError,
    TabularCMDP,
    check_distribution,
    flow_residual,
)

#: Largest flow-constraint violation accepted from the solver.
FLOW_TOL = 1e-9


def admissible_pairs(mdp: TabularCMDP, allowed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Prune ``allowed`` ``[S, A]`` to the pairs a flow-feasible occupancy can use, and the states it reaches.

    Returns ``(pairs, states)``: boolean masks of the admissible pairs and of the states reachable from
    :math:`\\rho_0` through them. Raises :class:`InfeasibleProblemError` when :math:`\\rho_0` has mass on a
    state without any admissible action.

    Examples:
        >>> mdp = TabularCMDP([[[1.0, 0.0], [0.0, 1.0]], [[0.0, 1.0], [0.0, 1.0]]],
        ...                   np.zeros((2, 2)), np.zeros((2, 2)), [1.0, 0.0], 0.9)
        >>> pairs, states = admissible_pairs(mdp, np.array([[True, True], [False, False]]))
        >>> pairs.tolist(), states.tolist()  # action 1 of state 0 leads to the dead state 1
        ([[True, False], [False, False]], [True, False])
    """
    pairs = allowed.copy()
    leads_to = mdp.transition > 0
    while True:
        dead = ~pairs.any(axis=1)
        into_dead = (leads_to & dead[None, None, :]).any(axis=2)
        pruned = pairs & ~into_dead
        if (pruned == pairs).all():
            break
        pairs = pruned
    dead = ~pairs.any(axis=1)
    if (mdp.init[dead] > 0).any():
        bad = np.flatnonzero(dead & (mdp.init > 0)).tolist()
        raise InfeasibleProblemError(
            f"no occupancy satisfies the support constraint: initial states {bad} have no admissible action "
            "(every action is off the support or leads, with positive probability, into states that have none). "
            "The feasibility assumption of Eq. (14) does not hold for this support."
        )
    states = mdp.init > 0
    while True:
        step = (leads_to & pairs[:, :, None] & states[:, None, None]).any(axis=(0, 1))
        grown = states | step
        if (grown == states).all():
            break
        states = grown
    return pairs & states[:, None], states


def _kl_flow_dual(mdp: TabularCMDP, d_ref: np.ndarray, pairs: np.ndarray, states: np.ndarray, max_iter: int):
    """Minimise the dual of ``min KL(d || d_ref)`` s.t. flow, over the admissible ``pairs`` (see module doc)."""
    idx_s = np.flatnonzero(states)
    pos = {s: i for i, s in enumerate(idx_s)}
    rows = np.argwhere(pairs)  # (k, 2): admissible (s, a)
    log_ref = np.log(d_ref[rows[:, 0], rows[:, 1]])
    # e = B nu over the reachable states: B[(s,a), s'] = gamma T(s'|s,a) - 1[s == s'].
    b = mdp.gamma * mdp.transition[rows[:, 0], rows[:, 1]][:, idx_s]
    b[np.arange(len(rows)), [pos[s] for s in rows[:, 0]]] -= 1.0
    c = (1.0 - mdp.gamma) * mdp.init[idx_s]

    def objective(nu):
        log_d = log_ref + b @ nu - 1.0
        with np.errstate(over="ignore"):  # an overshooting trial step is rejected by the line search
            return c @ nu + np.exp(log_d).sum(), log_d

    nu = np.zeros(len(idx_s))
    value, log_d = objective(nu)
    for _ in range(max_iter):
        d = np.exp(log_d)
        grad = c + b.T @ d  # = -(flow residual)
        if np.abs(grad).max() < FLOW_TOL * 1e-2:
            break
        hess = (b.T * d) @ b + 1e-14 * np.eye(len(idx_s))
        step = -np.linalg.solve(hess, grad)
        t = 1.0
        # Near the optimum the predicted decrease falls below the objective's round-off; without this slack
        # the Armijo test then rejects every step and Newton stalls a few digits short of FLOW_TOL.
        slack = 1e-12 * (abs(value) + 1.0)
        while True:
            new_value, new_log_d = objective(nu + t * step)
            if new_value <= value + 1e-4 * t * (grad @ step) + slack or t < 1e-12:
                break
            t *= 0.5
        nu, value, log_d = nu + t * step, new_value, new_log_d
    d_full = np.zeros((mdp.n_states, mdp.n_actions))
    d_full[rows[:, 0], rows[:, 1]] = np.exp(log_d)
    return d_full


def solve_kl_projection(mdp: TabularCMDP, d_ref, allowed: np.ndarray, *, max_iter: int = 500) -> np.ndarray:
    """The occupancy closest to ``d_ref`` in KL, :math:`\\arg\\min_d D_{KL}(d \\| d_{ref})`, using only ``allowed`` pairs.

    The workhorse of :func:`solve_spoildice` (and of DemoDICE's exact solution, whose objective is a KL to a
    geometric mixture). Raises :class:`InfeasibleProblemError` when no flow-feasible occupancy lives on
    ``allowed`` and ``RuntimeError`` if Newton's method fails to reach :data:`FLOW_TOL`.
    """
    d_ref = check_distribution(mdp, d_ref, "d_ref")
    allowed = np.asarray(allowed, dtype=bool) & (d_ref > 0)
    pairs, states = admissible_pairs(mdp, allowed)
    d = _kl_flow_dual(mdp, d_ref, pairs, states, max_iter)
    residual = np.abs(flow_residual(mdp, d)).max()
    if residual > FLOW_TOL:
        raise RuntimeError(f"the dual Newton solve did not converge (flow residual {residual:.3e})")
    return d


def solve_spoildice(mdp: TabularCMDP, d_P, d_S, threshold: float = 0.0) -> np.ndarray:
    """Exact SpoilDICE occupancy (Eq. 4; Table B row "SpoilDICE"): the occupancy closest to ``d_P`` in KL
    among those supported on :math:`\\{(s,a): d_S(s,a) > \\text{threshold}\\}`; with several constraints (a
    sequence of safe distributions, one per constraint), among those supported on the intersection of their
    supports (``docs/several_constraints.md``).

    Args:
        mdp: the CMDP (its reward and cost are not used).
        d_P: ``[S, A]`` performant distribution.
        d_S: ``[S, A]`` safe distribution whose support defines the constraint, or ``K`` of them (a sequence, or
            an array ``[K, S, A]``), one per constraint.
        threshold: pairs with ``d_S <= threshold`` are outside the support (appendix E.2 sweeps 1e-10 .. 1e-4).

    Returns:
        ``d`` ``[S, A]``: satisfies the flow constraint to :data:`FLOW_TOL` and is exactly 0 off the support
        (off any of the supports).

    Raises:
        InfeasibleProblemError: no occupancy lives on ``supp(d_P)`` and every support (Eq. 14 violated); with
            several constraints, the message gives the pairs inside each support and inside all of them.

    Examples:
        >>> mdp = TabularCMDP(np.full((2, 2, 2), 0.5), [[1.0, 0.0], [0.0, 0.0]], np.zeros((2, 2)),
        ...                   [0.5, 0.5], 0.9)
        >>> d_P = np.full((2, 2), 0.25)
        >>> d_S = np.array([[0.5, 0.0], [0.25, 0.25]])  # action 1 is never safe in state 0
        >>> d = solve_spoildice(mdp, d_P, d_S)
        >>> float(d[0, 1]), round(float(d.sum()), 9)
        (0.0, 1.0)
        >>> other = np.array([[0.25, 0.25], [0.5, 0.0]])  # a second constraint: action 1 never in state 1
        >>> d = solve_spoildice(mdp, d_P, [d_S, other])
        >>> float(d[0, 1]), float(d[1, 1]), round(float(d.sum()), 9)
        (0.0, 0.0, 1.0)
    """
    if threshold < 0:
        raise ValueError(f"threshold must be >= 0, got {threshold}")
    several = np.ndim(d_S) == 3  # one safe distribution per constraint
    safe = [
        check_distribution(mdp, d, f"d_S[{k}]" if several else "d_S")
        for k, d in enumerate(d_S if several else [d_S])
    ]
    if not safe:
        raise ValueError("d_S: no safe distribution (give one per constraint)")
    supports = [d > threshold for d in safe]
    allowed = np.logical_and.reduce(supports)
    if several and not allowed.any():
        sizes = ", ".join(f"constraint {k}: {int(m.sum())}" for k, m in enumerate(supports))
        raise InfeasibleProblemError(
            f"the {len(supports)} supports share no state-action pair (pairs inside each: {sizes}); no policy "
            "can respect every constraint"
        )
    return solve_kl_projection(mdp, d_P, allowed)


def solve_spoildice_lagrangian(
    mdp: TabularCMDP, d_P, d_S, threshold: float = 0.0, *, lagrange: float
) -> np.ndarray:
    """SpoilDICE at a *fixed* support multiplier :math:`\\lambda` (Eq. 5-6 before the minimisation over
    :math:`\\lambda`): :math:`\\arg\\min_d D_{KL}(d \\| d_P) - \\lambda \\sum_{s,a} \\mathbb{1}_{d_S}(s,a) d(s,a)`
    over occupancies, with :math:`\\mathbb{1}_{d_S} = [d_S > threshold]`.

    Since :math:`\\sum d = 1`, the penalty is :math:`\\lambda` times the mass ``d`` puts off the support, and the
    objective equals :math:`D_{KL}(d \\| q) + const` with :math:`q \\propto d_P \\exp(\\lambda(\\mathbb{1}_{d_S} - 1))`:
    off-support pairs keep their ``d_P`` mass scaled by :math:`e^{-\\lambda}`. As :math:`\\lambda \\to \\infty`
    this tends to :func:`solve_spoildice` whenever Eq. (4) is feasible; unlike Eq. (4) it still has a solution
    when the support violates the feasibility assumption (Eq. 14), e.g. when slips reach states at which every
    action of ``supp(d_P)`` falls below the threshold. Off-support mass is then traded against the KL at the
    exchange rate :math:`\\lambda` (what a finite learned :math:`\\lambda` does in the neural Algorithm 1).

    Examples:
        >>> mdp = TabularCMDP(np.ones((1, 2, 1)), np.zeros((1, 2)), np.zeros((1, 2)), [1.0], 0.9)
        >>> d = solve_spoildice_lagrangian(mdp, [[0.5, 0.5]], [[1.0, 0.0]], lagrange=np.log(3.0))
        >>> d.round(6).tolist()  # the off-support action keeps 1/3 of its d_P weight
        [[0.75, 0.25]]
    """
    d_P = check_distribution(mdp, d_P, "d_P")
    d_S = check_distribution(mdp, d_S, "d_S")
    if threshold < 0:
        raise ValueError(f"threshold must be >= 0, got {threshold}")
    if not np.isfinite(lagrange) or lagrange < 0:
        raise ValueError(f"lagrange must be a finite number >= 0, got {lagrange}")
    with np.errstate(divide="ignore"):
        log_q = np.log(d_P) + lagrange * ((d_S > threshold) - 1.0)
    log_q = log_q - log_q.max()
    q = np.exp(log_q)
    return solve_kl_projection(mdp, q / q.sum(), np.ones_like(q, dtype=bool))
