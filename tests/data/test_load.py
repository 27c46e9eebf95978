"""Loading DSRL-layout HDF5 files: episodes, TED keys and every bad input."""

from __future__ import annotations

import os

import h5py
import numpy as np
import pytest
import torch

from spoil_torchrl.data import DatasetError, load_episodes, read_metadata, write_dsrl_file
from spoil_torchrl.tasks import DSRL_DATASETS, UnknownDatasetError, get_dsrl_dataset
from tests.data.helpers import make_arrays


def _write(tmp_path, arrays, name="data.hdf5", **kwargs):
    return write_dsrl_file(tmp_path / name, arrays, **kwargs)


def test_episodes_and_ted_keys(tmp_path):
    path = _write(tmp_path, make_arrays(lengths=(3, 2, 4), ends=("timeout", "terminal", "timeout")))
    td = load_episodes(f"file:{path}")
    assert td.shape == (9,)
    assert td["episode"].tolist() == [0, 0, 0, 1, 1, 2, 2, 2, 2]
    assert td["is_init"].squeeze(-1).nonzero().squeeze(-1).tolist() == [0, 3, 5]
    assert td["next", "terminated"].squeeze(-1).nonzero().squeeze(-1).tolist() == [4]
    assert td["next", "truncated"].squeeze(-1).nonzero().squeeze(-1).tolist() == [2, 8]
    assert td["next", "done"].squeeze(-1).nonzero().squeeze(-1).tolist() == [2, 4, 8]
    for key in (("next", "reward"), ("next", "cost"), ("next", "terminated"), "is_init"):
        assert td[key].shape == (9, 1), key
    assert td["next", "reward"].dtype == torch.float32 and td["next", "terminated"].dtype == torch.bool
    # a truncated step keeps its real next observation (no zeroing, unlike D4RLExperienceReplay)
    torch.testing.assert_close(td["next", "observation"][2], torch.full((4,), 3.0))


def test_missing_final_flag_is_a_truncated_episode_with_a_warning(tmp_path):
    path = _write(tmp_path, make_arrays(lengths=(2, 3), ends=("terminal", None)))
    with pytest.warns(UserWarning, match="last 3 rows"):
        td = load_episodes(f"file:{path}")
    assert td["episode"].tolist() == [0, 0, 1, 1, 1]
    assert td["next", "truncated"].squeeze(-1).tolist() == [False, False, False, False, True]


@pytest.mark.parametrize("flag_dtype", [np.float64, np.bool_, np.int64])
@pytest.mark.parametrize("float_dtype", [np.float32, np.float64])
def test_flag_and_float_dtypes(tmp_path, flag_dtype, float_dtype):
    arrays = make_arrays(flag_dtype=flag_dtype, float_dtype=float_dtype)
    td = load_episodes(f"file:{_write(tmp_path, arrays)}")
    assert td["episode"].max().item() == 2
    assert td["observation"].dtype == torch.float32


def test_terminal_and_timeout_on_the_same_step_is_terminal(tmp_path):
    arrays = make_arrays(lengths=(2,), ends=("terminal",))
    arrays["timeouts"][1] = 1
    td = load_episodes(f"file:{_write(tmp_path, arrays)}")
    assert td["next", "terminated"][1].item() and not td["next", "truncated"][1].item()


def test_bare_path_and_metadata(tmp_path):
    path = _write(tmp_path, make_arrays(), metadata={"task": "demo", "seed": 3})
    assert load_episodes(str(path)).shape == (9,)
    assert read_metadata(path) == {"task": "demo", "seed": 3}


def test_memmap_storage(tmp_path):
    path = _write(tmp_path, make_arrays())
    td = load_episodes(f"file:{path}", memmap_dir=tmp_path / "mm")
    assert td["observation"].__class__.__name__ == "MemoryMappedTensor"
    assert (tmp_path / "mm" / "observations.memmap").exists()
    torch.testing.assert_close(td["observation"], load_episodes(f"file:{path}")["observation"])


@pytest.mark.parametrize(
    ("mutate", "match"),
    [
        (lambda a: a.pop("costs"), "missing array 'costs'"),
        (lambda a: a.update(rewards=a["rewards"][:-1]), "different lengths"),
        (lambda a: a["observations"].__setitem__((4, 1), np.nan), "'observations' contains NaN.*row 4"),
        (lambda a: a["costs"].__setitem__(2, np.inf), "'costs' contains NaN or infinite"),
        (lambda a: a["timeouts"].__setitem__(0, 0.5), "0/1 flags"),
        (lambda a: a.update(next_observations=a["next_observations"][:, :2]), "differ in shape"),
    ],
)
def test_bad_arrays_raise_clear_errors(tmp_path, mutate, match):
    arrays = make_arrays()
    mutate(arrays)
    path = tmp_path / "bad.hdf5"
    with h5py.File(path, "w") as f:
        for key, value in arrays.items():
            f.create_dataset(key, data=value)
    with pytest.raises(DatasetError, match=match) as info:
        load_episodes(f"file:{path}")
    assert str(path) in str(info.value)


def test_empty_dataset(tmp_path):
    arrays = {k: v[:0] for k, v in make_arrays().items()}
    path = tmp_path / "empty.hdf5"
    with h5py.File(path, "w") as f:
        for key, value in arrays.items():
            f.create_dataset(key, data=value)
    with pytest.raises(DatasetError, match="empty"):
        load_episodes(f"file:{path}")


def test_empty_non_hdf5_and_truncated_files(tmp_path):
    empty = tmp_path / "zero.hdf5"
    empty.write_bytes(b"")
    with pytest.raises(DatasetError, match="empty"):
        load_episodes(f"file:{empty}")
    text = tmp_path / "text.hdf5"
    text.write_text("<html>not found</html>")
    with pytest.raises(DatasetError, match="not an HDF5 file"):
        load_episodes(f"file:{text}")
    good = _write(tmp_path, make_arrays(lengths=(300, 300), ends=("timeout", "timeout")), compression=None)
    cut = tmp_path / "cut.hdf5"
    cut.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    with pytest.raises(DatasetError, match="truncated or corrupt|not an HDF5"):
        load_episodes(f"file:{cut}")
    with pytest.raises(DatasetError, match="no such file"):
        load_episodes(f"file:{tmp_path / 'nope.hdf5'}")


def test_unknown_source_and_dataset_id():
    with pytest.raises(DatasetError, match="dataset.source = 's3:bucket/file': unknown dataset source"):
        load_episodes("s3:bucket/file")
    with pytest.raises(UnknownDatasetError, match="did you mean 'OfflinePointCircle1Gymnasium-v0'"):
        load_episodes("dsrl:OfflinePointCircle1-v0")


def test_dsrl_source_reads_the_cache_and_checks_dims(tmp_path, monkeypatch):
    monkeypatch.setenv("DSRL_DATASET_DIR", str(tmp_path))
    dataset = get_dsrl_dataset("OfflinePointCircle1Gymnasium-v0")
    _write(tmp_path, make_arrays(obs_dim=28, act_dim=2), name=dataset.file_name)
    assert load_episodes(f"dsrl:{dataset.dataset_id}").shape == (9,)
    (tmp_path / dataset.file_name).unlink()
    _write(tmp_path, make_arrays(obs_dim=27, act_dim=2), name=dataset.file_name)
    with pytest.raises(DatasetError, match="observation dimension is 27, but the task expects 28"):
        load_episodes(f"dsrl:{dataset.dataset_id}")


def test_generated_source(tmp_path, monkeypatch):
    monkeypatch.setenv("SPOIL_TORCHRL_DATA_DIR", str(tmp_path))
    with pytest.raises(DatasetError, match="collect_demos.py name=point-circle1-mixed"):
        load_episodes("generated:point-circle1-mixed")
    with pytest.raises(DatasetError, match="not one of the known generated datasets .point-circle1-mixed"):
        load_episodes("generated:pointcircle1-mixed")
    _write(tmp_path, make_arrays(), name="pointcircle1-mixed.hdf5", metadata={"task": "x"})
    assert load_episodes("generated:pointcircle1-mixed").shape == (9,)


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    arrays = make_arrays()
    arrays["observations"] = object()  # h5py cannot store this
    with pytest.raises(TypeError):
        write_dsrl_file(tmp_path / "x.hdf5", arrays)
    assert list(tmp_path.iterdir()) == []


def test_written_file_has_the_usual_permissions(tmp_path):
    # the unique temporary file is owner-only; the published dataset follows the umask like any new file
    old = os.umask(0o022)
    try:
        write_dsrl_file(tmp_path / "x.hdf5", make_arrays())
    finally:
        os.umask(old)
    assert (tmp_path / "x.hdf5").stat().st_mode & 0o777 == 0o644


def test_task_table_has_the_38_datasets_and_table_c():
    assert len(DSRL_DATASETS) == 38
    with_thresholds = [d for d in DSRL_DATASETS.values() if d.cost_threshold is not None]
    assert len(with_thresholds) == 21  # the paper's Table C
    d = DSRL_DATASETS["OfflineCarCircle-v0"]
    assert (d.episode_length, d.n_trajectories, d.max_cost) == (300, 1450, 100.0)
    assert round(d.max_return, 2) == 534.31 and round(d.min_return, 2) == 3.48
    assert d.url.endswith("/SafetyCarCircle-v0-100-1450.hdf5")
