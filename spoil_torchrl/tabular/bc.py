"""Behavioural-cloning targets of Table B: BC (``d = d_P``) and filtered BC (``d_P`` restricted to
``supp(d_S)``, renormalised).

Neither is a flow-constrained problem: Table B defines them as distributions, and their policies
:math:`\\pi(a|s) = d(s,a) / \\sum_{\\bar a} d(s,\\bar a)` are what appendix E.2 evaluates. ``solve_bc`` returns an
occupancy exactly when ``d_P`` is one; ``solve_fbc``'s output generally is not (it is the data distribution
BC would be trained on).
"""

from __future__ import annotations

import numpy as np

from spoil_torchrl.tabular.cmdp import INPUT_TOL, InfeasibleProblemError


def check_pair_distribution(d, name: str = "d") -> np.ndarray:
    """Validate a state-action distribution ``[S, A]`` without a CMDP at hand: 2-D, finite, non-negative,
    summing to 1. Returns a float64 copy.

    Examples:
        >>> check_pair_distribution([[0.25, 0.75]]).tolist()
        [[0.25, 0.75]]
    """
    if hasattr(d, "detach"):
        d = d.detach().cpu().numpy()
    arr = np.array(d, dtype=np.float64)
    if arr.ndim != 2:
        raise ValueError(f"{name} must be a [S, A] array, got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} contains NaN or infinite values")
    if (arr < 0).any() or abs(arr.sum() - 1.0) > INPUT_TOL:
        raise ValueError(f"{name} must be a distribution over state-action pairs (non-negative, sum 1)")
    return arr


def solve_bc(d_P) -> np.ndarray:
    """Table B row "BC": :math:`d = d_P` (behavioural cloning of the performant demonstrations).

    Examples:
        >>> solve_bc([[0.5, 0.25], [0.25, 0.0]]).tolist()
        [[0.5, 0.25], [0.25, 0.0]]
    """
    return check_pair_distribution(d_P, "d_P")


def solve_fbc(d_P, d_S, threshold: float = 0.0) -> np.ndarray:
    """Table B row "Filtered BC": :math:`d(s,a) = d_P(s,a)\\, \\mathbb{1}_{d_S}(s,a) / Z` with
    :math:`Z = \\sum_{(s,a) \\in supp(d_S)} d_P(s,a)` and :math:`supp(d_S) = \\{(s,a): d_S(s,a) > threshold\\}`
    (appendix E.2 sweeps the threshold over 1e-10 .. 1e-4).

    Raises:
        InfeasibleProblemError: ``d_P`` has no mass on the support (Z = 0), so there is nothing to clone.

    Examples:
        >>> solve_fbc([[0.5, 0.25], [0.25, 0.0]], [[0.5, 0.0], [0.3, 0.2]]).tolist()
        [[0.6666666666666666, 0.0], [0.3333333333333333, 0.0]]
    """
    d_P = check_pair_distribution(d_P, "d_P")
    d_S = check_pair_distribution(d_S, "d_S")
    if d_P.shape != d_S.shape:
        raise ValueError(f"d_P and d_S must have the same shape, got {d_P.shape} and {d_S.shape}")
    if not np.isfinite(threshold) or threshold < 0:
        raise ValueError(f"threshold must be a finite number >= 0, got {threshold}")
    kept = np.where(d_S > threshold, d_P, 0.0)
    z = kept.sum()
    if z <= 0.0:
        raise InfeasibleProblemError(
            f"filtered BC has nothing to clone: d_P puts no mass on supp(d_S) = {{d_S > {threshold:g}}}"
        )
    return kept / z
