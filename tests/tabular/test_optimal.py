"""CMDP / MDP optima by linear programming, and SpoilDICE at a fixed lambda (Eq. 6)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from spoil_torchrl.tabular import (
    InfeasibleProblemError,
    TabularCMDP,
    flow_residual,
    occupancy,
    solve_cmdp_optimum,
    solve_mdp_optimum,
    solve_spoildice,
    solve_spoildice_lagrangian,
    total_variation,
)
from spoil_torchrl.tabular.problems import random_cmdp, random_dual_demo_problem


def _two_state(gamma=0.8, exit_cost=1.0, stay_cost=0.0):
    """s0 (start): a0 stays, a1 moves to the absorbing s1 whose pairs pay reward 1."""
    transition = np.zeros((2, 2, 2))
    transition[0, 0, 0] = transition[0, 1, 1] = 1.0
    transition[1, :, 1] = 1.0
    reward = np.array([[0.0, 0.0], [1.0, 1.0]])
    cost = np.array([[stay_cost, exit_cost], [0.0, 0.0]])
    return TabularCMDP(transition, reward, cost, [1.0, 0.0], gamma)


def _value_iteration(mdp: TabularCMDP, iters: int = 2000) -> float:
    v = np.zeros(mdp.n_states)
    for _ in range(iters):
        v = (mdp.reward + mdp.gamma * mdp.transition @ v).max(axis=1)
    return float((1 - mdp.gamma) * mdp.init @ v)


def test_cmdp_optimum_by_hand():
    # Exit with probability p in s0: d(s0) = (1-g) / (1-g+g p), cost = p d(s0), return = 1 - d(s0).
    # With g = 0.8 and delta = 0.1: p (0.2) = 0.1 (0.2 + 0.8 p)  =>  p = 1/6, d(s0) = 0.6, return 0.4.
    mdp = _two_state(gamma=0.8)
    d = solve_cmdp_optimum(mdp, cost_limit=0.1)
    np.testing.assert_allclose(d[0], [0.5, 0.1], atol=1e-9)
    assert d[1].sum() == pytest.approx(0.4, abs=1e-9)
    assert np.abs(flow_residual(mdp, d)).max() < 1e-12
    # Unconstrained: exit at once, d(s0) = 1 - g = 0.2, return 0.8 (and cost 0.2).
    d = solve_mdp_optimum(mdp)
    np.testing.assert_allclose(d[0], [0.0, 0.2], atol=1e-9)
    assert (d * mdp.reward).sum() == pytest.approx(0.8, abs=1e-9)
    # A loose limit does not bind.
    np.testing.assert_allclose(solve_cmdp_optimum(mdp, cost_limit=0.5), d, atol=1e-9)


def test_infeasible_cost_limit_raises():
    # Both actions of s0 cost 1 and s0 holds at least 1 - g = 0.2 of the mass: the least cost is 0.2.
    mdp = _two_state(gamma=0.8, exit_cost=1.0, stay_cost=1.0)
    assert (solve_cmdp_optimum(mdp, 0.2) * mdp.cost).sum() == pytest.approx(0.2, abs=1e-9)
    with pytest.raises(InfeasibleProblemError, match="cost limit"):
        solve_cmdp_optimum(mdp, 0.1)
    with pytest.raises(ValueError, match="cost_limit"):
        solve_cmdp_optimum(mdp, -1.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_lp_optimum_beats_every_feasible_policy(seed):
    mdp = random_cmdp(3, 2, seed=seed, gamma=0.8, slip=0.5)
    grid = np.linspace(0.0, 1.0, 11)
    policies = [np.array([[p, 1 - p] for p in ps]) for ps in itertools.product(grid, repeat=3)]
    values = [
        (float((d * mdp.reward).sum()), float((d * mdp.cost).sum()))
        for d in map(lambda p: occupancy(mdp, p), policies)
    ]
    costs = [c for _, c in values]
    limit = 0.5 * (min(costs) + max(costs))  # binding for these problems
    d = solve_cmdp_optimum(mdp, limit)
    best_return, best_cost = float((d * mdp.reward).sum()), float((d * mdp.cost).sum())
    assert best_cost <= limit + 1e-9
    assert np.abs(flow_residual(mdp, d)).max() < 1e-9
    feasible = [r for r, c in values if c <= limit]
    assert max(feasible) <= best_return + 1e-9
    assert max(feasible) > best_return - 0.02  # the grid gets close to the optimum
    # The unconstrained optimum matches value iteration and beats every policy.
    d_u = solve_mdp_optimum(mdp)
    assert float((d_u * mdp.reward).sum()) == pytest.approx(_value_iteration(mdp), abs=1e-9)
    assert max(r for r, _ in values) <= float((d_u * mdp.reward).sum()) + 1e-9


def test_lagrangian_spoildice_single_state_by_hand():
    # One state: d is q = d_P exp(lambda (1_S - 1)) renormalised. d_P = (0.5, 0.5), action 1 off the support:
    # q = (0.5, 0.5 e^-lambda) -> d1 = 1 / (1 + e^lambda).
    mdp = TabularCMDP(np.ones((1, 2, 1)), np.zeros((1, 2)), np.zeros((1, 2)), [1.0], 0.9)
    for lam in (0.0, 1.0, 5.0):
        d = solve_spoildice_lagrangian(mdp, [[0.5, 0.5]], [[1.0, 0.0]], lagrange=lam)
        assert d[0, 1] == pytest.approx(1.0 / (1.0 + np.exp(lam)), abs=1e-9)
    with pytest.raises(ValueError, match="lagrange"):
        solve_spoildice_lagrangian(mdp, [[0.5, 0.5]], [[1.0, 0.0]], lagrange=-1.0)


def test_lagrangian_spoildice_tends_to_eq4_when_feasible():
    problem = random_dual_demo_problem(seed=0, slip=0.1)
    exact = solve_spoildice(problem.mdp, problem.d_P, problem.d_S)
    gaps = [
        total_variation(
            solve_spoildice_lagrangian(problem.mdp, problem.d_P, problem.d_S, lagrange=lam), exact
        )
        for lam in (1.0, 10.0, 40.0)
    ]
    assert gaps[0] > gaps[1] > gaps[2]
    assert gaps[2] < 1e-9


def test_lagrangian_spoildice_exists_where_eq4_is_infeasible():
    # s0 may only exit into s1, and s1 has no safe action: Eq. (4) has no solution, Eq. (6) trades mass.
    mdp = _two_state()
    d_P = occupancy(mdp, [[0.5, 0.5], [0.5, 0.5]])
    d_S = np.array([[0.0, 1.0], [0.0, 0.0]])
    with pytest.raises(InfeasibleProblemError):
        solve_spoildice(mdp, d_P, d_S)
    d = solve_spoildice_lagrangian(mdp, d_P, d_S, lagrange=20.0)
    assert np.abs(flow_residual(mdp, d)).max() < 1e-6
    # On-support mass is d(s0, a1) = 0.2 p / (0.2 + 0.8 p) for exit probability p, largest (0.2) at p = 1:
    # at lambda = 20 the solution all but always exits.
    assert d[0, 1] > 0.199
    assert d[0, 0] < 0.005
