"""DemoDICELoss + WeightedBCLoss optimise DemoDICE's objective: neural vs exact on random CMDPs.

With samples of d_R and the reward log d_P/d_R, the DemoDICE dual's optimum is
argmin_d KL(d||d_P) + alpha KL(d||d_R) over occupancies, i.e. ``solve_demodice(mdp, d_P, d_R, alpha)``:
d_R = d_S for DemoDICE-S (the Table B row of the gridworld experiment), d_R = d_U for DemoDICE-U. The rewards
are the exact log-ratios of the tables, so this checks the dual and the policy extraction (the discriminators
are checked by test_neural_convergence.py). One-hot features, the library's TorchRL buffers, 1,000 steps at
twice the default step sizes: half the time of 2,000 steps at the default sizes, with TVs within 0.003 of theirs.

Seed 2 of the slip-0.1 family fails for DemoDICE-S as it does for SpoilDICE (CONTRIBUTING.md, "Known
limitation of sample-based DICE"): the one-sample estimate of gamma nu(s') inside exp(.) is biased when nu has
a large range, so that case is a strict xfail here too.
"""

from __future__ import annotations

import numpy as np
import pytest

from spoil_torchrl.tabular import flow_residual, solve_demodice, total_variation
from spoil_torchrl.tabular.neural import TabularTrainingConfig, train_tabular_demodice
from spoil_torchrl.tabular.problems import random_dual_demo_problem

TV_TOLERANCE = 0.05
CONFIG = {"dice_steps": 1_000, "nu_lr": 2e-2, "actor_lr": 2e-2}


@pytest.mark.parametrize("seed", [0, 1, 3])
def test_neural_demodice_s_matches_the_exact_solution(seed):
    problem = random_dual_demo_problem(seed=seed, slip=0.1)
    exact = solve_demodice(problem.mdp, problem.d_P, problem.d_S, alpha=0.1)
    assert np.abs(flow_residual(problem.mdp, exact)).max() < 1e-6
    assert exact[problem.d_S <= 0].sum() == 0.0  # it lives on supp(d_S)
    assert total_variation(problem.d_P, exact) > 0.2  # the regulariser matters: BC is far from it

    result = train_tabular_demodice(
        problem, 0.1, regularization="safe", config=TabularTrainingConfig(seed=seed, **CONFIG)
    )

    assert total_variation(result.occupancy, exact) <= TV_TOLERANCE
    assert result.history[-1]["demodice/weight_max"] > 1.0


@pytest.mark.parametrize(("alpha", "seed"), [(0.1, 0), (0.1, 2), (1.0, 0), (1.0, 2)])
def test_neural_demodice_u_matches_the_exact_solution(alpha, seed):
    problem = random_dual_demo_problem(seed=seed, slip=0.1)
    exact = solve_demodice(problem.mdp, problem.d_P, problem.d_U, alpha=alpha)

    result = train_tabular_demodice(
        problem, alpha, regularization="unlabeled", config=TabularTrainingConfig(seed=seed, **CONFIG)
    )

    tv = total_variation(result.occupancy, exact)
    assert tv <= TV_TOLERANCE
    # closer to the answer than either distribution it trades off (at alpha = 0.1 d_P is only ~0.02 away)
    assert tv < total_variation(problem.d_P, exact) and tv < total_variation(problem.d_U, exact)


@pytest.mark.xfail(strict=True, reason="one-sample exp(gamma nu(s')) bias, see the module docstring")
def test_known_limitation_seed_2_demodice_s():
    problem = random_dual_demo_problem(seed=2, slip=0.1)
    exact = solve_demodice(problem.mdp, problem.d_P, problem.d_S, alpha=0.1)
    result = train_tabular_demodice(
        problem, 0.1, regularization="safe", config=TabularTrainingConfig(seed=2, **CONFIG)
    )
    assert total_variation(result.occupancy, exact) <= TV_TOLERANCE


def test_unknown_regularization_role_raises():
    with pytest.raises(ValueError, match="regularization"):
        train_tabular_demodice(random_dual_demo_problem(seed=0), 0.1, regularization="performant")
