"""Appendix E.2's evaluation protocol: feasibility and the per-problem selection over hyper-parameters.

The numbers Figure 3b / Figure A report use the evaluation package's helpers, not copies of them:

* normalised return :func:`~spoil_torchrl.eval.metrics.normalized_return` ``(J, J_random, J_cmdp_optimum)``:
  0 for the uniform random policy, 1 for the CMDP optimum, and normalised cost
  :func:`~spoil_torchrl.eval.metrics.normalized_cost` ``(J_c, delta_c)`` = ``J_c / delta_c`` (1 = on the
  limit), both through :func:`normalise`;
* mean and standard error over seeds :func:`~spoil_torchrl.eval.tables.mean_stderr` (sample standard deviation
  over ``sqrt(n)``; ``nan`` for a single seed).
"""

from __future__ import annotations

from collections.abc import Sequence

from spoil_torchrl.eval.metrics import normalized_cost, normalized_return

#: Relative slack on ``J(pi; c) <= delta_c``: the CMDP optimum sits *on* the limit, and its cost after the
#: exact policy evaluation exceeds delta_c by the LP's tolerance (primal feasibility 1e-10 absolute, i.e. up to
#: 1e-6 of delta_c = 1e-4; 1.2e-6 measured in the gridworld's seed 36), and ``solve_cmdp_optimum`` only
#: guarantees ``delta_c + 1e-9`` (its ``COST_TOL``), which is 1e-5 of delta_c = 1e-4.
FEASIBILITY_RTOL = 1e-5


def is_feasible(cost: float, cost_limit: float) -> bool:
    """``J(pi; c) <= delta_c`` up to :data:`FEASIBILITY_RTOL` (appendix E.2's feasibility).

    Examples:
        >>> is_feasible(1e-4, 1e-4), is_feasible(1.1e-4, 1e-4)
        (True, False)
    """
    return bool(cost <= cost_limit * (1.0 + FEASIBILITY_RTOL))


def select_candidate(candidates: Sequence[dict], cost_limit: float) -> dict:
    """Appendix E.2: among one method's candidates (one per hyper-parameter, each a dict with ``"return"``
    and ``"cost"``), the highest-return feasible one; if none is feasible, the lowest-cost one. Ties keep the
    first candidate. The returned dict is the chosen candidate with ``"feasible"`` added.

    Examples:
        >>> cands = [{"h": 1, "return": 0.9, "cost": 2e-4}, {"h": 2, "return": 0.5, "cost": 0.0}]
        >>> select_candidate(cands, 1e-4)["h"], select_candidate(cands, 1e-3)["h"]
        (2, 1)
    """
    if not candidates:
        raise ValueError("no candidates to select from")
    feasible = [c for c in candidates if is_feasible(c["cost"], cost_limit)]
    if feasible:
        best = max(feasible, key=lambda c: c["return"])
    else:
        best = min(candidates, key=lambda c: c["cost"])
    return {**best, "feasible": bool(feasible)}


def normalise(
    ret: float, cost: float, *, random_return: float, optimal_return: float, cost_limit: float
) -> dict[str, float]:
    """Figure A's normalised return (0 = uniform random policy, 1 = CMDP optimum) and Figure 3b's normalised
    cost (``J(pi; c) / delta_c``) of one policy, by :func:`~spoil_torchrl.eval.metrics.normalized_return` and
    :func:`~spoil_torchrl.eval.metrics.normalized_cost`.

    Examples:
        >>> normalise(0.75, 2e-4, random_return=0.5, optimal_return=1.0, cost_limit=1e-4)
        {'normalised_return': 0.5, 'normalised_cost': 2.0}
    """
    if not optimal_return > random_return:
        raise ValueError(
            f"the CMDP optimum's return ({optimal_return}) must exceed the random policy's ({random_return})"
        )
    return {
        "normalised_return": float(normalized_return(ret, random_return, optimal_return)),
        "normalised_cost": float(normalized_cost(cost, cost_limit)),
    }
