"""IL-SP labels, statistics tables, controlled mixes, corruption and replay subsets against hand counts."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from spoil_torchrl.data import (
    POOLS,
    controlled_mix,
    corrupt,
    draw,
    episode_stats,
    episodes_from_arrays,
    ilsp_return_threshold,
    label_ilsp,
    replay_subsets,
    stats_table,
)
from tests.data.helpers import make_arrays


@pytest.fixture
def episodes():
    # 5 episodes of lengths 2, 3, 1, 2, 2 with per-step rewards / costs chosen so that
    # returns = [2, 6, 10, 4, 8] and costs = [0, 30, 50, 10, 41].
    lengths = (2, 3, 1, 2, 2)
    rewards = [1, 1, 2, 2, 2, 10, 2, 2, 4, 4]
    costs = [0, 0, 10, 10, 10, 50, 5, 5, 40, 1]
    arrays = make_arrays(lengths=lengths, ends=("timeout",) * 5, rewards=rewards, costs=costs)
    return episodes_from_arrays(arrays)


def test_episode_stats(episodes):
    stats = episode_stats(episodes)
    assert stats["return"].tolist() == [2, 6, 10, 4, 8]
    assert stats["cost"].tolist() == [0, 30, 50, 10, 41]
    assert stats["length"].tolist() == [2, 3, 1, 2, 2]


def test_label_ilsp_by_hand(episodes):
    # cost threshold 40: safe = {0 (0), 1 (30), 3 (10)}; safe returns [2, 6, 4] -> 0.9-quantile
    # (linear) = 4 + 0.8 * (6 - 4) = 5.6; performant = return >= 5.6 = {1, 2, 4}.
    labels = label_ilsp(episodes, cost_threshold=40)
    assert ilsp_return_threshold(episode_stats(episodes), 40) == pytest.approx(5.6)
    assert labels["safe"].tolist() == [0, 1, 3]
    assert labels["performant"].tolist() == [1, 2, 4]
    assert labels["nonpreferred"].tolist() == [2, 4]
    assert labels["unlabeled"].tolist() == [0, 1, 2, 3, 4]
    # a cost exactly at the threshold is safe
    assert 1 in label_ilsp(episodes, cost_threshold=30)["safe"].tolist()


def test_label_ilsp_without_safe_episodes_raises(episodes):
    with pytest.raises(ValueError, match="no episode has cost <= -1"):
        label_ilsp(episodes, cost_threshold=-1)
    with pytest.raises(ValueError, match="return_quantile"):
        label_ilsp(episodes, cost_threshold=40, return_quantile=1.5)


def test_stats_table_by_hand(episodes):
    labels = label_ilsp(episodes, cost_threshold=40)
    table = stats_table(episodes, labels, cost_threshold=40, return_threshold=5.6)
    rows = {line.split("|")[1].strip(): line for line in table.splitlines()[2:]}
    # safe {0,1,3}: performant only 1 -> 1/3; performant {1,2,4}: safe only 1 -> 1/3
    assert rows["safe"] == "| safe | 1.00 | 0.33 | 0.33 | 3 |"
    assert rows["performant"] == "| performant | 0.33 | 1.00 | 0.33 | 3 |"
    assert rows["nonpreferred"] == "| nonpreferred | 0.00 | 1.00 | 0.00 | 2 |"
    assert rows["unlabeled"] == "| unlabeled | 0.60 | 0.60 | 0.20 | 5 |"


def test_draw_is_seeded_and_checked():
    a, b = draw(torch.arange(50), 10, seed=3), draw(torch.arange(50), 10, seed=3)
    assert a.tolist() == b.tolist() and len(set(a.tolist())) == 10
    assert draw(torch.arange(50), 10, seed=4).tolist() != a.tolist()
    with pytest.raises(ValueError, match="cannot draw 11"):
        draw(torch.arange(10), 11, seed=0)


def _pools():
    return {name: torch.arange(20) + 100 * i for i, name in enumerate(POOLS)}


@pytest.mark.parametrize(("performance", "safeness"), [(0.05, 0.95), (0.5, 0.5), (1.0, 0.0)])
def test_controlled_mix_shares(performance, safeness):
    mix = controlled_mix(
        _pools(),
        n_safe=20,
        performance=performance,
        n_performant=20,
        safeness=safeness,
        n_unlabeled=40,
        seed=1,
    )
    pool_of = {name: set(ids.tolist()) for name, ids in _pools().items()}
    safe, perf = mix["safe"].tolist(), mix["performant"].tolist()
    assert len(safe) == 20 and len(perf) == 20
    assert sum(i in pool_of["safe-high"] for i in safe) == round(performance * 20)
    assert all(i in pool_of["safe-high"] | pool_of["safe-medium"] for i in safe)
    assert sum(i in pool_of["safe-high"] for i in perf) == round(safeness * 20)
    assert all(i in pool_of["safe-high"] | pool_of["unsafe-high"] for i in perf)
    assert not set(safe) & set(perf)
    unl = mix["unlabeled"].tolist()
    assert len(unl) == 40 and all(sum(i in pool_of[p] for i in unl) == 10 for p in POOLS)


def test_controlled_mix_errors_and_all_unlabeled():
    with pytest.raises(ValueError, match="safe-high"):
        controlled_mix(_pools(), n_safe=20, performance=1.0, n_performant=20, safeness=1.0, seed=0)
    with pytest.raises(ValueError, match="performance"):
        controlled_mix(_pools(), n_safe=2, performance=1.5, n_performant=2, safeness=0.5)
    with pytest.raises(ValueError, match="missing"):
        controlled_mix({"safe-high": torch.arange(3)}, n_safe=1, performance=1, n_performant=1, safeness=0)
    mix = controlled_mix(_pools(), n_safe=2, performance=0.5, n_performant=2, safeness=0.5)
    assert len(mix["unlabeled"]) == 80


def test_corrupt_replaces_the_given_share():
    noisy = corrupt(torch.arange(20), torch.arange(100, 130), rate=0.25, seed=0)
    assert len(noisy) == 20 and int((noisy >= 100).sum()) == 5
    assert corrupt(torch.arange(20), torch.arange(100, 130), rate=0.25, seed=0).tolist() == noisy.tolist()


def test_replay_subsets(episodes):
    subsets = replay_subsets(episodes, cost_threshold=40, safe_optimal_return=6.0)
    assert subsets["safe"].tolist() == [0, 1, 3]
    assert subsets["performant"].tolist() == [1, 2, 4]  # return >= 5.4
    assert subsets["unlabeled"].tolist() == [0, 1, 2, 3, 4]


def test_float64_and_bool_flags_give_the_same_labels():
    base = make_arrays(
        lengths=(2, 3, 1, 2, 2),
        ends=("timeout", "terminal", "timeout", "terminal", "timeout"),
        rewards=np.arange(10),
        costs=np.arange(10) % 3,
    )
    as_bool = dict(base, terminals=base["terminals"].astype(bool), timeouts=base["timeouts"].astype(bool))
    as_f64 = dict(
        base, terminals=base["terminals"].astype(np.float64), timeouts=base["timeouts"].astype(np.float64)
    )
    a, b = label_ilsp(episodes_from_arrays(as_bool), 3), label_ilsp(episodes_from_arrays(as_f64), 3)
    assert all(a[k].tolist() == b[k].tolist() for k in a)


def test_an_episode_at_exactly_the_threshold_is_safe_and_sets_the_return_cut():
    from tensordict import TensorDict

    from spoil_torchrl.data.labeling import ilsp_return_threshold

    # episode 2 has cost == threshold: it is safe (<=), so its high return sets the performant cut
    stats = TensorDict(
        {"return": torch.tensor([1.0, 2.0, 9.0, 20.0]), "cost": torch.tensor([0.0, 3.0, 10.0, 50.0])}, [4]
    )
    assert ilsp_return_threshold(stats, cost_threshold=10.0, return_quantile=1.0) == 9.0
    roles = label_ilsp(stats, cost_threshold=10.0, return_quantile=1.0)
    assert roles["safe"].tolist() == [0, 1, 2] and roles["performant"].tolist() == [2, 3]


def test_controlled_pools_beyond_the_four_join_d_u_only_and_leave_a_four_pool_mix_unchanged():
    pools = {name: torch.arange(10) + 10 * i for i, name in enumerate(POOLS)}
    kwargs = dict(n_safe=4, performance=0.5, n_performant=4, safeness=0.5, seed=3)
    four = controlled_mix(pools, **kwargs, n_unlabeled=8)
    six = controlled_mix(
        pools | {"x": torch.arange(40, 45), "y": torch.arange(45, 50)}, **kwargs, n_unlabeled=12
    )
    assert torch.equal(four["safe"], six["safe"]) and torch.equal(four["performant"], six["performant"])
    assert int((six["unlabeled"] >= 40).sum()) == 4  # two of each extra pool, as of the four
    every = controlled_mix(pools | {"x": torch.arange(40, 45)}, **kwargs)["unlabeled"]
    assert every.tolist() == list(range(45))
