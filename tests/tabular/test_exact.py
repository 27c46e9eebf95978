"""Exact tabular SpoilDICE (Eq. 4) and the CMDP helpers, against cases solved by hand."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from spoil_torchrl.tabular import (
    InfeasibleProblemError,
    TabularCMDP,
    evaluate,
    flow_residual,
    occupancy,
    policy_from_occupancy,
    solve_spoildice,
    total_variation,
)
from spoil_torchrl.tabular.problems import random_cmdp, random_dual_demo_problem
from tests.tabular.helpers import two_state_cmdp


def _kl(d, ref):
    mask = d > 0
    return float((d[mask] * np.log(d[mask] / ref[mask])).sum())


def test_occupancy_by_hand():
    mdp = two_state_cmdp(gamma=0.8)
    # pi(a1|s0) = 1: d(s0) = 1 - gamma = 0.2, the rest in s1.
    d = occupancy(mdp, [[0.0, 1.0], [0.5, 0.5]])
    np.testing.assert_allclose(d, [[0.0, 0.2], [0.4, 0.4]], atol=1e-12)
    # pi(a1|s0) = p: d(s0) = (1 - gamma) / (1 - gamma (1 - p)).
    p = 0.25
    d = occupancy(mdp, [[1 - p, p], [1.0, 0.0]])
    np.testing.assert_allclose(d[0].sum(), 0.2 / (1 - 0.8 * 0.75))
    assert np.abs(flow_residual(mdp, d)).max() < 1e-12
    assert evaluate(mdp, d) == pytest.approx((1 - d[0].sum(), d[0, 1]))


def test_support_excluding_the_exit_keeps_all_mass_in_the_start_state():
    mdp = two_state_cmdp()
    d_P = occupancy(mdp, [[0.5, 0.5], [0.5, 0.5]])
    d_S = np.array([[1.0, 0.0], [0.0, 0.0]])  # only (s0, a0) is safe
    d = solve_spoildice(mdp, d_P, d_S)
    np.testing.assert_allclose(d, [[1.0, 0.0], [0.0, 0.0]], atol=1e-9)


def test_full_support_returns_d_P_when_it_is_an_occupancy():
    """Appendix A, "trivial safe support": SpoilDICE collapses to distribution matching, i.e. BC."""
    problem = random_dual_demo_problem(seed=3)
    d = solve_spoildice(problem.mdp, problem.d_P, problem.d_U)  # d_U has full support
    assert total_variation(d, problem.d_P) < 1e-8


def test_single_state_projection_by_hand():
    mdp = TabularCMDP(np.ones((1, 3, 1)), np.zeros((1, 3)), np.zeros((1, 3)), [1.0], 0.9)
    d_P = np.array([[0.5, 0.3, 0.2]])
    d = solve_spoildice(mdp, d_P, [[0.4, 0.0, 0.6]])
    # KL projection onto {a0, a2} of a single-state problem renormalises d_P there.
    np.testing.assert_allclose(d, [[0.5 / 0.7, 0.0, 0.2 / 0.7]], atol=1e-9)


def test_matches_brute_force_over_policies():
    mdp = random_cmdp(3, 2, seed=4, gamma=0.7)
    d_P = occupancy(mdp, np.full((3, 2), 0.5))
    d_S = np.array([[0.3, 0.1], [0.0, 0.3], [0.2, 0.1]])  # (s1, a0) unsafe
    d = solve_spoildice(mdp, d_P, d_S)
    grid = np.linspace(0.0, 1.0, 41)
    best = np.inf
    for p0, p2 in itertools.product(grid, grid):
        pi = np.array([[p0, 1 - p0], [0.0, 1.0], [p2, 1 - p2]])
        best = min(best, _kl(occupancy(mdp, pi), d_P))
    assert _kl(d, d_P) <= best + 1e-9
    assert _kl(d, d_P) > best - 5e-3  # the grid's optimum is close to the exact one


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("slip", [1.0, 0.1, 0.01])
def test_flow_and_support_on_random_problems(seed, slip):
    # feasible by construction: d_S is a policy's occupancy and d_P has full support
    problem = random_dual_demo_problem(seed=seed, slip=slip)
    d = solve_spoildice(problem.mdp, problem.d_P, problem.d_S)
    assert np.abs(flow_residual(problem.mdp, d)).max() < 1e-6
    assert d[problem.d_S <= 0].sum() == 0.0
    assert d.sum() == pytest.approx(1.0, abs=1e-9)
    assert evaluate(problem.mdp, d)[1] == pytest.approx(0.0, abs=1e-12)  # safe support => zero cost


def test_infeasible_support_raises_a_clear_error():
    mdp = two_state_cmdp()
    d_P = occupancy(mdp, [[0.5, 0.5], [0.5, 0.5]])
    d_S = np.array([[0.0, 1.0], [0.0, 0.0]])  # s0 may only exit into s1, which has no safe action
    with pytest.raises(InfeasibleProblemError, match="Eq. \\(14\\)"):
        solve_spoildice(mdp, d_P, d_S)


def test_threshold_defines_the_support():
    mdp = two_state_cmdp()
    d_P = occupancy(mdp, [[0.5, 0.5], [0.5, 0.5]])
    d_S = np.array([[0.99, 1e-6], [0.0, 0.01 - 1e-6]])
    assert solve_spoildice(mdp, d_P, d_S, threshold=1e-5)[0, 1] == 0.0
    assert solve_spoildice(mdp, d_P, d_S, threshold=1e-7)[0, 1] > 0.0
    with pytest.raises(ValueError, match="threshold"):
        solve_spoildice(mdp, d_P, d_S, threshold=-1.0)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"transition": np.ones((2, 2, 2))}, "probability distribution"),
        ({"transition": np.ones((2, 2))}, "3 dimensions"),
        ({"cost": -np.ones((2, 2))}, "non-negative"),
        ({"reward": np.zeros((3, 2))}, "shape"),
        ({"init": [0.5, 0.6]}, "probability vector"),
        ({"gamma": 1.0}, "gamma"),
        ({"reward": np.full((2, 2), np.nan)}, "NaN"),
    ],
)
def test_bad_cmdp_inputs_raise(kwargs, match):
    base = two_state_cmdp()
    args = {
        "transition": base.transition,
        "reward": base.reward,
        "cost": base.cost,
        "init": base.init,
        "gamma": base.gamma,
        **kwargs,
    }
    with pytest.raises(ValueError, match=match):
        TabularCMDP(**args)


def test_bad_distributions_raise():
    mdp = two_state_cmdp()
    with pytest.raises(ValueError, match="shape"):
        solve_spoildice(mdp, np.ones((3, 2)) / 6, np.ones((2, 2)) / 4)
    with pytest.raises(ValueError, match="sum 1"):
        solve_spoildice(mdp, np.ones((2, 2)), np.ones((2, 2)) / 4)


def test_policy_from_occupancy_is_uniform_without_mass():
    pi = policy_from_occupancy(np.array([[0.0, 0.0], [0.2, 0.6]]))
    np.testing.assert_allclose(pi, [[0.5, 0.5], [0.25, 0.75]])


@pytest.mark.parametrize("seed", range(4))
def test_several_constraints_project_onto_the_intersection_of_the_supports(seed):
    """K safe distributions: the occupancy closest to d_P on the intersection of their supports, i.e. the
    single-constraint solution with the intersection as the support; one of them alone is the K = 1 case."""
    problem = random_dual_demo_problem(seed=seed, slip=0.1)
    mdp, d_S = problem.mdp, problem.d_S
    rng = np.random.default_rng(seed)
    allowed = rng.random(d_S.shape) < 0.5  # the second constraint's safe actions: half of them at random,
    allowed[np.arange(mdp.n_states), (d_S > 0).argmax(axis=1)] = True  # and one of the first's in each state
    other = occupancy(mdp, allowed / allowed.sum(axis=1, keepdims=True))
    assert ((d_S > 0) & ~(other > 0)).any()  # the second constraint cuts pairs the first allows
    intersection = ((d_S > 0) & (other > 0)).astype(float)
    d_two = solve_spoildice(mdp, problem.d_P, [d_S, other])
    d_cut = solve_spoildice(mdp, problem.d_P, intersection / intersection.sum())
    np.testing.assert_allclose(d_two, d_cut, atol=1e-12)
    assert d_two[(d_S <= 0) | (other <= 0)].sum() == 0.0
    assert np.abs(flow_residual(mdp, d_two)).max() < 1e-6
    np.testing.assert_array_equal(
        solve_spoildice(mdp, problem.d_P, [d_S]), solve_spoildice(mdp, problem.d_P, d_S)
    )
    assert _kl(d_two, problem.d_P) >= _kl(solve_spoildice(mdp, problem.d_P, d_S), problem.d_P) - 1e-12


def test_supports_without_a_common_pair_are_refused_with_their_sizes():
    mdp = two_state_cmdp()
    d_P = occupancy(mdp, [[0.5, 0.5], [0.5, 0.5]])
    left = np.array([[1.0, 0.0], [0.0, 0.0]])
    right = np.array([[0.0, 0.5], [0.5, 0.0]])
    with pytest.raises(
        InfeasibleProblemError, match="share no state-action pair .*constraint 0: 1, constraint 1: 2"
    ):
        solve_spoildice(mdp, d_P, np.stack([left, right]))
