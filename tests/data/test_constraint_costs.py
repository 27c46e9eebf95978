"""Per-constraint costs through the data layer: both file forms load with their names, bad ones are refused in one
line, a file without them loads exactly as before, and each constraint gets its own safe set."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from spoil_torchrl.data import DatasetError
from spoil_torchrl.data.constraint_costs import (
    CONSTRAINTS_KEY,
    constraint_names,
    constraint_roles,
    constraint_safe_ids,
    episode_constraint_costs,
)
from spoil_torchrl.data.episodes import episodes_from_arrays
from spoil_torchrl.data.hdf5 import read_dsrl_file, write_dsrl_file
from tests.data.helpers import make_arrays

LENGTHS = (3, 2, 4)
# per step: episode 0 crosses x twice, episode 1 crosses y once, episode 2 crosses nothing
X_WALL = [1, 0, 1, 0, 0, 0, 0, 0, 0]
Y_WALL = [0, 0, 0, 0, 1, 0, 0, 0, 0]


def _arrays(**extra):
    arrays = make_arrays(lengths=LENGTHS, costs=np.maximum(X_WALL, Y_WALL))
    arrays.update({k: np.asarray(v, np.float32) for k, v in extra.items()})
    return arrays


def test_named_cost_arrays_load_as_named_components_beside_the_tasks_cost(tmp_path):
    path = write_dsrl_file(tmp_path / "walls.hdf5", _arrays(cost_x_wall=X_WALL, cost_y_wall=Y_WALL))
    episodes = read_dsrl_file(path)
    assert constraint_names(episodes) == ["x_wall", "y_wall"]
    assert episodes["next", CONSTRAINTS_KEY, "x_wall"].shape == (9, 1)
    assert episodes["next", "cost"].reshape(-1).tolist() == np.maximum(X_WALL, Y_WALL).tolist()
    per_episode = episode_constraint_costs(episodes)
    assert per_episode["x_wall"].tolist() == [2.0, 0.0, 0.0] and per_episode["y_wall"].tolist() == [
        0.0,
        1.0,
        0.0,
    ]


def test_a_costs_matrix_names_its_columns_by_the_metadata_and_the_tasks_cost_is_their_sum(tmp_path):
    arrays = _arrays()
    arrays["costs"] = np.stack([X_WALL, Y_WALL], 1).astype(np.float32)
    path = write_dsrl_file(tmp_path / "matrix.hdf5", arrays, metadata={"constraints": ["x_wall", "y_wall"]})
    episodes = read_dsrl_file(path)
    assert constraint_names(episodes) == ["x_wall", "y_wall"]
    assert episodes["next", "cost"].reshape(-1).tolist() == (np.add(X_WALL, Y_WALL)).tolist()
    unnamed = episodes_from_arrays(arrays)
    assert constraint_names(unnamed) == ["c0", "c1"]


def test_a_file_without_components_loads_as_before(tmp_path):
    path = write_dsrl_file(tmp_path / "plain.hdf5", _arrays())
    episodes = read_dsrl_file(path)
    assert constraint_names(episodes) == [] and ("next", CONSTRAINTS_KEY) not in episodes.keys(True)
    assert sorted(episodes["next"].keys()) == [
        "cost",
        "done",
        "observation",
        "reward",
        "terminated",
        "truncated",
    ]


@pytest.mark.parametrize(
    ("change", "match"),
    [
        ({"cost_x_wall": [1.0] * 8}, "constraint 'x_wall'.s costs have shape"),
        ({"cost_x_wall": [-1.0] + [0.0] * 8}, "constraint 'x_wall' has negative costs"),
        ({"cost_x_wall": [float("nan")] + [0.0] * 8}, "must be finite"),
        ({"cost_x wall": [0.0] * 9}, "constraint name 'x wall'"),
    ],
)
def test_bad_components_are_refused_naming_the_constraint(change, match):
    with pytest.raises(DatasetError, match=match):
        episodes_from_arrays(_arrays(**change), source="walls.hdf5")


def test_cost_columns_that_disagree_with_the_names_and_two_forms_at_once_are_refused():
    arrays = _arrays()
    arrays["costs"] = np.stack([X_WALL, Y_WALL], 1).astype(np.float32)
    with pytest.raises(DatasetError, match="'costs' has 2 columns, but 3 constraint names"):
        episodes_from_arrays(arrays, constraints=["a", "b", "c"])
    arrays["cost_z"] = np.zeros(9, np.float32)
    with pytest.raises(DatasetError, match="store the constraints' costs one way"):
        episodes_from_arrays(arrays)


def test_each_constraint_gets_a_safe_set_of_its_own_and_bad_choices_are_named():
    episodes = episodes_from_arrays(_arrays(cost_x_wall=X_WALL, cost_y_wall=Y_WALL))
    safe = constraint_safe_ids(episodes, ["x_wall", "y_wall"], {"x_wall": 0.0, "y_wall": 0.0})
    assert safe["x_wall"].tolist() == [1, 2] and safe["y_wall"].tolist() == [0, 2]
    roles = constraint_roles(
        episodes, {"constraints": ["x_wall", "y_wall"], "n_safe": 1}, cost_threshold=0.0, seed=0
    )
    assert sorted(roles) == ["safe_x_wall", "safe_y_wall"]
    assert roles["safe_x_wall"].item() in (1, 2) and roles["safe_y_wall"].item() in (0, 2)
    again = constraint_roles(
        episodes, {"constraints": ["x_wall", "y_wall"], "n_safe": 1}, cost_threshold=0.0, seed=0
    )
    assert all(torch.equal(roles[k], again[k]) for k in roles)
    assert constraint_roles(episodes, {"n_safe": 1}, cost_threshold=0.0, seed=0) == {}
    with pytest.raises(
        DatasetError, match=r"names \['z_wall'\], but the data carry the costs of \['x_wall', 'y_wall'\]"
    ):
        constraint_safe_ids(episodes, ["z_wall"], {"z_wall": 0.0})
    with pytest.raises(DatasetError, match="no episode is within constraint 'x_wall'"):
        constraint_safe_ids(episodes, ["x_wall"], {"x_wall": -1.0})
    with pytest.raises(DatasetError, match="fewer than n_safe_per_constraint=3"):
        constraint_roles(
            episodes,
            {"constraints": ["x_wall"], "n_safe": 1, "n_safe_per_constraint": 3},
            cost_threshold=0.0,
            seed=0,
        )
    with pytest.raises(DatasetError, match=r"constraint_thresholds names \['y_wall'\]"):
        constraint_roles(
            episodes,
            {"constraints": ["x_wall"], "n_safe": 1, "constraint_thresholds": {"y_wall": 1.0}},
            cost_threshold=0.0,
            seed=0,
        )


def test_typed_pools_give_each_constraint_the_merged_safe_set_and_its_own_annotators_episodes():
    episodes = episodes_from_arrays(_arrays(cost_x_wall=X_WALL, cost_y_wall=Y_WALL))
    cfg = {
        "constraints": ["x_wall", "y_wall"],
        "n_safe": 1,
        "constraint_pools": {"x_wall": "x-only", "y_wall": "y-only"},
    }
    pools = {"x-only": torch.tensor([1]), "y-only": torch.tensor([0, 1])}  # episode 1 is over y's threshold
    merged = torch.tensor([2])  # safe on both walls: in every constraint's safe set
    roles = constraint_roles(episodes, cfg, cost_threshold=0.0, seed=0, safe=merged, pools=pools)
    assert roles["safe_x_wall"].tolist() == [1, 2] and roles["safe_y_wall"].tolist() == [0, 2]
    overlapping = pools | {"x-only": torch.tensor([1, 2])}  # D_S's episode 2 is in x's pool too: drawn once
    for seed in range(4):
        again = constraint_roles(episodes, cfg, cost_threshold=0.0, seed=seed, safe=merged, pools=overlapping)
        assert again["safe_x_wall"].tolist() == [1, 2]
    bad = [
        ({"constraint_pools": {"x_wall": "x-only"}}, {}, r"one typed pool for each of dataset.constraints"),
        ({"constraint_pools": {"x_wall": "x-only", "y_wall": "z"}}, {}, r"names the pools \['z'\]"),
        ({}, {"pools": None}, "needs a collected file's typed pools"),
        ({}, {"safe": torch.tensor([0])}, r"D_S's episodes \[0\] exceed constraint 'x_wall'"),
        ({"n_safe_per_constraint": 2}, {}, "1 episodes of pool 'x-only' are within constraint 'x_wall'"),
    ]
    for change, given, match in bad:
        with pytest.raises(DatasetError, match=match):
            kwargs = {"safe": merged, "pools": pools} | given
            constraint_roles(episodes, cfg | change, cost_threshold=0.0, seed=0, **kwargs)


def test_point_circle2_records_each_walls_cost_and_the_task_cost_is_their_union(tmp_path):
    """Collected with components, a file carries x_wall / y_wall per step, computed from the agent's position
    after the step, and the simulator's own cost is exactly their maximum (its Sigwalls cost is the union)."""
    import importlib.util

    if importlib.util.find_spec("safety_gymnasium") is None:
        pytest.skip("safety-gymnasium not installed (EXTRAS=dev)")
    from spoil_torchrl.data import Segment, collect

    path = collect(
        "SafetyPointCircle2-v0",
        [Segment("unsafe-high", "zoo:unsafe-high", 2)],
        tmp_path / "walls.hdf5",
        num_envs=2,
        reference_episodes=1,
        progress=False,
        components=True,
    )
    episodes = read_dsrl_file(path)
    assert constraint_names(episodes) == ["x_wall", "y_wall"]
    parts = episodes["next", CONSTRAINTS_KEY]
    union = torch.maximum(parts["x_wall"], parts["y_wall"])
    assert torch.equal(union, episodes["next", "cost"])
    per_episode = episode_constraint_costs(episodes)
    assert bool((per_episode["x_wall"] > 0).any()) and bool((per_episode["y_wall"] > 0).any())
    with pytest.raises(ValueError, match="SafetyPointCircle1-v0 has no per-constraint costs"):
        collect(
            "SafetyPointCircle1-v0",
            [Segment("unsafe-high", "zoo:unsafe-high", 1)],
            tmp_path / "none.hdf5",
            progress=False,
            components=True,
        )
