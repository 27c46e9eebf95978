"""From a dataset file to D_S / D_P / D_U, the task and the normalisation constants."""

from __future__ import annotations

import pytest
import torch

from spoil_torchrl.data import POOLS, DatasetError, episode_stats, load_episodes, read_metadata
from spoil_torchrl.data.prepare import prepare_dataset, select_roles

ILSP = {"scheme": "ilsp", "return_quantile": 0.9, "n_safe": 2, "n_performant": 2, "n_unlabeled": None}


def test_ilsp_roles_from_a_collected_file(tiny_pc1_dataset):
    data = prepare_dataset({"source": f"file:{tiny_pc1_dataset}", **ILSP}, env_id="SafetyPointCircle1-v0")
    meta = read_metadata(tiny_pc1_dataset)
    assert data.cost_threshold == 25.0 and data.env_id == "SafetyPointCircle1-v0"
    assert data.return_range == (meta["random_return"], meta["safe_high_return"])
    stats = episode_stats(data.episodes)
    assert bool((stats["cost"][data.roles["safe"]] <= 25.0).all())
    assert data.roles["safe"].numel() == 2 and data.roles["performant"].numel() == 2
    assert data.roles["unlabeled"].tolist() == list(range(12))
    # the same seed gives the same draw; over a few seeds the draws differ
    again = prepare_dataset({"source": f"file:{tiny_pc1_dataset}", **ILSP}, env_id="SafetyPointCircle1-v0")
    assert torch.equal(again.roles["safe"], data.roles["safe"])
    draws = {
        tuple(prepare_dataset({"source": f"file:{tiny_pc1_dataset}", **ILSP}, seed=s).roles["safe"].tolist())
        for s in range(5)
    }
    assert len(draws) > 1
    summary = data.summary()
    assert summary["unlabeled"]["episodes"] == 12 and summary["safe"]["transitions"] == 1000


def test_controlled_roles_use_the_policy_pools(tiny_pc1_dataset):
    cfg = {
        "source": f"file:{tiny_pc1_dataset}",
        "scheme": "controlled",
        "n_safe": 2,
        "n_performant": 2,
        "performance": 0.5,
        "safeness": 0.0,
        "n_unlabeled": 8,
    }
    data = prepare_dataset(cfg, env_id="SafetyPointCircle1-v0", seed=1)
    pools = {p: set(range(3 * i, 3 * i + 3)) for i, p in enumerate(POOLS)}
    assert set(data.roles["performant"].tolist()) <= pools["unsafe-high"]  # safeness 0: all unsafe-high
    assert len(set(data.roles["safe"].tolist()) & pools["safe-high"]) == 1
    assert data.roles["unlabeled"].numel() == 8


def test_nonpreferred_role_only_when_asked(tiny_pc1_dataset):
    source = f"file:{tiny_pc1_dataset}"
    plain = prepare_dataset({"source": source, **ILSP}, env_id="SafetyPointCircle1-v0")
    assert set(plain.roles) == {"safe", "performant", "unlabeled"}
    data = prepare_dataset({"source": source, **ILSP}, extra_roles=("nonpreferred",))
    cost = episode_stats(data.episodes)["cost"]
    unsafe = (cost > data.cost_threshold).nonzero().squeeze(-1)
    assert data.roles["nonpreferred"].tolist() == unsafe.tolist() and unsafe.numel() > 0  # all unsafe of D_U
    assert all(torch.equal(data.roles[r], plain.roles[r]) for r in plain.roles)  # the other draws unchanged
    assert data.summary()["nonpreferred"]["safe_share"] == 0.0
    drawn = prepare_dataset({"source": source, **ILSP, "n_nonpreferred": 2}, extra_roles=("nonpreferred",))
    assert drawn.roles["nonpreferred"].numel() == 2 and set(drawn.roles["nonpreferred"].tolist()) <= set(
        unsafe.tolist()
    )
    # the controlled scheme: the unsafe episodes of its D_U
    controlled = {"scheme": "controlled", "n_safe": 2, "n_performant": 2, "performance": 0.5, "safeness": 0.5}
    mix = prepare_dataset({"source": source, **controlled, "n_unlabeled": 8}, extra_roles=("nonpreferred",))
    assert set(mix.roles["nonpreferred"].tolist()) <= set(mix.roles["unlabeled"].tolist())
    assert bool((cost[mix.roles["nonpreferred"]] > mix.cost_threshold).all())
    with pytest.raises(DatasetError, match="fewer than n_nonpreferred"):
        prepare_dataset({"source": source, **ILSP, "n_nonpreferred": 100}, extra_roles=("nonpreferred",))
    with pytest.raises(DatasetError, match="no unsafe episode"):
        prepare_dataset(
            {"source": source, **ILSP, "cost_threshold": 1e9, "return_range": [0, 1]},
            extra_roles=("nonpreferred",),
        )
    with pytest.raises(ValueError, match="unknown extra roles"):
        prepare_dataset({"source": source, **ILSP}, extra_roles=("expert",))


def test_bad_inputs_give_clear_errors(tiny_pc1_dataset):
    source = f"file:{tiny_pc1_dataset}"
    with pytest.raises(DatasetError, match="recorded in SafetyPointCircle1-v0"):
        prepare_dataset({"source": source, **ILSP}, env_id="SafetyHalfCheetahVelocity-v1")
    with pytest.raises(DatasetError, match="fewer than n_safe=50"):
        prepare_dataset({"source": source, **ILSP, "n_safe": 50})
    with pytest.raises(ValueError, match="unknown labelling scheme"):
        select_roles(load_episodes(source), {"scheme": "magic"}, cost_threshold=25.0, metadata={}, seed=0)
    # an overridden threshold wins over the metadata
    data = prepare_dataset({"source": source, **ILSP, "cost_threshold": 300.0, "return_range": [0, 1]})
    assert data.cost_threshold == 300.0 and data.return_range == (0.0, 1.0)


def _typed_episodes(costs):
    """One transition per episode, the episode's whole cost on it, four pools of equal size in POOLS order."""
    from tensordict import TensorDict

    n = len(costs)
    episodes = TensorDict(
        {
            "episode": torch.arange(n),
            "next": {"reward": torch.ones(n, 1), "cost": torch.tensor(costs, dtype=torch.float32)[:, None]},
        },
        [n],
    )
    size = n // 4
    segments = [{"label": p, "start": i * size, "stop": (i + 1) * size} for i, p in enumerate(POOLS)]
    return episodes, {"segments": segments}


def test_controlled_roles_draw_safe_types_within_the_limit_and_unsafe_types_over_it():
    # safe-high 0-9 with 3 episodes over the limit, safe-medium 10-19 with 2, unsafe-high 20-29 with 1 within it
    costs = [0.0] * 40
    for i in (1, 4, 7, 12, 15):
        costs[i] = 60.0
    for i in range(20, 40):
        costs[i] = 0.0 if i == 23 else 200.0
    episodes, metadata = _typed_episodes(costs)
    cfg = {
        "source": "file:typed.hdf5",
        "scheme": "controlled",
        "n_safe": 8,
        "n_performant": 10,
        "performance": 0.5,
        "safeness": 0.3,
    }
    cost = torch.tensor(costs)
    unsafe_high_within = 0
    for seed in range(20):
        roles = select_roles(episodes, cfg, cost_threshold=25.0, metadata=metadata, seed=seed)
        assert bool((cost[roles["safe"]] <= 25.0).all()), seed  # D_S: safe demonstrations only
        performant = roles["performant"]
        assert int((cost[performant] <= 25.0).sum()) == 3  # safeness 0.3 of 10 is exactly the safe share
        unsafe_high_within += int((performant == 23).sum())
        assert roles["unlabeled"].tolist() == list(
            range(40)
        )  # D_U keeps every episode, over the limit or not
    assert unsafe_high_within == 0
    # a pool with too few episodes within the limit says so
    with pytest.raises(DatasetError, match="'safe-high' has 7 trajectories within the cost limit 25.0, 8"):
        select_roles(
            episodes,
            {**cfg, "performance": 1.0, "safeness": 0.0},
            cost_threshold=25.0,
            metadata=metadata,
            seed=0,
        )


def test_controlled_draw_is_unchanged_where_no_episode_is_over_the_limit():
    """Restricting the pools skips episodes in the same shuffled order, so a draw that held none is unchanged."""
    from spoil_torchrl.data import controlled_mix

    pools = {p: torch.arange(10) + 10 * i for i, p in enumerate(POOLS)}
    kwargs = dict(n_safe=4, performance=0.5, n_performant=4, safeness=0.5, n_unlabeled=12)
    for seed in range(5):
        plain = controlled_mix(pools, **kwargs, seed=seed)
        # every safe-high / safe-medium episode the draw did not take goes over the limit (and one unsafe-high
        # episode it did not take stays within it): filtering before the shuffle would change the draw
        cost = torch.cat([torch.zeros(20), torch.full((20,), 100.0)])
        taken = torch.cat([plain["safe"], plain["performant"]])
        untaken_safe = [i for i in range(20) if i not in taken.tolist()]
        cost[untaken_safe] = 60.0
        cost[next(i for i in range(20, 30) if i not in taken.tolist())] = 0.0
        limited = controlled_mix(pools, **kwargs, seed=seed, episode_cost=cost, cost_limit=25.0)
        assert all(torch.equal(plain[k], limited[k]) for k in plain), seed
    with pytest.raises(ValueError, match="together"):
        controlled_mix(pools, **kwargs, episode_cost=torch.zeros(40))


def test_corruption_replaces_a_share_of_d_s_by_unsafe_episodes_outside_d_s_and_d_p():
    costs = [0.0] * 20 + [200.0] * 20  # safe types within the limit, unsafe types over it
    episodes, metadata = _typed_episodes(costs)
    cfg = {
        "source": "file:typed.hdf5",
        "scheme": "controlled",
        "n_safe": 10,
        "n_performant": 4,
        "performance": 0.5,
        "safeness": 0.5,
    }
    cost = torch.tensor(costs)
    clean = select_roles(episodes, cfg, cost_threshold=25.0, metadata=metadata, seed=3)
    noisy = select_roles(episodes, {**cfg, "corruption": 0.3}, cost_threshold=25.0, metadata=metadata, seed=3)
    assert noisy["safe"].numel() == 10 and int((cost[noisy["safe"]] > 25.0).sum()) == 3
    assert len(set(noisy["safe"].tolist()) & set(clean["safe"].tolist())) == 7  # 7 of the clean D_S kept
    assert not set(noisy["safe"].tolist()) & set(noisy["performant"].tolist())
    assert torch.equal(noisy["performant"], clean["performant"]) and torch.equal(
        noisy["unlabeled"], clean["unlabeled"]
    )
    again = select_roles(episodes, {**cfg, "corruption": 0.3}, cost_threshold=25.0, metadata=metadata, seed=3)
    assert torch.equal(again["safe"], noisy["safe"])
    for rate in (-0.1, 1.0):
        with pytest.raises(DatasetError, match="expected a share in"):
            select_roles(
                episodes, {**cfg, "corruption": rate}, cost_threshold=25.0, metadata=metadata, seed=3
            )
    with pytest.raises(DatasetError, match="unsafe episodes outside D_S and D_P"):
        select_roles(
            episodes,
            {**cfg, "corruption": 0.5, "n_unlabeled": 8},
            cost_threshold=25.0,
            metadata=metadata,
            seed=3,
        )
