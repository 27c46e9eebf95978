"""BC, filtered BC and DemoDICE (Table B rows) against cases solved by hand and by brute force."""

from __future__ import annotations

import numpy as np
import pytest

from spoil_torchrl.tabular import (
    InfeasibleProblemError,
    TabularCMDP,
    demodice_objective,
    flow_residual,
    geometric_mixture,
    occupancy,
    solve_bc,
    solve_demodice,
    solve_fbc,
    solve_kl_projection,
    total_variation,
)
from spoil_torchrl.tabular.problems import random_cmdp, random_dual_demo_problem
from tests.tabular.helpers import two_state_cmdp


def test_bc_is_d_p_and_validates():
    d_P = np.array([[0.1, 0.2], [0.3, 0.4]])
    np.testing.assert_array_equal(solve_bc(d_P), d_P)
    with pytest.raises(ValueError, match="sum 1"):
        solve_bc(d_P * 2)
    with pytest.raises(ValueError, match=r"\[S, A\]"):
        solve_bc(np.ones(4) / 4)
    with pytest.raises(ValueError, match="NaN"):
        solve_bc([[np.nan, 1.0]])


def test_fbc_equals_the_renormalised_restriction():
    # By hand: supp(d_S) = {(0,0), (1,0), (1,1)}; d_P there sums to 0.1 + 0.3 + 0.4 = 0.8.
    d_P = np.array([[0.1, 0.2], [0.3, 0.4]])
    d_S = np.array([[0.5, 0.0], [0.25, 0.25]])
    np.testing.assert_allclose(solve_fbc(d_P, d_S), [[0.125, 0.0], [0.375, 0.5]])
    # A threshold of 0.3 leaves only (0,0): d = its renormalised d_P mass, i.e. 1.
    np.testing.assert_allclose(solve_fbc(d_P, d_S, threshold=0.3), [[1.0, 0.0], [0.0, 0.0]])


def test_fbc_random_problems_match_the_formula():
    rng = np.random.default_rng(0)
    for _ in range(5):
        d_P = rng.dirichlet(np.ones(12)).reshape(4, 3)
        d_S = rng.dirichlet(np.ones(12)).reshape(4, 3) * (rng.uniform(size=(4, 3)) < 0.6)
        d_S = d_S / d_S.sum()
        threshold = 0.02
        keep = d_S > threshold
        np.testing.assert_allclose(solve_fbc(d_P, d_S, threshold), d_P * keep / (d_P * keep).sum())


def test_fbc_raises_when_nothing_remains():
    with pytest.raises(InfeasibleProblemError, match="nothing to clone"):
        solve_fbc([[1.0, 0.0]], [[0.0, 1.0]])
    with pytest.raises(ValueError, match="threshold"):
        solve_fbc([[1.0, 0.0]], [[1.0, 0.0]], threshold=-1.0)
    with pytest.raises(ValueError, match="same shape"):
        solve_fbc([[1.0, 0.0]], [[1.0], [0.0]])


def test_geometric_mixture_identity():
    """KL(d||P) + a KL(d||S) = (1+a) KL(d||m) - (1+a) log Z for every d (the identity DemoDICE uses)."""
    rng = np.random.default_rng(1)
    p, s_ = rng.dirichlet(np.ones(6)).reshape(2, 3), rng.dirichlet(np.ones(6)).reshape(2, 3)
    alpha = 2.5
    log_z = np.log((p ** (1 / (1 + alpha)) * s_ ** (alpha / (1 + alpha))).sum())
    m = geometric_mixture(p, s_, alpha)
    for _ in range(3):
        d = rng.dirichlet(np.ones(6)).reshape(2, 3)
        kl_m = float((d * np.log(d / m)).sum())
        assert demodice_objective(d, p, s_, alpha) == pytest.approx((1 + alpha) * (kl_m - log_z), rel=1e-10)


def test_demodice_single_state_by_hand():
    # One state: the flow constraint only asks for sum 1, so d = m = sqrt(d_P d_S) / Z at alpha = 1:
    # sqrt(0.5 * 0.8) = 0.632.., sqrt(0.5 * 0.2) = 0.316.. -> (2/3, 1/3). This case also used to stall the
    # Newton solver's line search in round-off (regression test).
    mdp = TabularCMDP(np.ones((1, 2, 1)), np.zeros((1, 2)), np.zeros((1, 2)), [1.0], 0.9)
    d = solve_demodice(mdp, [[0.5, 0.5]], [[0.8, 0.2]], alpha=1.0)
    np.testing.assert_allclose(d, [[2 / 3, 1 / 3]], atol=1e-9)


def test_demodice_two_state_against_the_occupancy_family():
    """On _two_state (gamma = 0.8) every occupancy is d = [[x, y], [z, 4y - z]]: flow at s0 reads
    x + y = 0.2 + 0.8 x, so y = 0.2 (1 - x), and flow at s1 reads d(s1) = 0.8 (y + d(s1)), so d(s1) = 4 y.
    Minimising the DemoDICE objective over a fine (x, z) grid of that family must not beat the solver."""
    mdp = two_state_cmdp(gamma=0.8)
    d_P = occupancy(mdp, [[0.2, 0.8], [0.5, 0.5]])
    d_S = occupancy(mdp, [[0.9, 0.1], [0.3, 0.7]])
    alpha = 3.0
    d = solve_demodice(mdp, d_P, d_S, alpha)
    y = 0.2 * (1 - d[0, 0])
    np.testing.assert_allclose([d[0, 1], d[1].sum()], [y, 4 * y], atol=1e-9)  # it lies in the family
    best = np.inf
    for x in np.linspace(0.0005, 0.9995, 400):
        y = 0.2 * (1 - x)
        for share in np.linspace(0.0025, 0.9975, 200):
            candidate = np.array([[x, y], [share * 4 * y, (1 - share) * 4 * y]])
            best = min(best, demodice_objective(candidate, d_P, d_S, alpha))
    value = demodice_objective(d, d_P, d_S, alpha)
    assert value <= best + 1e-12
    assert value > best - 1e-4
    assert np.abs(flow_residual(mdp, d)).max() < 1e-6


def test_demodice_tends_to_bc_as_alpha_vanishes_with_full_support_d_s():
    problem = random_dual_demo_problem(seed=3)
    d_S = problem.d_U  # full support
    gaps = [
        total_variation(solve_demodice(problem.mdp, problem.d_P, d_S, a), problem.d_P)
        for a in (1.0, 1e-2, 1e-4)
    ]
    assert gaps[0] > gaps[1] > gaps[2]
    assert gaps[2] < 1e-3
    assert total_variation(solve_demodice(problem.mdp, problem.d_P, d_S, 0.0), problem.d_P) < 1e-8


def test_demodice_restricts_to_the_intersection_of_supports():
    problem = random_dual_demo_problem(seed=1)  # supp(d_S) excludes every costly pair
    for alpha in (1e-3, 1.0, 100.0):
        d = solve_demodice(problem.mdp, problem.d_P, problem.d_S, alpha)
        assert d[problem.d_S == 0].sum() == 0.0
        assert np.abs(flow_residual(problem.mdp, d)).max() < 1e-6


def test_demodice_tends_to_the_restricted_safe_behaviour_for_large_alpha():
    """alpha -> inf: m -> d_S restricted to supp(d_P), renormalised; d -> its KL projection."""
    mdp = random_cmdp(5, 3, seed=2, gamma=0.8)
    rng = np.random.default_rng(2)
    pi_P = rng.dirichlet(np.ones(3), size=5) * (rng.uniform(size=(5, 3)) < 0.7)
    pi_P[np.arange(5), rng.integers(3, size=5)] = 1.0  # every state keeps an action
    d_P = occupancy(mdp, pi_P / pi_P.sum(1, keepdims=True))
    d_S = occupancy(mdp, rng.dirichlet(np.ones(3), size=5))  # full support
    restricted = np.where(d_P > 0, d_S, 0.0)
    limit = solve_kl_projection(mdp, restricted / restricted.sum(), d_P > 0)
    gaps = [total_variation(solve_demodice(mdp, d_P, d_S, a), limit) for a in (1.0, 100.0, 1e4)]
    assert gaps[0] > gaps[1] > gaps[2]
    assert gaps[2] < 1e-3
    # with full-support d_P the limit is d_S itself
    d_P_full = occupancy(mdp, np.full((5, 3), 1 / 3))
    assert total_variation(solve_demodice(mdp, d_P_full, d_S, 1e5), d_S) < 1e-4


def test_demodice_bad_inputs():
    mdp = two_state_cmdp()
    d = occupancy(mdp, [[0.5, 0.5], [0.5, 0.5]])
    with pytest.raises(ValueError, match="alpha"):
        solve_demodice(mdp, d, d, alpha=-1.0)
    with pytest.raises(ValueError, match="disjoint"):
        solve_demodice(mdp, [[1.0, 0.0], [0.0, 0.0]], [[0.0, 1.0], [0.0, 0.0]], alpha=1.0)
    # supports that meet only where no occupancy can live: s0 may only exit into s1, whose pairs are excluded
    with pytest.raises(InfeasibleProblemError):
        solve_demodice(mdp, d, [[0.0, 1.0], [0.0, 0.0]], alpha=1.0)
