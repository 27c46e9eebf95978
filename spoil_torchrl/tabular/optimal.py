"""Optimal occupancies by linear programming: the CMDP optimum :math:`d^*_{M_c}` and the MDP optimum
:math:`d^*_M` of appendix E.1.

Both are the primal LP over normalised occupancies (section 3.1)

.. math::
    \\max_{d \\ge 0} \\; E_d[r] \\quad \\text{s.t.} \\quad \\sum_a d(s,a) = (1-\\gamma)\\rho_0(s)
    + \\gamma \\sum_{\\bar s,\\bar a} T(s|\\bar s,\\bar a) d(\\bar s,\\bar a) \\;\\forall s,
    \\qquad E_d[c] \\le \\delta_c,

with the cost row for the CMDP and without it for the MDP, solved by HiGHS (``scipy.optimize.linprog``).
The LP's vertex is then *polished*: the policy :math:`\\pi = d / \\sum_a d` is extracted and its occupancy
recomputed by a linear solve, so the returned ``d`` satisfies the flow constraint to machine precision (HiGHS
itself only guarantees its primal feasibility tolerance, about 1e-7).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linprog

from spoil_torchrl.tabular.cmdp import InfeasibleProblemError, TabularCMDP, occupancy, policy_from_occupancy

#: HiGHS primal / dual feasibility tolerance (its default, 1e-7, is 1e-3 of the paper's delta_c).
LP_TOL = 1e-10
#: Slack allowed on ``E_d[c] <= cost_limit`` after polishing (absolute, in normalised-occupancy units).
COST_TOL = 1e-9


def flow_matrix(mdp: TabularCMDP) -> np.ndarray:
    """The Bellman-flow equality rows ``[S, S*A]``: ``(flow_matrix @ d.ravel())[s]`` is the left-hand side
    :math:`\\sum_a d(s,a) - \\gamma \\sum_{\\bar s,\\bar a} T(s|\\bar s,\\bar a) d(\\bar s,\\bar a)`, to equal
    :math:`(1-\\gamma)\\rho_0(s)`.

    Examples:
        >>> mdp = TabularCMDP([[[0.0, 1.0]], [[0.0, 1.0]]], [[0.0], [1.0]], [[0.0], [0.0]], [1.0, 0.0], 0.5)
        >>> flow_matrix(mdp).tolist()
        [[1.0, 0.0], [-0.5, 0.5]]
    """
    n_s, n_a = mdp.n_states, mdp.n_actions
    own = np.repeat(np.eye(n_s), n_a, axis=1)  # [s, (s̄, ā)] = 1[s̄ == s]
    inflow = mdp.transition.reshape(n_s * n_a, n_s).T  # [s, (s̄, ā)] = T(s | s̄, ā)
    return own - mdp.gamma * inflow


def _solve_lp(mdp: TabularCMDP, cost_limit: float | None) -> np.ndarray:
    n_s, n_a = mdp.n_states, mdp.n_actions
    kwargs = {}
    if cost_limit is not None:
        kwargs = {"A_ub": mdp.cost.reshape(1, -1), "b_ub": [cost_limit]}
    result = linprog(
        -mdp.reward.ravel(),
        A_eq=flow_matrix(mdp),
        b_eq=(1.0 - mdp.gamma) * mdp.init,
        bounds=(0, None),
        method="highs",
        options={"primal_feasibility_tolerance": LP_TOL, "dual_feasibility_tolerance": LP_TOL},
        **kwargs,
    )
    if result.status == 2:
        raise InfeasibleProblemError(
            f"no occupancy satisfies E_d[c] <= {cost_limit}: the cost limit is below the least achievable "
            "expected cost of this CMDP (HiGHS reports the LP infeasible)"
        )
    if result.status != 0:
        raise RuntimeError(f"the occupancy LP failed: {result.message}")
    d = np.clip(result.x.reshape(n_s, n_a), 0.0, None)
    polished = occupancy(mdp, policy_from_occupancy(d))
    if cost_limit is not None and (polished * mdp.cost).sum() > cost_limit + COST_TOL:
        raise RuntimeError(
            f"the polished LP solution violates the cost limit by {(polished * mdp.cost).sum() - cost_limit:.3e}"
        )
    return polished


def solve_cmdp_optimum(mdp: TabularCMDP, cost_limit: float) -> np.ndarray:
    """The CMDP-optimal occupancy :math:`d^*_{M_c} = \\arg\\max_d E_d[r]` s.t. flow and
    :math:`E_d[c] \\le \\delta_c` (section 3.1's CMDP; appendix E.1's :math:`d^*_{M_c}`).

    Args:
        mdp: the CMDP.
        cost_limit: :math:`\\delta_c` (appendix E.1 uses 1e-4), in normalised-occupancy units.

    Returns:
        ``d`` ``[S, A]`` satisfying the flow constraint to machine precision and ``E_d[c] <= cost_limit``
        (to :data:`COST_TOL`). An LP vertex: the policy randomises in at most one state.

    Raises:
        InfeasibleProblemError: no occupancy meets the cost limit.

    Examples:
        >>> # s0: a0 stays (reward 0), a1 jumps to s1 (cost 1); s1 pays reward 1 forever.
        >>> T = np.zeros((2, 2, 2)); T[0, 0, 0] = T[0, 1, 1] = 1.0; T[1, :, 1] = 1.0
        >>> mdp = TabularCMDP(T, [[0.0, 0.0], [1.0, 1.0]], [[0.0, 1.0], [0.0, 0.0]], [1.0, 0.0], 0.5)
        >>> d = solve_cmdp_optimum(mdp, cost_limit=0.25)  # jump w.p. 1/3: d(s0, a1) = 0.25
        >>> np.round(d[0], 9).tolist(), round(float(d[1].sum()), 9), round(float((d * mdp.cost).sum()), 9)
        ([0.5, 0.25], 0.25, 0.25)
    """
    if not np.isfinite(cost_limit) or cost_limit < 0:
        raise ValueError(f"cost_limit must be a finite non-negative number, got {cost_limit}")
    return _solve_lp(mdp, float(cost_limit))


def solve_mdp_optimum(mdp: TabularCMDP) -> np.ndarray:
    """The unconstrained optimal occupancy :math:`d^*_M = \\arg\\max_d E_d[r]` s.t. flow (appendix E.1).

    Examples:
        >>> T = np.zeros((2, 2, 2)); T[0, 0, 0] = T[0, 1, 1] = 1.0; T[1, :, 1] = 1.0
        >>> mdp = TabularCMDP(T, [[0.0, 0.0], [1.0, 1.0]], [[0.0, 1.0], [0.0, 0.0]], [1.0, 0.0], 0.5)
        >>> d = solve_mdp_optimum(mdp)  # jump at once, whatever it costs
        >>> float(d[0, 1]), float(d[1].sum())
        (0.5, 0.5)
    """
    return _solve_lp(mdp, None)
