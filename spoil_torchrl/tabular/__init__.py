"""Exact distribution-level solvers on finite CMDPs (paper Table B), used to check the neural losses."""

from spoil_torchrl.tabular.cmdp import (
    InfeasibleProblemError,
    TabularCMDP,
    check_distribution,
    evaluate,
    flow_residual,
    occupancy,
    policy_from_occupancy,
    total_variation,
)
from spoil_torchrl.tabular.spoildice import admissible_pairs, solve_kl_projection, solve_spoildice

__all__ = [
    "InfeasibleProblemError",
    "TabularCMDP",
    "admissible_pairs",
    "check_distribution",
    "evaluate",
    "flow_residual",
    "occupancy",
    "policy_from_occupancy",
    "solve_kl_projection",
    "solve_spoildice",
    "total_variation",
]
