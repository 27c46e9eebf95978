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
