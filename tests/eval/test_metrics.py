"""Evaluation metrics against hand-computed episodes (paper 5.2)."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from spoil_torchrl.eval import (
    aggregate_over_seeds,
    episode_cost,
    episode_metrics,
    episode_return,
    feasible_return,
    mean_of_last,
    normalized_cost,
    normalized_return,
    strict_feasible_return,
)

# One episode, by hand:      t = 0   1   2   3    4
REWARD = torch.tensor([1.0, 2.0, 4.0, 8.0, 16.0])
COST = torch.tensor([0.0, 1.0, 0.0, 2.0, 0.0])  # cumulative cost 0, 1, 1, 3, 3


def test_return_and_cost():
    assert episode_return(REWARD) == 31.0
    assert episode_cost(COST) == 3.0
    assert episode_return(REWARD.unsqueeze(-1)) == 31.0  # TED [T, 1]
    assert episode_return(torch.tensor([])) == 0.0
    with pytest.raises(ValueError, match=r"shape \[T\] or \[T, 1\]"):
        episode_return(torch.ones(2, 3))


def test_feasible_return_threshold_reading():
    # threshold 1: cumulative cost reaches 1 at t=1 (not a violation) and first exceeds it at t=3,
    # so rewards of t = 0, 1, 2 count and the violating step's reward (8) does not.
    assert feasible_return(REWARD, COST, threshold=1.0) == 1 + 2 + 4
    # threshold 3: reached exactly at t=3 but never exceeded -> the whole return.
    assert feasible_return(REWARD, COST, threshold=3.0) == 31.0
    # threshold 2.5: exceeded at t=3 as well.
    assert feasible_return(REWARD, COST, threshold=2.5) == 7.0
    # violation at the very first step: nothing counts.
    assert feasible_return(torch.tensor([5.0, 1.0]), torch.tensor([2.0, 0.0]), threshold=1.0) == 0.0
    # [T, 1] inputs, float64 accumulation.
    assert feasible_return(REWARD[:, None], COST[:, None], 1.0) == 7.0


def test_strict_feasible_return_reading():
    # first positive cost at t=1: only r_0 counts.
    assert strict_feasible_return(REWARD, COST) == 1.0
    assert strict_feasible_return(REWARD, torch.zeros(5)) == 31.0
    assert strict_feasible_return(torch.tensor([3.0]), torch.tensor([0.5])) == 0.0
    # with non-negative costs the strict reading is the threshold reading at threshold 0.
    assert strict_feasible_return(REWARD, COST) == feasible_return(REWARD, COST, threshold=0.0)


def test_feasible_return_zero_threshold():
    assert feasible_return(REWARD, COST, threshold=0.0) == 1.0
    assert feasible_return(REWARD, torch.zeros(5), threshold=0.0) == 31.0


def test_feasible_return_errors():
    with pytest.raises(ValueError, match="one value per step"):
        feasible_return(REWARD, COST[:3], 1.0)
    with pytest.raises(ValueError, match="NaN"):
        feasible_return(REWARD, torch.tensor([0.0, math.nan, 0.0, 0.0, 0.0]), 1.0)
    with pytest.raises(ValueError, match="NaN"):
        strict_feasible_return(REWARD, torch.tensor([0.0, math.nan, 0.0, 0.0, 0.0]))
    with pytest.raises(ValueError, match=">= 0"):
        feasible_return(REWARD, COST, -1.0)


def test_normalized_return():
    assert normalized_return(30.0, min_return=10.0, max_return=50.0) == 0.5
    assert normalized_return(10.0, 10.0, 50.0) == 0.0 and normalized_return(50.0, 10.0, 50.0) == 1.0
    assert normalized_return(-30.0, 10.0, 50.0) == -1.0  # not clipped
    out = normalized_return(torch.tensor([10.0, 30.0, 70.0]), 10.0, 50.0)
    assert torch.allclose(out, torch.tensor([0.0, 0.5, 1.5]))
    for lo, hi in ((5.0, 5.0), (6.0, 5.0), (0.0, math.inf)):
        with pytest.raises(ValueError, match="R_max > R_min"):
            normalized_return(1.0, lo, hi)


def test_normalized_cost():
    assert normalized_cost(15.0, threshold=10.0) == 1.5
    assert normalized_cost(10.0, threshold=10.0) == 1.0  # exactly at the threshold: safe (<= 1)
    # threshold 0: DSRL's (C + 1) / (0 + 1).
    assert normalized_cost(0.0, threshold=0.0) == 1.0
    assert normalized_cost(2.0, threshold=0.0) == 3.0
    out = normalized_cost(torch.tensor([0.0, 5.0]), threshold=0.0)
    assert out.tolist() == [1.0, 6.0]
    for bad in (-1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="threshold"):
            normalized_cost(1.0, bad)


def _padded():
    reward = torch.zeros(3, 5, 1)
    cost = torch.zeros(3, 5, 1)
    mask = torch.zeros(3, 5, dtype=torch.bool)
    episodes = [
        (REWARD, COST),
        (torch.tensor([5.0, 1.0]), torch.tensor([2.0, 0.0])),
        (torch.ones(3), torch.zeros(3)),
    ]
    for e, (r, c) in enumerate(episodes):
        reward[e, : len(r), 0], cost[e, : len(c), 0], mask[e, : len(r)] = r, c, True
    reward[1, 2:] = 100.0  # padding must be ignored
    cost[2, 3:] = 100.0
    return TensorDict({"next": {"reward": reward, "cost": cost}, "mask": mask}, [3, 5]), episodes


def test_episode_metrics_batched():
    td, episodes = _padded()
    m = episode_metrics(td, cost_threshold=1.0, return_range=(0.0, 31.0))
    assert m.batch_size == (3,)
    assert m["length"].tolist() == [5, 2, 3]
    assert m["return"].tolist() == [31.0, 6.0, 3.0]
    assert m["cost"].tolist() == [3.0, 2.0, 0.0]
    assert m["feasible_return"].tolist() == [7.0, 0.0, 3.0]
    assert m["strict_feasible_return"].tolist() == [1.0, 0.0, 3.0]
    assert m["normalized_cost"].tolist() == [3.0, 2.0, 0.0]
    assert m["normalized_return"].tolist() == [1.0, 6 / 31, 3 / 31]
    assert m["normalized_feasible_return"].tolist() == [7 / 31, 0.0, 3 / 31]
    for e, (r, c) in enumerate(episodes):  # the same functions as per episode
        assert m["feasible_return"][e] == feasible_return(r, c, 1.0)
    assert "normalized_return" not in episode_metrics(td, cost_threshold=1.0).keys()


def test_episode_metrics_rejects_bad_masks():
    td, _ = _padded()
    td["mask"][0, 1] = False  # a hole: not a prefix
    with pytest.raises(ValueError, match="row 0 is not a prefix"):
        episode_metrics(td, cost_threshold=1.0)
    with pytest.raises(ValueError, match=r"\[episodes, steps\]"):
        episode_metrics(td[0], cost_threshold=1.0)


def test_mean_of_last_and_aggregate_by_hand():
    # 12 evaluations per seed; the last 10 of each are constant + a ramp whose mean is known.
    seeds = [[100.0, 100.0] + [1.0] * 10, [-5.0, 7.0] + [2.0, 4.0] * 5, [0.0, 0.0] + list(range(10))]
    assert mean_of_last(seeds[0]) == 1.0
    assert mean_of_last(seeds[1]) == 3.0
    assert mean_of_last(seeds[2]) == 4.5
    agg = aggregate_over_seeds(seeds)
    assert agg.per_seed == (1.0, 3.0, 4.5)
    mean = (1.0 + 3.0 + 4.5) / 3
    std = math.sqrt(((1.0 - mean) ** 2 + (3.0 - mean) ** 2 + (4.5 - mean) ** 2) / 2)  # n - 1
    assert agg.mean == pytest.approx(mean, abs=1e-12)
    assert agg.stderr == pytest.approx(std / math.sqrt(3), abs=1e-12)
    assert aggregate_over_seeds(torch.tensor(seeds)).mean == pytest.approx(mean, abs=1e-12)  # [seeds, evals]
    one = aggregate_over_seeds([seeds[0]])
    assert one.mean == 1.0 and math.isnan(one.stderr)


def test_aggregate_errors():
    with pytest.raises(ValueError, match="no seeds"):
        aggregate_over_seeds([])
    with pytest.raises(ValueError, match=r"seed #1: 3 evaluations, fewer than the last=10"):
        aggregate_over_seeds([[0.0] * 10, [0.0] * 3])
    with pytest.raises(ValueError, match="fewer than the last=10"):
        mean_of_last([])
    with pytest.raises(ValueError, match="last must be >= 1"):
        mean_of_last([1.0], last=0)
    assert aggregate_over_seeds([[0.0] * 3, [1.0] * 3], last=3).mean == 0.5


def test_feasible_return_is_robust_to_round_off_in_the_cost_sum():
    import torch

    from spoil_torchrl.eval.metrics import feasible_return

    reward = torch.tensor([1.0, 1.0, 1.0, 1.0])
    cost = torch.tensor([0.1, 0.1, 0.1, 0.1], dtype=torch.float64)  # 0.1 + 0.1 + 0.1 = 0.30000000000000004
    assert feasible_return(reward, cost, threshold=0.3) == 3.0  # exceeded only at the 4th step
