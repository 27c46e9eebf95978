"""Collection: rollouts in the real simulator, atomic DSRL files with segment metadata, generated datasets."""

from __future__ import annotations

import importlib.util
import json

import h5py
import numpy as np
import pytest
import torch

from spoil_torchrl.data import (
    DatasetError,
    Segment,
    collect,
    load_episodes,
    read_metadata,
    segment_pools,
)
from spoil_torchrl.data import generated as generated_module
from spoil_torchrl.data.hdf5 import METADATA_ATTR
from spoil_torchrl.envs.rollout import rollout
from spoil_torchrl.stack import current_stack
from spoil_torchrl.zoo import zoo_policy
from spoil_torchrl.zoo.policy_files import load_policy

# the package re-exports the function collect(), which hides the module of the same name
collect_module = importlib.import_module("spoil_torchrl.data.collect")
pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("safety_gymnasium") is None, reason="safety-gymnasium not installed (EXTRAS=dev)"
)
ENV = "SafetyPointCircle1-v0"


@pytest.fixture(scope="module")
def policy():
    return load_policy(zoo_policy(ENV, "unsafe-high"), env_id=ENV)[0]


def test_rollout_layout(policy):
    arrays = rollout(ENV, policy, 3, seed=0, num_envs=2, progress=False)
    n = 3 * 500
    assert arrays["observations"].shape == (n, 28) and arrays["actions"].shape == (n, 2)
    assert arrays["observations"].dtype == np.float32 and arrays["terminals"].dtype == bool
    # PointCircle1 never terminates; it is truncated every 500 steps
    assert not arrays["terminals"].any()
    np.testing.assert_array_equal(np.flatnonzero(arrays["timeouts"]), [499, 999, 1499])
    # within an episode the next observation is the following observation; at a time limit it is the real
    # next state, not the next episode's reset observation
    np.testing.assert_array_equal(arrays["next_observations"][:499], arrays["observations"][1:500])
    assert not np.array_equal(arrays["next_observations"][499], arrays["observations"][500])
    assert set(np.unique(arrays["costs"])) <= {0.0, 1.0}
    assert np.abs(arrays["actions"]).max() <= 1.0
    # the unconstrained expert runs outside the circle's safe band: it must pay cost
    assert arrays["costs"].sum() > 50


def test_rollout_is_deterministic_by_seed(policy):
    a = rollout(ENV, policy, 2, seed=3, num_envs=2, progress=False)
    b = rollout(ENV, policy, 2, seed=3, num_envs=2, progress=False)
    c = rollout(ENV, policy, 2, seed=4, num_envs=2, progress=False)
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])
    assert not np.array_equal(a["actions"], c["actions"])


def test_deterministic_actions_differ_from_sampled(policy):
    sampled = rollout(ENV, policy, 1, seed=0, progress=False)
    greedy = rollout(ENV, policy, 1, seed=0, progress=False, deterministic=True)
    np.testing.assert_array_equal(sampled["observations"][0], greedy["observations"][0])
    assert not np.array_equal(sampled["actions"], greedy["actions"])


def test_random_policy_and_bad_arguments():
    arrays = rollout(ENV, None, 1, seed=0, progress=False)
    assert arrays["rewards"].shape == (500,) and np.abs(arrays["actions"]).max() <= 1.0
    with pytest.raises(ValueError, match="episodes"):
        rollout(ENV, None, 0, seed=0)
    with pytest.raises(ValueError, match="episodes"):
        Segment("x", "random", 0)


def test_collect_writes_a_loadable_file_with_segments(tmp_path):
    segments = [Segment("safe-high", "zoo:safe-high", 2), Segment("random", "random", 1)]
    torch.manual_seed(0)
    before = torch.get_rng_state()
    path = collect(
        ENV, segments, tmp_path / "d.hdf5", seed=1, num_envs=2, reference_episodes=1, progress=False
    )
    # making a dataset leaves the caller's generator alone: a run that makes its data first trains from the
    # same initial weights as one that finds them cached
    assert torch.equal(torch.get_rng_state(), before)
    meta = read_metadata(path)
    assert meta["env_id"] == ENV and meta["cost_threshold"] == 25.0 and meta["steps"] == 1500
    assert meta["safe_high_return"] > 20 > meta["random_return"]
    pools = segment_pools(meta)
    assert {k: v.tolist() for k, v in pools.items()} == {"safe-high": [0, 1], "random": [2]}
    episodes = load_episodes(f"file:{path}")
    assert int(episodes["episode"].max()) == 2 and episodes.shape[0] == 1500
    returns = torch.zeros(3, dtype=torch.float64).index_add_(
        0, episodes["episode"], episodes["next", "reward"].reshape(-1).double()
    )
    assert abs(float(returns[:2].mean()) - meta["segments"][0]["mean_return"]) < 1e-3


def test_interrupted_collection_leaves_no_file(tmp_path, monkeypatch):
    calls = []
    real = collect_module.rollout

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(collect_module, "rollout", failing)
    target = tmp_path / "d.hdf5"
    with pytest.raises(KeyboardInterrupt):
        collect(ENV, [Segment("a", "random", 1), Segment("b", "random", 1)], target, progress=False)
    assert list(tmp_path.iterdir()) == []


def test_a_write_killed_midway_leaves_no_file(tmp_path, monkeypatch):
    import h5py

    real = h5py.Group.create_dataset
    written = []

    def failing(self, name, *args, **kwargs):
        written.append(name)
        if len(written) == 3:
            raise KeyboardInterrupt  # killed after two arrays are on disk
        return real(self, name, *args, **kwargs)

    monkeypatch.setattr(h5py.Group, "create_dataset", failing)
    with pytest.raises(KeyboardInterrupt):
        collect(ENV, [Segment("a", "random", 1)], tmp_path / "d.hdf5", reference_episodes=1, progress=False)
    assert len(written) == 3 and list(tmp_path.iterdir()) == []


def test_metadata_cannot_override_the_collectors_entries(tmp_path):
    with pytest.raises(ValueError, match="segments"):
        collect(ENV, [Segment("a", "random", 1)], tmp_path / "d.hdf5", metadata={"segments": []})


def test_unknown_zoo_policy_names_the_available_ones():
    with pytest.raises(ValueError, match="available: .*safe-high"):
        collect_module.resolve_policy("zoo:nope", ENV)


def test_ensure_generated_makes_once_then_reuses(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("SPOIL_TORCHRL_DATA_DIR", str(tmp_path))
    tiny = generated_module.GeneratedDataset(
        "tiny", ENV, (Segment("unsafe-medium", "zoo:unsafe-medium", 1),), "test"
    )
    monkeypatch.setitem(generated_module.GENERATED_DATASETS, "tiny", tiny)
    with pytest.raises(DatasetError, match="collect_demos.py name=tiny"):
        load_episodes("generated:tiny")
    made = []
    real = generated_module.collect

    def counting(*args, **kwargs):
        made.append(1)
        return real(*args, **{**kwargs, "reference_episodes": 1})

    monkeypatch.setattr(generated_module, "collect", counting)
    path = generated_module.ensure_generated("tiny", num_envs=1, progress=False)
    assert path == tmp_path / "tiny.hdf5" and read_metadata(path)["name"] == "tiny"
    assert generated_module.ensure_generated("tiny", num_envs=1, progress=False) == path and len(made) == 1
    assert load_episodes("generated:tiny").shape[0] == 500
    # a cached file from another recipe (here: another num_envs) is made again, not silently reused
    generated_module.ensure_generated("tiny", num_envs=2, progress=False)
    assert len(made) == 2 and read_metadata(path)["num_envs"] == 2
    # a cached file made on another software stack is made again, with a line that says why
    assert read_metadata(path)["stack"] == current_stack()
    with h5py.File(path, "r+") as f:
        meta = json.loads(f.attrs[METADATA_ATTR])
        meta["stack"] = dict(meta["stack"], mujoco="0.0.1")  # a simulator this process does not have
        f.attrs[METADATA_ATTR] = json.dumps(meta)
    generated_module.ensure_generated("tiny", num_envs=2, progress=False)
    assert "made on another software stack" in capsys.readouterr().out
    assert len(made) == 3 and read_metadata(path)["stack"] == current_stack()
    with pytest.raises(KeyError, match="point-circle1-mixed"):
        generated_module.get_generated("nope")
