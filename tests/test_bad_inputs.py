"""The bad-input corpus: every way a user can hand the library a broken file or setting gets one clear error
that names the file or setting, and leaves every file outside the run directory as it was."""

from __future__ import annotations

import hashlib
import json
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
from spoil_torchrl.runs.settings import SettingsError, check_settings
from spoil_torchrl.tasks import UnknownDatasetError
from spoil_torchrl.zoo import PolicyFileError, load_policy, save_policy
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
    proc = subprocess.run(
        [sys.executable, "-m", "spoil_torchrl.inspect", str(path)], capture_output=True, text=True, cwd=ROOT
    )
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
    proc = subprocess.run(
        [sys.executable, "-m", "spoil_torchrl.inspect", str(path)], capture_output=True, text=True, cwd=ROOT
    )
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


# -- settings -------------------------------------------------------------------------------------------------

SETTING_CASES = [
    ({"algo": {"kappa": 1.5}}, "algo.kappa = 1.5"),
    ({"algo": {"kappa": 0.0}}, "algo.kappa = 0.0"),
    ({"algo": {"gamma": 1.0}}, "algo.gamma = 1.0"),
    ({"algo": {"nu_lr": -1e-3}}, "algo.nu_lr = -0.001"),
    ({"algo": {"discriminator": {"lr": 0.0}}}, "algo.discriminator.lr = 0.0"),
    (
        {"algo": {"discriminator": {"gradient_penalty": {"safe": -1.0}}}},
        "algo.discriminator.gradient_penalty",
    ),
    ({"algo": {"hidden_cells": [256, 0]}}, "algo.hidden_cells"),
    ({"algo": {"alpha": "big"}}, "algo.alpha = 'big'"),
    ({"algo": {"eta": 1.2}}, "algo.eta = 1.2"),
    ({"train": {"discriminator_steps": 0}}, "train.discriminator_steps = 0"),
    ({"train": {"lr": float("nan")}}, "train.lr = nan"),
    ({"train": {"batch_size": 12.5}}, "train.batch_size = 12.5"),
    (
        {"train": {"matmul_precision": "bf16"}},
        "train.matmul_precision = 'bf16': expected highest | high | medium",
    ),
    ({"threads": 0}, "threads = 0"),
    ({"dataset": {"n_safe": 0}}, "dataset.n_safe = 0"),
    ({"dataset": {"safeness": 1.5}}, "dataset.safeness = 1.5"),
    ({"dataset": {"n_unlabeled": -5}}, "dataset.n_unlabeled = -5"),
    ({"dataset": {"cost_threshold": -1.0}}, "dataset.cost_threshold = -1.0"),
    ({"dataset": {"scheme": "magic"}}, "dataset.scheme = 'magic'"),
    ({"seed": -1}, "seed = -1"),
    ({"normalize_observations": "no"}, "normalize_observations = 'no': expected true or false"),
    ({"progress": 0}, "progress = 0: expected true or false"),
    ({"eval": {"frames": "off"}}, "eval.frames = 'off'"),
    ({"train": {"checkpoint": "no"}}, "train.checkpoint = 'no'"),
    ({"train": {"compile": 1}}, "train.compile = 1"),
    ({"dataset": {"generate": "yes"}}, "dataset.generate = 'yes'"),
    ({"threads": 999}, "threads = 999: expected an integer from 1 to"),
    ({"task": {"eval_num_envs": 0}}, "task.eval_num_envs = 0"),
    ({"dataset": {"return_range": [0, 40, -7]}}, "dataset.return_range = [0, 40, -7]"),
    ({"dataset": {"return_range": "abc"}}, "dataset.return_range = 'abc'"),
    ({"dataset": {"return_range": [40, 0]}}, "dataset.return_range = [40, 0]"),
    ({"dataset": {"return_range": [0, float("inf")]}}, "dataset.return_range = [0, inf]"),
    ({"dataset": {"performance": "half"}}, "dataset.performance = 'half'"),
    ({"dataset": {"return_quantile": 2}}, "dataset.return_quantile = 2"),
    ({"dataset": {"n_performant": 2.5}}, "dataset.n_performant = 2.5"),
    ({"seeds": [0, 0]}, "seeds = [0, 0]"),
    ({"seeds": []}, "seeds = []"),
    ({"threads": "two"}, "threads = 'two'"),
    ({"train": {"eval_interval": 0}}, "train.eval_interval = 0"),
    ({"train": {"steps": 1.5}}, "train.steps = 1.5"),
    ({"train": {"log_interval": -1}}, "train.log_interval = -1"),
    ({"algo": {"hidden_cells": "256"}}, "algo.hidden_cells = '256'"),
    ({"algo": {"standardize_reward": "yes"}}, "algo.standardize_reward = 'yes'"),
]


@pytest.mark.parametrize("settings, match", SETTING_CASES)
def test_a_bad_setting_is_named(settings, match):
    with pytest.raises(SettingsError, match=match.replace("[", r"\[").replace(".", r"\.")):
        check_settings({"seed": 0, "threads": 1, **settings})


# -- through the recipe: one line on stderr, exit status 2, nothing outside the run directory touched ----------


def _snapshot(folder: Path) -> dict[str, str]:
    return {
        str(p): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.rglob("*")) if p.is_file()
    }


@pytest.mark.parametrize(
    "overrides, match",
    [
        (["algo.kappa=2"], "algo.kappa = 2"),
        (["train.discriminator_steps=0"], "train.discriminator_steps = 0"),
        (["threads=0"], "threads = 0"),
        (["resume=maybe"], "resume must be one of"),
        (["algo.name=sac"], "has no builder"),
        (["logger.type=tensorbord"], "'tensorbord' is not a logger"),
        (["DATA=negative"], "costs are negative"),
        (["DATA=truncated"], "truncated or corrupt|corrupt"),
        (["RUN=existing"], "already holds a run"),
        (["RUN=blocked-checkpoints"], "cannot write checkpoints"),
        (["normalize_observations=no"], "normalize_observations = 'no'"),
        (["threads=999"], "threads = 999"),
        (["dataset.return_range=[0,40,-7]"], "dataset.return_range"),
        (["task.eval_num_envs=0"], "task.eval_num_envs = 0"),
        (["dataset.source=generated:no-such-data"], "unknown generated dataset 'no-such-data'"),
        (
            ["DATA=task", "dataset.n_safe=1", "dataset.n_performant=1", "dataset.n_unlabeled=1000"],
            "fewer than n_unlabeled=1000",
        ),
        (["DATA=no-safe"], "no episode has cost <= 25"),
        (
            ["DATA=wrong-size", "dataset.cost_threshold=25", "dataset.return_range=[0,1]"],
            "observation/action sizes 4/2",
        ),
        (["DATA=big-actions"], "action values lie outside SafetyPointCircle1-v0's bounds"),
        (["RUN=a-file"], "is a file, not a run directory"),
        (["RUN=uncreatable"], "cannot be created"),
        (
            ["DATA=task", "dataset.n_safe=1", "dataset.n_performant=1", "logger=wandb"],
            "logger=wandb cannot start|needs the wandb package",
        ),
    ],
)
def test_the_recipe_reports_user_errors_in_one_line(tmp_path, overrides, match):
    data_dir = tmp_path / "data"
    data_dir.mkdir()
    data = _good(data_dir / "ok.hdf5")
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    if "DATA=negative" in overrides:
        data = _arrays_file(costs=lambda a: a - 1.0)(data_dir / "negative.hdf5")
    if "DATA=truncated" in overrides:
        data = _truncated(data_dir / "truncated.hdf5")
    task_file = dict(lengths=(30, 20, 40), obs_dim=28)  # PointCircle1's sizes
    if "DATA=no-safe" in overrides:
        arrays = make_arrays(**task_file)
        arrays["costs"] = arrays["costs"] * 0 + 5.0  # every episode far over the threshold of 25
        data = write_dsrl_file(data_dir / "no-safe.hdf5", arrays, metadata=_task_metadata())
    if "DATA=task" in overrides:  # a good PointCircle1 file
        data = write_dsrl_file(data_dir / "task.hdf5", make_arrays(**task_file), metadata=_task_metadata())
    if "DATA=big-actions" in overrides:
        arrays = make_arrays(**task_file)
        arrays["actions"] = arrays["actions"] * 1e6
        data = write_dsrl_file(data_dir / "big-actions.hdf5", arrays, metadata=_task_metadata())
    if "RUN=existing" in overrides:
        (run_dir / "results.json").write_text(json.dumps({"status": "finished"}))
    if "RUN=a-file" in overrides:
        run_dir.rmdir()
        run_dir.write_text("a file where the run directory should be")
    if "RUN=uncreatable" in overrides:
        run_dir = run_dir / "file" / "run"
        (run_dir.parent.parent / "file").write_text("")
    existing_run = "RUN=existing" in overrides
    run_before = _snapshot(run_dir) if existing_run else None
    if "RUN=blocked-checkpoints" in overrides:
        (run_dir / "checkpoints").write_text("a file where the folder should be")
    overrides = [o for o in overrides if not o.startswith(("DATA=", "RUN="))]
    before = _snapshot(data_dir)
    cmd = [
        sys.executable,
        str(ROOT / "recipes" / "spoildice_dsrl.py"),
        "preset=smoke",
        "progress=false",
        f"dataset.source=file:{data}",
        f"hydra.run.dir={run_dir}",
        *overrides,
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=ROOT)
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error: ")]
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert len(errors) == 1 and __import__("re").search(match, errors[0]), proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    assert _snapshot(data_dir) == before
    assert not (run_dir / "run.lock").exists()
    if existing_run:  # a refused command leaves an existing run as it was
        assert _snapshot(run_dir) == run_before


# -- the other commands: report, inspect, expert training -----------------------------------------------------


def _results_json(folder: Path, seed: int, steps: int = 100) -> None:
    metrics = {"normalized_feasible_return": 0.5, "normalized_cost": 0.5, "normalized_return": 0.5}
    folder.mkdir(parents=True)
    (folder / "results.json").write_text(
        json.dumps(
            {
                "status": "finished",
                "dataset": "d",
                "algo": "bc",
                "seed": seed,
                "aggregate": metrics,
                "total_seconds": 1.0,
                "evaluations": [{"step": 100, **metrics}],
            }
        )
    )
    (folder / "config.yaml").write_text(f"train:\n  steps: {steps}\n")


def _command_case(tmp_path: Path, case: str) -> list[str]:
    report, inspect = [str(ROOT / "recipes" / "report.py")], ["-m", "spoil_torchrl.inspect"]
    experts = [
        str(ROOT / "recipes" / "train_experts.py"),
        "progress=false",
        f"hydra.run.dir={tmp_path / 'expert'}",
    ]
    if case == "report: no such folder":
        return [*report, str(tmp_path / "nowhere")]
    if case == "report: only an unreadable results.json":
        (tmp_path / "run").mkdir()
        (tmp_path / "run" / "results.json").write_text("{not json")
        return [*report, str(tmp_path)]
    if case == "report: one dataset, two budgets":
        _results_json(tmp_path / "a", 0, steps=100)
        _results_json(tmp_path / "b", 1, steps=200)
        return [*report, str(tmp_path)]
    if case == "report: a seed twice":
        _results_json(tmp_path / "a", 0)
        _results_json(tmp_path / "b", 0)
        return [*report, str(tmp_path)]
    if case == "inspect: no such file":
        return [*inspect, str(tmp_path / "missing.mcap")]
    if case == "inspect: a text file":
        (tmp_path / "notes.mcap").write_text("not a rollout file")
        return [*inspect, str(tmp_path / "notes.mcap")]
    if case == "inspect: an empty file":
        (tmp_path / "empty.mcap").write_bytes(b"")
        return [*inspect, str(tmp_path / "empty.mcap")]
    if case == "experts: unknown task":
        return [*experts, "env_id=SafetyPointCircle9-v0"]
    if case == "experts: minibatch larger than the batch":
        return [*experts, "ppo.frames_per_batch=100", "ppo.minibatch_size=1000"]
    if case == "experts: more threads than cores":
        return [*experts, "threads=999"]
    if case == "experts: run directory is a file":
        (tmp_path / "expert").write_text("")
        return experts
    if case == "experts: resume with nothing to resume":
        (tmp_path / "expert").mkdir()
        (tmp_path / "expert" / "results.json").write_text('{"status": "training"}')
        return [*experts, "resume=true"]
    raise AssertionError(case)


COMMAND_CASES = {
    "report: no such folder": "no such folder",
    "report: only an unreadable results.json": "unreadable",
    "report: one dataset, two budgets": "different train settings",
    "report: a seed twice": "seed 0 of bc on d twice",
    "inspect: no such file": "missing.mcap",
    "inspect: a text file": "notes.mcap",
    "inspect: an empty file": "empty.mcap",
    "experts: unknown task": "unknown task 'SafetyPointCircle9-v0'",
    "experts: minibatch larger than the batch": "minibatch_size = 1000 is larger",
    "experts: more threads than cores": "threads = 999",
    "experts: run directory is a file": "is a file, not a run directory",
    "experts: resume with nothing to resume": "has no checkpoint",
}


@pytest.mark.parametrize("case", list(COMMAND_CASES))
def test_the_other_commands_report_user_errors_in_one_line(tmp_path, case):
    cmd = [sys.executable, *_command_case(tmp_path, case)]
    before = _snapshot(tmp_path)
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert proc.returncode != 0 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert __import__("re").search(COMMAND_CASES[case], proc.stderr), proc.stderr[-2000:]
    assert _snapshot(tmp_path) == before  # nothing written, nothing changed


def test_an_unknown_minari_dataset_says_where_it_was_looked_for(tmp_path, monkeypatch):
    pytest.importorskip("minari")
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    with pytest.raises(DatasetError, match=f"'nope/none-v0' is not in {tmp_path}"):
        load_episodes("minari:nope/none-v0")


@pytest.mark.parametrize(
    "change, match",
    [
        ({"lagrangian": "no"}, "ppo.lagrangian = 'no'"),
        ({"actor_lr": -1.0}, "ppo.actor_lr = -1.0"),
        ({"gamma": float("nan")}, "ppo.gamma = nan"),
        ({"epochs": 0}, "ppo.epochs = 0"),
    ],
)
def test_expert_settings_are_checked(change, match):
    from spoil_torchrl.experts import PPOConfig

    with pytest.raises(ValueError, match=match.replace(".", r"\.")):
        PPOConfig(**change)
