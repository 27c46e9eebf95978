"""DualDemoBuffers: per-role buffers, initial states, reproducible sampling, annotation."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tensordict.nn import TensorDictModule

from spoil_torchrl.data import (
    DualDemoBuffers,
    episodes_from_arrays,
    label_ilsp,
    load_episodes,
    write_dsrl_file,
)
from spoil_torchrl.objectives import LogRatio
from tests.data.helpers import make_arrays


@pytest.fixture
def episodes():
    arrays = make_arrays(
        lengths=(3, 2, 4, 1),
        ends=("timeout", "terminal", "timeout", "terminal"),
        costs=[0, 0, 0, 5, 5, 0, 0, 0, 0, 9],
    )
    return episodes_from_arrays(arrays)


def _buffers(episodes, **kwargs):
    roles = {"safe": [0, 2], "performant": [1], "unlabeled": [0, 1, 2, 3]}
    kwargs.setdefault("batch_size", {"safe": 5, "performant": 3, "unlabeled": 7, "init": 2})
    return DualDemoBuffers(episodes, roles, **kwargs)


def test_roles_hold_their_episodes(episodes):
    buffers = _buffers(episodes)
    assert buffers.roles == ["safe", "performant", "unlabeled", "init"]
    assert len(buffers["safe"]) == 7 and len(buffers["performant"]) == 2 and len(buffers["unlabeled"]) == 10
    batch = buffers.sample()
    assert set(batch["safe", "episode"].tolist()) <= {0, 2}
    assert set(batch["performant", "episode"].tolist()) == {1}
    assert batch["safe"].shape == (5,) and batch["unlabeled"].shape == (7,) and batch["init"].shape == (2,)


def test_init_states_are_first_observations_of_unlabeled_episodes(episodes):
    buffers = _buffers(episodes)
    stored = buffers["init"].storage[: len(buffers["init"])]
    assert stored["observation"][:, 0].tolist() == [0.0, 3.0, 5.0, 9.0]  # row index of each episode start
    assert stored["episode"].tolist() == [0, 1, 2, 3]


def test_sampling_is_reproducible_by_seed(episodes):
    a, b = _buffers(episodes, seed=7).sample(), _buffers(episodes, seed=7).sample()
    c = _buffers(episodes, seed=8).sample()
    assert (a["unlabeled", "observation"] == b["unlabeled", "observation"]).all()
    assert not all((a[r, "observation"] == c[r, "observation"]).all() for r in ("safe", "unlabeled"))


def test_drawing_some_roles_draws_the_same_batches_for_them(episodes):
    full, some = _buffers(episodes, seed=3), _buffers(episodes, seed=3)
    for _ in range(3):
        a, b = full.sample(), some.sample(["unlabeled", "init"])
        assert sorted(b.keys()) == ["init", "unlabeled"]
        for role in ("unlabeled", "init"):
            assert (a[role, "observation"] == b[role, "observation"]).all()
    state = some.rng_state()
    assert torch.equal(state["safe"], _buffers(episodes, seed=3).rng_state()["safe"])  # never drawn
    with pytest.raises(ValueError, match=r"no buffer for roles \['expert'\]"):
        some.sample(["expert"])


def test_all_episodes_role_shares_the_dataset(episodes):
    buffers = _buffers(episodes)
    storage = buffers["unlabeled"].storage._storage
    assert storage["observation"].data_ptr() == episodes["observation"].data_ptr()


def test_truncated_steps_keep_their_next_observation(episodes):
    buffers = _buffers(episodes, batch_size=64)
    batch = buffers.sample()
    unl = batch["unlabeled"]
    trunc = unl["next", "truncated"].squeeze(-1)
    assert trunc.any()
    torch.testing.assert_close(unl["next", "observation"][trunc], unl["observation"][trunc] + 1)


def test_annotate_writes_once_into_the_role_storage(episodes):
    buffers = _buffers(episodes)
    disc = TensorDictModule(
        lambda o, a: o[..., :1] * 2, in_keys=["observation", "action"], out_keys=["logit"]
    )
    buffers.annotate("unlabeled", LogRatio(disc), chunk_size=3)
    batch = buffers.sample()
    torch.testing.assert_close(
        batch["unlabeled", "log_ratio_performant"], batch["unlabeled", "observation"][:, :1] * 2
    )


def test_memmap_copies_of_role_subsets(episodes, tmp_path):
    buffers = _buffers(episodes, memmap_dir=tmp_path)
    assert buffers["safe"].storage._storage.is_memmap()
    assert (tmp_path / "safe").exists()
    assert buffers.sample()["safe"].shape == (5,)


def test_memmap_loaded_dataset_stays_memory_mapped(tmp_path):
    path = write_dsrl_file(tmp_path / "d.hdf5", make_arrays())
    episodes = load_episodes(f"file:{path}", memmap_dir=tmp_path / "mm")
    labels = label_ilsp(episodes, cost_threshold=1.0)
    buffers = DualDemoBuffers(episodes, {"unlabeled": labels["unlabeled"]}, batch_size=4)
    assert type(buffers["unlabeled"].storage._storage["observation"]).__name__ == "MemoryMappedTensor"


def test_bad_roles_raise(episodes):
    with pytest.raises(ValueError, match="reserved"):
        DualDemoBuffers(episodes, {"init": [0], "unlabeled": [0]})
    with pytest.raises(ValueError, match="init_role"):
        DualDemoBuffers(episodes, {"safe": [0]})
    with pytest.raises(ValueError, match="episode ids must lie in"):
        DualDemoBuffers(episodes, {"safe": [9], "unlabeled": [0]})


def test_ids_that_are_not_whole_numbers_and_empty_batches_are_refused(episodes):
    """A float id would be truncated to another episode, a mask read as ids 0 and 1, a batch of 0 drawn empty."""
    with pytest.raises(ValueError, match=r"role 'safe': episode ids must be whole numbers, got \[1.7, 3.2\]"):
        DualDemoBuffers(episodes, {"safe": [1.7, 3.2], "unlabeled": [0, 1, 2, 3]})
    with pytest.raises(ValueError, match="role 'unlabeled': episode ids expected, got a boolean mask"):
        DualDemoBuffers(episodes, {"safe": [0], "unlabeled": [True, False, True, True]})
    with pytest.raises(ValueError, match="batch_size of role 'performant' = 0: expected an integer >= 1"):
        _buffers(episodes, batch_size={"safe": 5, "performant": 0, "unlabeled": 7, "init": 2})
    with pytest.raises(ValueError, match="batch_size of role 'safe' = 0"):
        _buffers(episodes, batch_size=0)
    with pytest.raises(ValueError, match="role 'safe': episode ids must be whole numbers"):
        DualDemoBuffers(episodes, {"safe": [0.0, float("inf")], "unlabeled": [0, 1, 2, 3]})
    whole = DualDemoBuffers(episodes, {"safe": [0.0, 2.0], "unlabeled": [0, 1, 2, 3]}, batch_size=np.int64(4))
    assert sorted(set(whole["safe"].storage._storage["episode"].tolist())) == [0, 2]


def test_annotate_with_a_key_and_a_function(episodes):
    buffers = _buffers(episodes)
    buffers.annotate("safe", "double_cost", lambda td: 2 * td["next", "cost"], chunk_size=2)
    stored = buffers["safe"].storage[: len(buffers["safe"])]
    torch.testing.assert_close(stored["double_cost"], 2 * stored["next", "cost"])
    with pytest.raises(TypeError, match="needs fn"):
        buffers.annotate("safe", "x")
