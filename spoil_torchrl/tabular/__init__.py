"""Exact distribution-level solvers on finite CMDPs (paper Table B), used to check the neural losses and to run
the tabular gridworld experiment (section 5.1)."""

from spoil_torchrl.tabular.bc import check_pair_distribution, solve_bc, solve_fbc
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
from spoil_torchrl.tabular.demodice import demodice_objective, geometric_mixture, solve_demodice
from spoil_torchrl.tabular.optimal import flow_matrix, solve_cmdp_optimum, solve_mdp_optimum
from spoil_torchrl.tabular.spoildice import (
    admissible_pairs,
    solve_kl_projection,
    solve_spoildice,
    solve_spoildice_lagrangian,
)

__all__ = [
    "InfeasibleProblemError",
    "TabularCMDP",
    "admissible_pairs",
    "check_distribution",
    "check_pair_distribution",
    "demodice_objective",
    "evaluate",
    "flow_matrix",
    "flow_residual",
    "geometric_mixture",
    "occupancy",
    "policy_from_occupancy",
    "solve_bc",
    "solve_cmdp_optimum",
    "solve_demodice",
    "solve_fbc",
    "solve_kl_projection",
    "solve_mdp_optimum",
    "solve_spoildice",
    "solve_spoildice_lagrangian",
    "total_variation",
]
