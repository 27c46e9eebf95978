"""The appendix-E.1 gridworld, its demonstrators, and the appendix-E.2 protocol."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from spoil_torchrl.eval.metrics import normalized_return
from spoil_torchrl.eval.tables import mean_stderr
from spoil_torchrl.tabular import evaluate, flow_residual, occupancy
from spoil_torchrl.tabular.gridworld import (
    LAYOUTS,
    MOVES,
    grid_transition,
    make_demonstrators,
    make_gridworld,
    performant_distribution,
    route_lengths,
    safe_distribution,
    safe_random_policy,
    zone_candidates,
    zone_cells,
)
from spoil_torchrl.tabular.protocol import is_feasible, normalise, select_candidate


@pytest.fixture(scope="module")
def grid():
    return make_gridworld(0)


@pytest.fixture(scope="module")
def demo(grid):
    return make_demonstrators(grid)


def test_sizes_and_rows(grid):
    mdp = grid.mdp
    assert (mdp.n_states, mdp.n_actions, mdp.gamma, grid.cost_limit) == (122, 4, 0.95, 1e-4)
    np.testing.assert_allclose(mdp.transition.sum(-1), 1.0, atol=1e-12)
    assert (grid.start, grid.goal) == ((5, 0), (5, 10))  # the default layout, "across"
    assert mdp.init[grid.cell(5, 0)] == 1.0


def test_moves_slips_and_walls():
    size, T = 11, grid_transition(11, goal=(10, 10), slip=0.01)
    s = 5 * size + 5  # an interior cell: 0.99 to the intended neighbour, 0.01 / 3 to each other one
    for a, (dr, dc) in enumerate(MOVES):
        assert T[s, a, (5 + dr) * size + 5 + dc] == pytest.approx(0.99)
        others = [(5 + r) * size + 5 + c for b, (r, c) in enumerate(MOVES) if b != a]
        np.testing.assert_allclose(T[s, a, others], 0.01 / 3)
    # the top-left corner: "up" hits the wall (0.99) and "left" slips into the other wall (0.01 / 3)
    assert T[0, 0, 0] == pytest.approx(0.99 + 0.01 / 3)
    assert T[0, 0, 1] == pytest.approx(0.01 / 3) and T[0, 0, size] == pytest.approx(0.01 / 3)


def test_goal_reward_and_absorbing_state(grid):
    mdp, goal, absorbing = grid.mdp, grid.cell(5, 10), grid.absorbing
    np.testing.assert_array_equal(mdp.transition[goal, :, absorbing], 1.0)
    np.testing.assert_array_equal(mdp.transition[absorbing, :, absorbing], 1.0)
    expected = np.zeros_like(mdp.reward)
    expected[goal] = 1.0
    np.testing.assert_array_equal(mdp.reward, expected)
    # Going straight there (along the middle row) takes 10 steps: reward (1 - g) g^10 without slips, a little
    # less with them.
    d = make_demonstrators(grid).d_mdp
    assert 0.97 * 0.05 * 0.95**10 < (d * mdp.reward).sum() <= 0.05 * 0.95**10


@pytest.mark.parametrize(("layout", "n_zones"), [("across", 4), ("along", 3)])
def test_zones_lie_on_the_diagonal_and_spare_start_and_goal(layout, n_zones):
    corners = [(0, 0), (0, 10), (10, 0), (10, 10)]
    for seed in range(20):
        grid = make_gridworld(seed, layout=layout)
        assert len(set(grid.zone_centers)) == n_zones and all(2 <= k <= 8 for k in grid.zone_centers)
        np.testing.assert_array_equal(grid.zone, zone_cells(11, grid.zone_centers))
        keep = [grid.cell(*c) for c in [grid.start, grid.goal, *corners]] + [grid.absorbing]
        assert not grid.zone[keep].any()
        assert grid.zone.sum() >= 9
    assert make_gridworld(3).zone_centers == make_gridworld(3).zone_centers  # deterministic per seed
    assert len({make_gridworld(s).zone_centers for s in range(10)}) > 3


def test_along_layout_is_the_layout_before():
    """layout="along" reproduces the earlier default: start and goal at the diagonal's ends, 3 zones (the same
    centres per seed), and a cost-free edge route as short as the diagonal one (no trade-off)."""
    assert LAYOUTS["along"](11) == ((0, 0), (10, 10), 3)
    assert zone_candidates(11, (0, 0), (10, 10)) == list(range(2, 9))
    assert [make_gridworld(s, layout="along").zone_centers for s in range(3)] == [
        (5, 6, 8),
        (4, 5, 7),
        (2, 3, 6),
    ]
    for seed in range(10):
        assert route_lengths(make_gridworld(seed, layout="along")) == (20, 20)
    with pytest.raises(ValueError, match="layout"):
        make_gridworld(0, layout="nonsense")


def test_across_layout_lengthens_every_cost_free_route():
    """In the default layout the zones block the middle row in every one of seeds 0 .. 49: the shortest
    cost-free route is 2 .. 10 moves longer than the shortest route (10 moves)."""
    extra = []
    for seed in range(50):
        shortest, safe = route_lengths(make_gridworld(seed))
        assert shortest == 10 and safe is not None
        extra.append(safe - shortest)
    assert min(extra) >= 2 and max(extra) <= 10
    # the single layout of 35 that leaves the middle row free has no trade-off
    free = dataclasses.replace(
        make_gridworld(0), zone_centers=(2, 3, 7, 8), zone=zone_cells(11, (2, 3, 7, 8))
    )
    assert route_lengths(free) == (10, 10)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_across_layout_has_a_return_safety_trade_off(seed):
    """d*_M walks through a zone (infeasible) and the CMDP optimum's return is strictly below d*_M's."""
    grid = make_gridworld(seed)
    demo = make_demonstrators(grid)
    r_m, c_m = evaluate(grid.mdp, demo.d_mdp)
    r_c, c_c = evaluate(grid.mdp, demo.d_cmdp)
    assert not is_feasible(c_m, grid.cost_limit) and c_m > 100 * grid.cost_limit
    assert is_feasible(c_c, grid.cost_limit)
    # at least two extra moves: about a factor 0.95^2 on the return
    assert r_c < 0.95 * r_m
    assert normalized_return(r_m, demo.random_return, demo.optimal_return) > 1.1


def test_crossing_cost_rule(grid):
    mdp, zone, size = grid.mdp, grid.zone, grid.size
    for row in range(size):
        for col in range(size):
            s = grid.cell(row, col)
            for a, (dr, dc) in enumerate(MOVES):
                r, c = row + dr, col + dc
                target = grid.cell(r, c) if 0 <= r < size and 0 <= c < size else s
                if s == grid.cell(*grid.goal):
                    target = grid.absorbing
                assert mdp.cost[s, a] == float(zone[target] and not zone[s]), (row, col, a)
    assert mdp.cost[grid.absorbing].sum() == 0.0


def test_transition_cost_rule():
    grid = make_gridworld(0, cost_model="transition")
    T, zone = grid.mdp.transition, grid.zone
    expected = T[:, :, zone].sum(-1) * ~zone[:, None]
    np.testing.assert_allclose(grid.mdp.cost, expected)
    # next to a zone, every action of an outside cell costs at least one slip
    k = grid.zone_centers[0]
    assert grid.mdp.cost[grid.cell(k - 2, k)].min() >= 0.01 / 3 - 1e-15
    with pytest.raises(ValueError, match="cost_model"):
        make_gridworld(0, cost_model="nonsense")


def test_safe_random_policy_never_chooses_to_enter(grid):
    pi = safe_random_policy(grid)
    np.testing.assert_allclose(pi.sum(1), 1.0)
    assert (pi * grid.mdp.cost).sum() == 0.0  # never picks a crossing move
    d0 = occupancy(grid.mdp, pi)
    assert evaluate(grid.mdp, d0)[1] == 0.0  # so its cost is exactly 0 under the crossing model


def test_demonstrators(grid, demo):
    mdp = grid.mdp
    for d in (demo.d_mdp, demo.d_cmdp, demo.d_random):
        assert np.abs(flow_residual(mdp, d)).max() < 1e-6
    r_m, c_m = (demo.d_mdp * mdp.reward).sum(), (demo.d_mdp * mdp.cost).sum()
    r_c, c_c = (demo.d_cmdp * mdp.reward).sum(), (demo.d_cmdp * mdp.cost).sum()
    assert r_m >= r_c - 1e-12 and c_c <= grid.cost_limit * (1 + 1e-9)
    assert c_m > 100 * grid.cost_limit  # seed 0's unconstrained optimum walks through a zone
    assert demo.optimal_return == pytest.approx(r_c) and demo.random_return < r_c


def test_demonstration_mixtures(demo):
    d_P = performant_distribution(demo.d_mdp, demo.d_cmdp, 0.3)
    np.testing.assert_allclose(d_P, 0.7 * demo.d_mdp + 0.3 * demo.d_cmdp)
    d_S = safe_distribution(demo.d_cmdp, demo.d_random, 0.9)
    np.testing.assert_allclose(d_S, 0.9 * demo.d_cmdp + 0.1 * demo.d_random)
    with pytest.raises(ValueError, match="safeness"):
        performant_distribution(demo.d_mdp, demo.d_cmdp, 1.5)
    with pytest.raises(ValueError, match="performance"):
        safe_distribution(demo.d_cmdp, demo.d_random, -0.1)


def test_selection_rule():
    limit = 1e-4
    cands = [
        {"h": "unsafe", "return": 0.9, "cost": 5e-4},
        {"h": "safe-low", "return": 0.2, "cost": 0.0},
        {"h": "safe-high", "return": 0.6, "cost": 1e-4},
    ]
    assert select_candidate(cands, limit)["h"] == "safe-high"
    picked = select_candidate([cands[0], {"h": "less", "return": 0.1, "cost": 2e-4}], limit)
    assert picked["h"] == "less" and picked["feasible"] is False
    with pytest.raises(ValueError):
        select_candidate([], limit)
    assert is_feasible(limit * (1 + 1e-9), limit) and not is_feasible(limit * 1.001, limit)


def test_normalisations():
    """protocol.normalise is spoil_torchrl.eval's normalized_return / normalized_cost; the mean and standard error
    over seeds is eval's mean_stderr (nan for a single seed)."""
    scale = {"random_return": 0.2, "optimal_return": 0.6, "cost_limit": 1e-4}
    assert normalise(0.2, 0.0, **scale) == {"normalised_return": 0.0, "normalised_cost": 0.0}
    out = normalise(0.6, 3e-4, **scale)
    assert out["normalised_return"] == 1.0 and out["normalised_cost"] == pytest.approx(3.0)
    with pytest.raises(ValueError, match="CMDP optimum"):
        normalise(0.1, 0.0, random_return=0.5, optimal_return=0.5, cost_limit=1e-4)
    mean, se = mean_stderr(torch.tensor([1.0, 2.0, 3.0]))
    assert mean == 2.0 and se == pytest.approx(1.0 / np.sqrt(3))
    assert np.isnan(mean_stderr(torch.tensor([1.0]))[1])


def test_slip_where_the_chosen_move_is_not_the_likeliest_is_rejected():
    import pytest

    from spoil_torchrl.tabular.gridworld import grid_transition

    with pytest.raises(ValueError, match="slip must lie in"):
        grid_transition(3, goal=(2, 2), slip=0.8)
