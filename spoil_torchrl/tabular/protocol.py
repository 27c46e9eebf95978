"""Appendix E.2's evaluation protocol: per-problem selection over hyper-parameters and the normalisations of
Figure 3b / Figure A."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

#: Relative slack on ``J(pi; c) <= delta_c``: the CMDP optimum sits *on* the limit, and its cost after the
#: exact policy evaluation differs from delta_c by round-off (about 1e-12 relative).
FEASIBILITY_RTOL = 1e-6


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


def normalised_return(value: float, random_return: float, optimal_return: float) -> float:
    """Figure A's normalised return: 0 for the uniform random policy, 1 for the CMDP optimum.

    Examples:
        >>> normalised_return(0.75, 0.5, 1.0)
        0.5
    """
    if not optimal_return > random_return:
        raise ValueError(
            f"the CMDP optimum's return ({optimal_return}) must exceed the random policy's ({random_return})"
        )
    return float((value - random_return) / (optimal_return - random_return))


def normalised_cost(value: float, cost_limit: float) -> float:
    """Figure 3b's normalised cost ``J(pi; c) / delta_c`` (1 = on the limit).

    Examples:
        >>> normalised_cost(2e-4, 1e-4)
        2.0
    """
    if not cost_limit > 0:
        raise ValueError(f"cost_limit must be positive, got {cost_limit}")
    return float(value / cost_limit)


def mean_and_standard_error(values) -> tuple[float, float]:
    """Mean and standard error (sample std with ``ddof=1`` over ``sqrt(n)``; 0 for a single value).

    Examples:
        >>> mean_and_standard_error([1.0, 3.0])
        (2.0, 1.0)
    """
    x = np.asarray(values, dtype=np.float64)
    if x.size == 0:
        raise ValueError("no values")
    se = float(x.std(ddof=1) / np.sqrt(x.size)) if x.size > 1 else 0.0
    return float(x.mean()), se
