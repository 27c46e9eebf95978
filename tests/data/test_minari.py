"""Minari both ways: ours -> Minari -> ours round trips, Minari's own datasets, errors, the stored-roles scheme."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import spoil_torchrl  # noqa: F401 - first, so that importing minari prints no gymnasium-robotics notice
from spoil_torchrl.data import (
    DatasetError,
    load_episodes,
    read_source_metadata,
    select_episodes,
    write_dsrl_file,
)
from spoil_torchrl.data.prepare import prepare_dataset
from tests.data.helpers import make_arrays

minari = pytest.importorskip("minari")
from spoil_torchrl.data.minari_export import write_minari  # noqa: E402
from spoil_torchrl.data.minari_io import read_minari_roles  # noqa: E402

LENGTHS = (3, 2, 4, 5, 1, 2)
ENDS = ("timeout", "terminal", "timeout", "terminal", "timeout", "timeout")
SEGMENTS = [
    {"label": "safe-high", "policy": "zoo:safe-high", "episodes": 2, "start": 0, "stop": 2},
    {"label": "safe-medium", "policy": "zoo:safe-medium", "episodes": 1, "start": 2, "stop": 3},
    {"label": "unsafe-high", "policy": "zoo:unsafe-high", "episodes": 2, "start": 3, "stop": 5},
    {"label": "unsafe-medium", "policy": "zoo:unsafe-medium", "episodes": 1, "start": 5, "stop": 6},
]
METADATA = {
    "env_id": "SafetyPointCircle1-v0",
    "cost_threshold": 25.0,
    "segments": SEGMENTS,
    "random_return": 0.0,
    "safe_high_return": 50.0,
    "name": "tiny",
}


@pytest.fixture(autouse=True)
def minari_home(tmp_path, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path / "minari"))
    return tmp_path / "minari"


@pytest.fixture
def dsrl_file(tmp_path):
    rng = np.random.default_rng(0)
    n = sum(LENGTHS)
    arrays = make_arrays(LENGTHS, ENDS, obs_dim=28, rewards=rng.normal(size=n), costs=rng.integers(0, 3, n))
    arrays["observations"] = arrays["observations"] + rng.normal(size=arrays["observations"].shape)
    arrays["next_observations"] = np.concatenate(
        [arrays["observations"][1:], arrays["observations"][-1:] + 1]
    )
    return write_dsrl_file(tmp_path / "tiny.hdf5", arrays, metadata=METADATA)


def test_round_trip_gives_identical_episodes_and_metadata(dsrl_file):
    ours = load_episodes(f"file:{dsrl_file}")
    roles = {"safe": torch.tensor([0, 1]), "performant": torch.tensor([2, 3]), "unlabeled": torch.arange(6)}
    dataset = write_minari(ours, "test/tiny-v0", metadata=METADATA, roles=roles, return_range=(0.0, 50.0))
    assert dataset.total_episodes == len(LENGTHS) and dataset.total_steps == sum(LENGTHS)

    back = load_episodes("minari:test/tiny-v0")
    assert set(back.keys(True, True)) == set(ours.keys(True, True))
    for key in ours.keys(True, True):
        assert torch.equal(back[key], ours[key]), key
    meta = read_source_metadata("minari:test/tiny-v0")
    assert meta["segments"] == SEGMENTS and meta["env_id"] == METADATA["env_id"]
    assert meta["return_range"] == [0.0, 50.0] and meta["cost_threshold"] == 25.0
    assert meta["roles"] == {name: ids.tolist() for name, ids in roles.items()}
    # what other tools see: Minari's layout, the cost in infos (DataCollector layout), the episode metadata
    episode = minari.load_dataset("test/tiny-v0")[2]
    assert episode.observations.shape == (LENGTHS[2] + 1, 28) and episode.rewards.shape == (LENGTHS[2],)
    assert episode.infos["cost"][0] == 0 and np.array_equal(
        episode.infos["cost"][1:], ours["next", "cost"][ours["episode"] == 2].reshape(-1).numpy()
    )
    assert "next_observation" not in episode.infos  # consistent data needs no copy of the next observations
    entry = next(iter(dataset.storage.get_episode_metadata([2])))
    assert entry["policy_type"] == "safe-medium" and entry["role_performant"] and not entry["role_safe"]
    assert minari.get_normalized_score(dataset, np.array([25.0])) == pytest.approx(0.5)


def test_subset_keeps_policy_types_and_inconsistent_next_observations(dsrl_file):
    ours = load_episodes(f"file:{dsrl_file}")
    subset = select_episodes(ours, [1, 3, 4])
    subset["next", "observation"][0] += 7.0  # a next observation that is not the following observation
    write_minari(subset, "test/subset-v0", metadata=METADATA, roles={"safe": torch.tensor([3])})
    back = load_episodes("minari:test/subset-v0")
    assert torch.equal(back["next", "observation"], subset["next", "observation"])
    assert torch.equal(back["observation"], subset["observation"])
    assert back["episode"].unique().tolist() == [0, 1, 2]  # renumbered 0..n-1
    meta = read_source_metadata("minari:test/subset-v0")
    assert meta["segments"] == [
        {"label": "safe-high", "start": 0, "stop": 1},
        {"label": "unsafe-high", "start": 1, "stop": 3},
    ]
    assert read_minari_roles("test/subset-v0")["safe"].tolist() == [1]


def _minari_dataset(dataset_id, episodes, observation_space=None):
    import gymnasium
    from minari.data_collector.episode_buffer import EpisodeBuffer

    box = gymnasium.spaces.Box(-np.inf, np.inf, shape=(2,), dtype=np.float32)
    buffers = [EpisodeBuffer(id=k, **episode) for k, episode in enumerate(episodes)]
    with pytest.warns(UserWarning):  # Minari's advice to name an author etc.
        return minari.create_dataset_from_buffers(
            dataset_id, buffers, observation_space=observation_space or box, action_space=box
        )


def _episode(n, *, cost_rows=None, terminated=False, truncated=True):
    ends = np.zeros(n, bool)
    infos = {} if cost_rows is None else {"cost": np.arange(cost_rows, dtype=np.float32)}
    return {
        "observations": np.arange(2 * (n + 1), dtype=np.float32).reshape(n + 1, 2),
        "actions": np.zeros((n, 2), np.float32),
        "rewards": np.ones(n),
        "terminations": ends | (np.arange(n) == n - 1) & terminated,
        "truncations": ends | (np.arange(n) == n - 1) & truncated,
        "infos": infos,
    }


def test_reads_datasets_written_by_minari_itself():
    # a DataCollector-style cost (T + 1 entries), a per-step one (T entries), and an episode with no end flag
    episodes = [_episode(3, cost_rows=4), _episode(2, cost_rows=2, terminated=True, truncated=False)]
    episodes.append(_episode(2, cost_rows=3, truncated=False))
    _minari_dataset("test/theirs-v0", episodes)
    td = load_episodes("minari:test/theirs-v0")
    assert td["episode"].tolist() == [0, 0, 0, 1, 1, 2, 2]
    assert td["next", "cost"].reshape(-1).tolist() == [1, 2, 3, 0, 1, 1, 2]
    assert td["next", "terminated"].reshape(-1).tolist() == [0, 0, 0, 0, 1, 0, 0]
    assert td["next", "truncated"].reshape(-1).tolist() == [0, 0, 1, 0, 0, 0, 1]  # the cut episode ends
    assert torch.equal(td["next", "observation"][0], td["observation"][1])
    assert read_source_metadata("minari:test/theirs-v0") == {}


def test_refuses_datasets_it_cannot_use(monkeypatch):
    import gymnasium

    _minari_dataset("test/nocost-v0", [_episode(3)])
    with pytest.raises(DatasetError, match=r"minari:test/nocost-v0: episode 0 has no infos\['cost'\]"):
        load_episodes("minari:test/nocost-v0")
    _minari_dataset("test/badcost-v0", [_episode(3, cost_rows=7)])
    with pytest.raises(DatasetError, match=r"infos\['cost'\] has 7 rows for an episode of 3 steps"):
        load_episodes("minari:test/badcost-v0")
    space = gymnasium.spaces.Dict({"x": gymnasium.spaces.Box(-1, 1, shape=(2,))})
    episode = _episode(2, cost_rows=3)
    episode["observations"] = {"x": episode["observations"]}
    _minari_dataset("test/dict-v0", [episode], observation_space=space)
    with pytest.raises(DatasetError, match="the observation space is Dict; only Box spaces are supported"):
        load_episodes("minari:test/dict-v0")

    def offline(dataset_id, force_download=False):
        raise ConnectionError("no network")

    monkeypatch.setattr(minari, "download_dataset", offline)
    with pytest.raises(DatasetError, match=r"'nobody/nothing-v0' is not in .* could not be downloaded"):
        load_episodes("minari:nobody/nothing-v0")


def test_export_refuses_to_overwrite_unless_asked(dsrl_file):
    ours = load_episodes(f"file:{dsrl_file}")
    write_minari(ours, "test/twice-v0")
    with pytest.raises(FileExistsError, match="already exists"):
        write_minari(ours, "test/twice-v0")
    write_minari(select_episodes(ours, [0]), "test/twice-v0", overwrite=True)
    assert load_episodes("minari:test/twice-v0")["episode"].unique().tolist() == [0]


def test_prepare_dataset_uses_stored_roles_and_policy_pools(dsrl_file):
    controlled = {"source": f"file:{dsrl_file}", "scheme": "controlled", "n_safe": 1, "n_performant": 2}
    controlled.update(performance=0.0, safeness=1.0, n_unlabeled=None)
    ours = prepare_dataset(controlled, env_id="SafetyPointCircle1-v0", seed=3)
    write_minari(ours.episodes, "test/roles-v0", metadata=ours.metadata, roles=ours.roles)
    stored = prepare_dataset({"source": "minari:test/roles-v0", "scheme": "stored"}, seed=99)
    assert {k: v.tolist() for k, v in stored.roles.items()} == {k: v.tolist() for k, v in ours.roles.items()}
    assert stored.env_id == "SafetyPointCircle1-v0" and stored.cost_threshold == 25.0
    assert stored.return_range == (0.0, 50.0)  # from the exported random / safe-high returns
    # the policy-type pools travel too: the controlled scheme draws the same roles from the Minari copy
    again = prepare_dataset(
        {**controlled, "source": "minari:test/roles-v0"}, env_id="SafetyPointCircle1-v0", seed=3
    )
    assert {k: v.tolist() for k, v in again.roles.items()} == {k: v.tolist() for k, v in ours.roles.items()}
    write_minari(ours.episodes, "test/noroles-v0", metadata=ours.metadata)
    with pytest.raises(DatasetError, match="dataset.scheme=stored, but the dataset stores no 'safe' role"):
        prepare_dataset({"source": "minari:test/noroles-v0", "scheme": "stored"}, seed=0)


def test_each_constraints_cost_travels_as_an_info_entry_and_loads_back(tmp_path):
    rng = np.random.default_rng(1)
    n = sum(LENGTHS)
    x, y = rng.integers(0, 2, n).astype(np.float32), rng.integers(0, 2, n).astype(np.float32)
    arrays = make_arrays(LENGTHS, ENDS, obs_dim=28, costs=np.maximum(x, y))
    arrays |= {"cost_x_wall": x, "cost_y_wall": y}
    ours = load_episodes(f"file:{write_dsrl_file(tmp_path / 'walls.hdf5', arrays, metadata=METADATA)}")
    write_minari(ours, "test/walls-v0", metadata=METADATA)
    episode = minari.load_dataset("test/walls-v0")[3]
    assert sorted(k for k in episode.infos if k.startswith("cost_")) == ["cost_x_wall", "cost_y_wall"]
    assert episode.infos["cost_y_wall"][0] == 0 and episode.infos["cost_y_wall"].shape == (LENGTHS[3] + 1,)
    back = load_episodes("minari:test/walls-v0")
    for name in ("x_wall", "y_wall"):
        assert torch.equal(back["next", "constraint_costs", name], ours["next", "constraint_costs", name])
    # Safety-Gymnasium's total is not a constraint; episodes that disagree on their constraints are refused
    import gymnasium
    from minari.data_collector.episode_buffer import EpisodeBuffer

    def buffer(k, infos):
        return EpisodeBuffer(
            id=k,
            observations=np.zeros((3, 2), np.float32),
            actions=np.zeros((2, 1), np.float32),
            rewards=np.zeros(2),
            terminations=np.zeros(2, bool),
            truncations=np.array([False, True]),
            infos={"cost": np.zeros(3)} | infos,
        )

    box = gymnasium.spaces.Box(-np.inf, np.inf, shape=(2,), dtype=np.float32)
    act = gymnasium.spaces.Box(-1, 1, shape=(1,), dtype=np.float32)
    summed = [buffer(0, {"cost_sum": np.zeros(3), "cost_a": np.zeros(3)})]
    minari.create_dataset_from_buffers("test/sum-v0", summed, observation_space=box, action_space=act)
    assert list(load_episodes("minari:test/sum-v0")["next", "constraint_costs"].keys()) == ["a"]
    mixed = [buffer(0, {"cost_a": np.zeros(3)}), buffer(1, {"cost_b": np.zeros(3)})]
    minari.create_dataset_from_buffers("test/mixed-v0", mixed, observation_space=box, action_space=act)
    with pytest.raises(DatasetError, match=r"episode 1 carries the constraint costs \['cost_b'\]"):
        load_episodes("minari:test/mixed-v0")
