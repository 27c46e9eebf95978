"""The bad-input corpus: every way a user can hand the library a broken file (data, policy, checkpoint, rollouts)
gets one clear error that names the file, and leaves every file as it was. Settings: test_bad_settings.py;
commands: test_command_errors.py."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from spoil_torchrl.data import DualDemoBuffers, load_episodes
from spoil_torchrl.data.episodes import DatasetError, select_episodes
from spoil_torchrl.data.hdf5 import METADATA_ATTR, read_metadata, write_dsrl_file
from spoil_torchrl.modules import make_actor
from spoil_torchrl.runs.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from spoil_torchrl.tasks import UnknownDatasetError
from spoil_torchrl.zoo import PolicyFileError, load_policy, save_policy
from tests.cli import run_command
from tests.data.helpers import make_arrays

ROOT = Path(__file__).resolve().parents[1]


def _task_metadata() -> dict:
    return {
        "env_id": "SafetyPointCircle1-v0",
        "cost_threshold": 25.0,
        "random_return": 0.0,
        "safe_high_return": 40.0,
    }


def _good(path: Path, **kwargs) -> Path:
    return write_dsrl_file(path, make_arrays(lengths=(30, 20, 40), **kwargs), metadata={"note": "ok"})


# -- data files -----------------------------------------------------------------------------------------------


def _missing(path):
    return path


def _empty(path):
    path.write_bytes(b"")
    return path


def _not_hdf5(path):
    path.write_text("observations,actions\n1,2\n")
    return path


def _truncated(path):
    data = _good(path).read_bytes()
    path.write_bytes(data[: len(data) // 3])
    return path


def _damaged_header(path):
    data = bytearray(_good(path).read_bytes())
    for i in range(40, 120):  # superblock and root group header, after the signature
        data[i] ^= 0xA5
    path.write_bytes(bytes(data))
    return path


def _damaged_chunk(path):
    write_dsrl_file(path, make_arrays(lengths=(300, 200), ends=("timeout", "timeout")), compression=None)
    with h5py.File(path, "r") as f:
        offset = f["observations"].id.get_offset() or f["observations"].id.get_chunk_info(0).byte_offset
    data = bytearray(path.read_bytes())
    data[offset + 16] ^= 0xFF  # one byte of the observations, its fletcher32 checksum kept
    path.write_bytes(bytes(data))
    return path


def _arrays_file(**change):
    def make(path):
        arrays = make_arrays(lengths=(3, 2, 4))
        for key, value in change.items():
            if value is None:
                del arrays[key]
            else:
                arrays[key] = value(arrays[key])
        with h5py.File(path, "w") as f:  # bypasses the writer's own checks, as a foreign file would
            for key, value in arrays.items():
                f.create_dataset(key, data=value)
        return path

    return make


DATA_CASES = {
    "missing file": (_missing, "no such file"),
    "empty file": (_empty, "empty"),
    "not HDF5": (_not_hdf5, "not an HDF5 file"),
    "truncated": (_truncated, "truncated or corrupt|corrupt"),
    "damaged header": (_damaged_header, "corrupt|not an HDF5"),
    "damaged data chunk": (_damaged_chunk, "cannot read 'observations'|corrupt"),
    "ragged arrays": (_arrays_file(rewards=lambda a: a[:-1]), "different lengths"),
    "NaN values": (_arrays_file(observations=lambda a: np.where(a == 2, np.nan, a)), "NaN or infinite"),
    "missing key": (_arrays_file(costs=None), "missing array 'costs'"),
    "negative costs": (_arrays_file(costs=lambda a: a - 1.0), "costs are negative"),
    "2-D rewards": (_arrays_file(rewards=lambda a: np.stack([a, a], 1)), "'rewards' must be 1-D"),
    "non-0/1 flags": (_arrays_file(terminals=lambda a: a + 2.0), "terminals"),
    "text flags": (_arrays_file(terminals=lambda a: a.astype("S1")), "'terminals' must hold 0/1 flags"),
    "beyond float32": (
        _arrays_file(observations=lambda a: np.where(a == 2, 1e39, a.astype(np.float64))),
        "holds 1e\\+39 at row 2, beyond the float32 range",
    ),
    "a directory": (lambda path: (path.mkdir(), path)[1], "a directory, not an HDF5 file"),
    "symlink loop": (lambda path: (path.symlink_to(path), path)[1], "a symlink loop"),
    "broken symlink": (
        lambda path: (path.symlink_to(path.with_name("gone.hdf5")), path)[1],
        "broken symlink",
    ),
}


@pytest.mark.parametrize("case", list(DATA_CASES))
def test_a_broken_data_file_is_one_clear_error(tmp_path, case):
    make, match = DATA_CASES[case]
    path = make(tmp_path / "data.hdf5")
    before = {p: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()}
    with pytest.raises(DatasetError, match=match) as err:
        load_episodes(f"file:{path}")
    assert str(path) in str(err.value)
    assert {p: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()} == before


def test_a_file_another_process_writes_is_not_called_corrupt(tmp_path):
    path = _good(tmp_path / "data.hdf5")
    writer = subprocess.Popen(
        [
            sys.executable,
            "-c",
            f"import h5py, time; f = h5py.File({str(path)!r}, 'a'); print(1, flush=True); time.sleep(60)",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        writer.stdout.readline()
        with pytest.raises(DatasetError, match="another process has this file open.*keep it") as err:
            load_episodes(f"file:{path}")
        assert "delete" not in str(err.value)
    finally:
        writer.kill()
        writer.wait()


def test_malformed_metadata_names_the_file(tmp_path):
    path = _good(tmp_path / "data.hdf5")
    with h5py.File(path, "a") as f:
        f.attrs[METADATA_ATTR] = '{"segments": [1, 2'
    with pytest.raises(DatasetError, match=f"{path}.*not valid JSON"):
        read_metadata(path)
    with h5py.File(path, "a") as f:
        f.attrs[METADATA_ATTR] = "[1, 2]"
    with pytest.raises(DatasetError, match="not a JSON object"):
        read_metadata(path)


def test_unknown_sources_ids_and_empty_roles(tmp_path):
    with pytest.raises(UnknownDatasetError, match="no-such-dataset"):
        load_episodes("dsrl:no-such-dataset")
    with pytest.raises(ValueError, match="source"):
        load_episodes("ftp:somewhere")
    episodes = load_episodes(f"file:{_good(tmp_path / 'data.hdf5')}")
    with pytest.raises(ValueError, match=r"episode ids must lie in \[0, 3\)"):
        select_episodes(episodes, [0, 7])
    with pytest.raises(ValueError, match="role 'safe' has no transitions"):
        DualDemoBuffers(episodes, {"safe": [], "unlabeled": [0, 1, 2]})


# -- data that load but cannot be used as configured (prepare_dataset, before any training) -------------------

PC1 = "SafetyPointCircle1-v0"


def _pc1_file(path: Path, metadata=None, change=None) -> Path:
    arrays = make_arrays(
        lengths=(30, 20, 40, 25), ends=("timeout", "terminal", "timeout", "timeout"), obs_dim=28
    )
    arrays["costs"][20:50] = 2.0  # episode 1: cost 40, over the threshold of 25 (unsafe); the others safe
    if change is not None:
        change(arrays)
    meta = {"env_id": PC1, "cost_threshold": 25.0, "random_return": 0.0, "safe_high_return": 40.0}
    return write_dsrl_file(path, arrays, metadata=meta if metadata is None else metadata)


def _set(**values):
    def change(arrays):
        for key, (rows, value) in values.items():
            arrays[key][rows] = value

    return change


PREPARE_CASES = {
    "no safe episode": (dict(change=_set(costs=(slice(None), 5.0))), {}, "no episode has cost <= 25"),
    "n_safe beyond its pool": ({}, {"n_safe": 9}, "3 safe episodes .* fewer than n_safe=9"),
    "n_performant beyond its pool": ({}, {"n_performant": 9}, "fewer than n_performant=9"),
    "n_unlabeled beyond the data": ({}, {"n_unlabeled": 99}, "4 episodes, fewer than n_unlabeled=99"),
    "another task's observations": (
        dict(
            change=lambda a: a.update(
                observations=a["observations"][:, :4], next_observations=a["next_observations"][:, :4]
            )
        ),
        {},
        "observation/action sizes 4/2, but SafetyPointCircle1-v0 has 28/2",
    ),
    "another task's actions": (
        dict(change=lambda a: a.update(actions=np.zeros((len(a["actions"]), 6), np.float32))),
        {},
        "sizes 28/6",
    ),
    "recorded in another task": (
        dict(metadata={"env_id": "SafetyHopperVelocity-v1", "cost_threshold": 25.0}),
        {},
        "recorded in SafetyHopperVelocity-v1, but the task is SafetyPointCircle1-v0",
    ),
    "actions beyond the bounds": (
        dict(change=_set(actions=(5, 1.5))),
        {},
        "2 action values lie outside .* 1.5 at row 5",
    ),
    "inverted return range in the metadata": (
        dict(
            metadata={"env_id": PC1, "cost_threshold": 25.0, "random_return": 40.0, "safe_high_return": 0.0}
        ),
        {},
        "return range .* not two finite numbers R_min < R_max",
    ),
    "text return range in the metadata": (
        dict(metadata={"env_id": PC1, "cost_threshold": 25.0, "return_range": ["low", "high"]}),
        {},
        "return range .* not two finite numbers",
    ),
    "negative cost threshold in the metadata": (
        dict(
            metadata={"env_id": PC1, "cost_threshold": -3.0, "random_return": 0.0, "safe_high_return": 40.0}
        ),
        {},
        "cost threshold -3.0",
    ),
    "no return range anywhere": (
        dict(metadata={"env_id": PC1, "cost_threshold": 25.0}),
        {},
        "no return range known; set dataset.return_range",
    ),
    "controlled scheme on a file without pools": ({}, {"scheme": "controlled"}, "needs the typed pools"),
    "stored scheme without stored roles": ({}, {"scheme": "stored"}, "stores no 'safe' role"),
    "stored roles of another file": (
        dict(
            metadata={
                "env_id": PC1,
                "cost_threshold": 25.0,
                "random_return": 0.0,
                "safe_high_return": 40.0,
                "roles": {"safe": [0, 7], "performant": [1], "unlabeled": [0, 1, 2]},
            }
        ),
        {"scheme": "stored"},
        "names episodes outside the dataset's 4",
    ),
    "no unsafe episode for SafeDICE": (
        dict(change=_set(costs=(slice(None), 0.0))),
        {"EXTRA": ("nonpreferred",)},
        "unsafe|non-preferred",
    ),
}


@pytest.mark.parametrize("case", list(PREPARE_CASES))
def test_data_that_cannot_be_used_as_configured_is_one_clear_error(tmp_path, case):
    from spoil_torchrl.data.prepare import prepare_dataset

    file_kwargs, overrides, match = PREPARE_CASES[case]
    path = _pc1_file(tmp_path / "pc1.hdf5", **file_kwargs)
    extra = overrides.pop("EXTRA", ())
    cfg = {"source": f"file:{path}", "scheme": "ilsp", "n_safe": 1, "n_performant": 1, **overrides}
    with pytest.raises(DatasetError, match=match):
        prepare_dataset(cfg, env_id=PC1, progress=False, extra_roles=extra)


# -- policy files and checkpoints -----------------------------------------------------------------------------


def _policy(path: Path) -> Path:
    return save_policy(path, make_actor(28, 2, hidden_cells=(8,)), env_id="SafetyPointCircle1-v0")


def _flip_weights(path: Path) -> None:
    raw = torch.load(path, weights_only=True)
    first = next(iter(raw["actor"]))
    raw["actor"][first] = raw["actor"][first].clone()
    raw["actor"][first].view(-1)[:64] += 0.5  # weights changed, the stored checksum kept
    torch.save(raw, path)


def _nan_weights(path: Path) -> None:
    raw = torch.load(path, weights_only=True)
    raw.pop("weights_sha256")  # as in a file written by an older version, or by hand
    first = next(iter(raw["actor"]))
    raw["actor"][first] = raw["actor"][first].clone()
    raw["actor"][first].view(-1)[0] = float("nan")
    torch.save(raw, path)


@pytest.mark.parametrize(
    "damage, match",
    [
        (_flip_weights, "checksum"),
        (_nan_weights, "non-finite weights"),
        (lambda p: p.write_bytes(p.read_bytes()[:500]), "not a policy checkpoint"),
        (lambda p: torch.save({"weights": torch.zeros(2)}, p), "no 'actor' state dict"),
        (lambda p: p.unlink(), "no such policy file"),
    ],
)
def test_a_damaged_policy_file_is_refused(tmp_path, damage, match):
    path = _policy(tmp_path / "policy.pt")
    damage(path)
    with pytest.raises(PolicyFileError, match=match):
        load_policy(path)


def test_a_policy_for_another_task_is_refused(tmp_path):
    with pytest.raises(PolicyFileError, match="SafetyHalfCheetahVelocity-v1"):
        load_policy(_policy(tmp_path / "p.pt"), env_id="SafetyHalfCheetahVelocity-v1")


def test_a_damaged_training_checkpoint_is_refused(tmp_path):
    path = tmp_path / "state.pt"
    save_checkpoint(path, {"step": 1, "w": torch.randn(1000)})
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match=str(path)):
        load_checkpoint(path)


def test_inspect_fails_on_a_damaged_finished_rollout_file(tmp_path):
    from spoil_torchrl.eval import RolloutWriter

    path = tmp_path / "rollouts.mcap"
    with RolloutWriter(path, cost_threshold=1.0) as writer:
        for _ in range(3):
            for t in range(50):
                writer.add_step([0.1 * t] * 4, [0.0], reward=1.0, cost=0.0)
            writer.end_episode()
    from mcap.reader import make_reader

    with open(path, "rb") as f:  # damage the middle of the second chunk (an episode's compressed messages)
        chunk = make_reader(f).get_summary().chunk_indexes[1]
    data = bytearray(path.read_bytes())
    data[chunk.chunk_start_offset + chunk.chunk_length // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    proc = run_command(["-m", "spoil_torchrl.inspect", path])
    assert proc.returncode == 1 and "finished by its writer but is damaged" in proc.stderr


def test_inspect_refuses_an_mcap_file_without_rollouts(tmp_path):
    from mcap.writer import Writer

    path = tmp_path / "camera.mcap"
    with open(path, "wb") as f:  # a valid MCAP file of something else
        writer = Writer(f)
        writer.start()
        schema = writer.register_schema("image", "jsonschema", b"{}")
        channel = writer.register_channel("/camera", "json", schema)
        writer.add_message(channel, log_time=0, data=b"{}", publish_time=0)
        writer.finish()
    proc = run_command(["-m", "spoil_torchrl.inspect", path])
    assert proc.returncode == 1 and "without rollout topics" in proc.stderr and "0 episode" not in proc.stdout


def test_a_failed_atomic_write_leaves_no_temporary_file(tmp_path):
    from spoil_torchrl.files import write_atomic

    (tmp_path / "results.json").mkdir()  # os.replace onto a directory fails, like a full disk would
    with pytest.raises(OSError):
        write_atomic(tmp_path / "results.json", "{}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results.json"]


def test_observation_columns_a_few_extremes_would_erase_are_named():
    from spoil_torchrl.data.episodes import warn_erased_features

    x = torch.randn(500, 3)
    x[7, 2] = 1e38
    with pytest.warns(UserWarning, match="observation column 2: .* 1e\\+38 at row 7"):
        assert warn_erased_features(x) == [2]


def test_an_unknown_minari_dataset_says_where_it_was_looked_for(tmp_path, monkeypatch):
    minari = pytest.importorskip("minari")

    def offline(dataset_id, force_download=False):  # the remote's client retries for ~20 s without network
        raise ConnectionError("Name or service not known")

    monkeypatch.setattr(minari, "download_dataset", offline)
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    with pytest.raises(DatasetError, match=f"'nope/none-v0' is not in {tmp_path}"):
        load_episodes("minari:nope/none-v0")
