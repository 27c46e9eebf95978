"""Boundaries and determinism of the labelling and metrics: tests written against the survivors of a mutation
run (docs/mutation.md lists what each one guards)."""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict

from spoil_torchrl.data.labeling import (
    controlled_mix,
    corrupt,
    draw,
    ilsp_return_threshold,
    replay_subsets,
    stats_table,
)
from spoil_torchrl.eval import aggregate_over_seeds, episode_metrics, mean_of_last


def _stats(returns, costs):
    return TensorDict({"return": torch.tensor(returns), "cost": torch.tensor(costs)}, [len(returns)])


def test_draw_accepts_zero_and_all_and_refuses_more():
    ids = torch.arange(5)
    assert draw(ids, 0, seed=0).numel() == 0
    assert sorted(draw(ids, 5, seed=0).tolist()) == [0, 1, 2, 3, 4]
    with pytest.raises(ValueError, match="cannot draw 6"):
        draw(ids, 6, seed=0)
    assert draw([3, 1, 2], 3, seed=0).dtype == torch.int64


def test_return_quantile_zero_is_the_lowest_safe_return():
    stats = _stats([5.0, 2.0, 9.0, 50.0], [0.0, 1.0, 3.0, 99.0])
    assert ilsp_return_threshold(stats, cost_threshold=3.0, return_quantile=0.0) == 2.0


def test_stats_table_thresholds_are_inclusive_and_empty_roles_are_listed():
    stats = _stats([1.0, 3.0, 2.0], [5.0, 9.0, 0.0])  # episode 0 at the cost bound, 2 at the return bound
    table = stats_table(stats, {"all": torch.tensor([0, 1, 2]), "none": [], "last": [2]}, 5.0, 2.0)
    rows = table.splitlines()
    assert rows[0].startswith("| dataset | safe ratio") and rows[1] == "|---|---|---|---|---|"
    assert rows[2] == "| all | 0.67 | 0.67 | 0.33 | 3 |"
    assert rows[3] == "| none | - | - | - | 0 |" and rows[4] == "| last | 1.00 | 1.00 | 1.00 | 1 |"


def test_replay_subsets_thresholds_are_inclusive():
    stats = _stats([9.0, 10.0, 3.0], [4.0, 7.0, 0.0])
    roles = replay_subsets(stats, cost_threshold=4.0, safe_optimal_return=10.0, return_fraction=0.9)
    assert roles["safe"].tolist() == [0, 2] and roles["performant"].tolist() == [0, 1]


def _pools():
    return {
        "safe-high": torch.arange(0, 10),
        "safe-medium": torch.arange(10, 20),
        "unsafe-high": torch.arange(20, 30),
        "unsafe-medium": torch.arange(30, 40),
    }


def test_controlled_mix_is_seeded_and_splits_a_remainder_over_the_first_pools():
    kwargs = dict(n_safe=4, performance=0.5, n_performant=4, safeness=0.25, n_unlabeled=7)
    a, b = controlled_mix(_pools(), **kwargs, seed=3), controlled_mix(_pools(), **kwargs, seed=3)
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert any(not torch.equal(a[k], controlled_mix(_pools(), **kwargs, seed=4)[k]) for k in a)
    assert not torch.equal(controlled_mix(_pools(), **kwargs)["safe"], a["safe"])  # default seed 0
    per_pool = [int(((a["unlabeled"] >= lo) & (a["unlabeled"] < lo + 10)).sum()) for lo in (0, 10, 20, 30)]
    assert per_pool == [2, 2, 2, 1]
    assert a["unlabeled"].dtype == torch.int64
    with pytest.raises(ValueError, match="pool 'safe-high' has 10 trajectories, 12 are needed"):
        controlled_mix(_pools(), n_safe=10, performance=1.0, n_performant=2, safeness=1.0)
    with pytest.raises(ValueError, match="n_unlabeled=41"):
        controlled_mix(_pools(), n_safe=1, performance=1.0, n_performant=1, safeness=0.0, n_unlabeled=41)
    with pytest.raises(ValueError, match="safeness"):
        controlled_mix(_pools(), n_safe=1, performance=1.0, n_performant=1, safeness=1.5)


def test_corrupt_is_seeded():
    safe, unsafe = torch.arange(10), torch.arange(100, 120)
    assert torch.equal(corrupt(safe, unsafe, 0.3, seed=1), corrupt(safe, unsafe, 0.3, seed=1))
    assert not torch.equal(corrupt(safe, unsafe, 0.3, seed=1), corrupt(safe, unsafe, 0.3, seed=2))
    with pytest.raises(ValueError, match="rate"):
        corrupt(safe, unsafe, 1.5)


def test_mean_of_last_accepts_one_and_a_column():
    assert mean_of_last([1.0, 2.0, 4.0], last=1) == 4.0
    assert mean_of_last(torch.tensor([[1.0], [3.0]]), last=2) == 2.0
    with pytest.raises(ValueError, match="smaller `last`"):
        mean_of_last([1.0], last=2)


def test_two_seeds_have_a_standard_error():
    agg = aggregate_over_seeds([[1.0], [3.0]], last=1)
    assert agg.stderr == pytest.approx(math.sqrt(2.0) / math.sqrt(2.0))
    assert math.isnan(aggregate_over_seeds([[1.0]], last=1).stderr)


def test_episode_metrics_reads_a_trailing_singleton_mask_and_names_a_bad_row():
    td = TensorDict(
        {
            "next": {"reward": torch.ones(2, 3, 1), "cost": torch.zeros(2, 3, 1)},
            "mask": torch.tensor([[True, True, False], [True, True, True]]).unsqueeze(-1),
        },
        [2, 3],
    )
    metrics = episode_metrics(td, cost_threshold=1.0)
    assert metrics["length"].tolist() == [2, 3] and metrics["length"].dtype == torch.int64
    assert metrics["return"].tolist() == [2.0, 3.0]
    td["mask"] = torch.tensor([[True, True, True], [True, False, True]]).unsqueeze(-1)
    with pytest.raises(ValueError, match="episode row 1 is not a prefix"):
        episode_metrics(td, cost_threshold=1.0)
    td["mask"] = torch.ones(2, 3, 2, dtype=torch.bool)
    with pytest.raises(ValueError, match=r"shape \[episodes, steps\]; got \[2, 3, 2\]"):
        episode_metrics(td[:, :], cost_threshold=1.0)
