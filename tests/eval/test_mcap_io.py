"""MCAP rollout files: round trip, no NaN in JSON, salvage of files cut mid-write (files from the plain mcap
API: test_mcap_plain_files.py)."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import pytest
import torch
from mcap.reader import make_reader
from mcap.well_known import MessageEncoding, SchemaEncoding
from tensordict import TensorDict

from spoil_torchrl.eval import (
    EPISODE_SCHEMA,
    EPISODE_TOPIC,
    METADATA_NAME,
    STEP_SCHEMA,
    STEP_TOPIC,
    RolloutFileError,
    RolloutWriter,
    episode_metrics,
    read_rollouts,
)

ROOT = Path(__file__).resolve().parents[2]
OBS_DIM, ACT_DIM, THRESHOLD = 3, 2, 2.0
METADATA = {
    "task": "OfflinePointCircle1Gymnasium-v0",
    "algo": "spoildice",
    "seed": 7,
    "config_hash": "abc123",
}


def make_episode(length: int, seed: int) -> TensorDict:
    """A TorchRL-style rollout of one episode (batch size [T]) with hand-readable rewards and costs."""
    g = torch.Generator().manual_seed(seed)
    terminated = torch.zeros(length, 1, dtype=torch.bool)
    truncated = torch.zeros(length, 1, dtype=torch.bool)
    (terminated if seed % 2 else truncated)[-1] = True
    return TensorDict(
        {
            "observation": torch.randn(length, OBS_DIM, generator=g),
            "action": torch.rand(length, ACT_DIM, generator=g) * 2 - 1,
            "next": {
                "reward": torch.arange(1, length + 1, dtype=torch.float32).unsqueeze(-1),
                "cost": (torch.arange(length) % 2).float().unsqueeze(-1),  # 0, 1, 0, 1, ...
                "terminated": terminated,
                "truncated": truncated,
            },
        },
        [length],
    )


LENGTHS = (4, 7, 5, 6)
EPISODES = [make_episode(n, seed) for seed, n in enumerate(LENGTHS)]


def write_file(path: Path, episodes=EPISODES, finish: bool = True, **kwargs) -> RolloutWriter:
    writer = RolloutWriter(path, cost_threshold=THRESHOLD, metadata=METADATA, **kwargs)
    for i, ep in enumerate(episodes):
        writer.write_episode(ep, evaluation_step=1000 * (i // 2))
    if finish:
        writer.finish()
    return writer


def check_episodes(rollouts, indices):
    """The rollouts hold exactly EPISODES[indices], step for step."""
    assert rollouts.episodes["episode"].tolist() == list(indices)
    lengths = [LENGTHS[i] for i in indices]
    assert rollouts.episodes["length"].tolist() == lengths
    assert rollouts.steps.batch_size == (len(indices), max(lengths, default=0))
    for row, i in enumerate(indices):
        ep, n = EPISODES[i], LENGTHS[i]
        got = rollouts.steps[row]
        assert got["mask"].tolist() == [True] * n + [False] * (rollouts.steps.shape[1] - n)
        assert torch.equal(got["observation"][:n], ep["observation"])  # float32 survives JSON exactly
        assert torch.equal(got["action"][:n], ep["action"])
        for key in ("reward", "cost", "terminated", "truncated"):
            assert torch.equal(got["next", key][:n], ep["next", key]), key
        assert torch.equal(got["next", "cumulative_cost"][:n], ep["next", "cost"].cumsum(0))
        assert got["step"][:n].tolist() == list(range(n))
        assert (got["episode"] == i).all() and (got["evaluation_step"] == 1000 * (i // 2)).all()
        assert not got["mask"][n:].any() and (got["next", "reward"][n:] == 0).all()


def test_round_trip(tmp_path):
    path = tmp_path / "rollouts.mcap"
    before = time.time_ns()
    write_file(path)
    after = time.time_ns()
    r = read_rollouts(path)
    assert r.finished and r.skipped == 0 and r.stop_reason is None
    check_episodes(r, range(4))
    # Summaries, by hand: rewards 1..n, costs 0,1,0,1,... (cumulative 0,1,1,2,2,3,3), threshold 2.
    # Episode of length 7: return 28, cost 3, cumulative cost first exceeds 2 at t=5 -> 1+..+5 = 15,
    # first positive cost at t=1 -> 1.
    s = r.episodes
    assert s["return"].tolist() == [10.0, 28.0, 15.0, 21.0]
    assert s["cost"].tolist() == [2.0, 3.0, 2.0, 3.0]
    assert s["feasible_return"].tolist() == [10.0, 15.0, 15.0, 15.0]
    assert s["strict_feasible_return"].tolist() == [1.0] * 4
    assert s["cost_threshold"].tolist() == [THRESHOLD] * 4
    assert s["evaluation_step"].tolist() == [0, 0, 1000, 1000]
    assert s["terminated"].tolist() == [False, True, False, True]
    assert s["truncated"].tolist() == [True, False, True, False]
    # The summaries are the metric functions on the stored steps.
    m = episode_metrics(r.steps, THRESHOLD)
    for key in ("return", "cost", "feasible_return", "strict_feasible_return", "length"):
        assert m[key].tolist() == s[key].tolist(), key
    # Metadata: strings; non-strings as JSON text; the threshold and writer are added.
    assert r.metadata["task"] == METADATA["task"] and r.metadata["seed"] == "7"
    assert r.metadata["config_hash"] == "abc123" and float(r.metadata["cost_threshold"]) == THRESHOLD
    assert r.metadata["writer"].startswith("spoil_torchrl")
    # The file is valid MCAP for the seeking reader too; log times are ns, non-decreasing.
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary.statistics.message_count == sum(LENGTHS) + len(LENGTHS)
        encodings = {
            c.topic: (c.message_encoding, summary.schemas[c.schema_id]) for c in summary.channels.values()
        }
        assert [m.name for m in reader.iter_metadata()] == [METADATA_NAME]
        times = [message.log_time for _, _, message in reader.iter_messages(log_time_order=False)]
    # simulation time from the writer's start: strictly increasing, the first at the (wall-clock) start
    assert times == sorted(set(times)) and before <= times[0] <= after
    for topic, schema in ((STEP_TOPIC, STEP_SCHEMA), (EPISODE_TOPIC, EPISODE_SCHEMA)):
        message_encoding, stored = encodings[topic]
        assert message_encoding == MessageEncoding.JSON and stored.encoding == SchemaEncoding.JSONSchema
        assert json.loads(stored.data) == schema


def _foxglove_parsable(schema: dict) -> bool:
    """The subset Foxglove's JSON-schema parser accepts: object root, one string type per field."""
    simple = {"boolean", "string", "number", "integer"}
    if schema.get("type") != "object":
        return False
    for spec in schema["properties"].values():
        kind = spec.get("type")
        if kind == "array":
            if spec["items"].get("type") not in simple:
                return False
        elif kind == "object":
            if not _foxglove_parsable(spec):
                return False
        elif kind not in simple:  # a union such as ["number", "null"] is rejected
            return False
    return True


def test_schemas_are_foxglove_plottable():
    assert _foxglove_parsable(STEP_SCHEMA) and _foxglove_parsable(EPISODE_SCHEMA)
    for field in ("observation", "action"):
        assert STEP_SCHEMA["properties"][field] == {
            "type": "array",
            "items": {"type": "number"},
            "description": STEP_SCHEMA["properties"][field]["description"],
        }


def test_non_finite_numbers_become_null(tmp_path):
    path = tmp_path / "nan.mcap"
    with RolloutWriter(path, cost_threshold=1.0) as writer:
        writer.add_step([math.nan, math.inf, 1.0], [-math.inf], reward=2.0, cost=0.0)
        writer.add_step([0.0, 0.0, 0.0], [0.0], reward=math.nan, cost=math.inf)
        summary = writer.end_episode()
    # return NaN and cost inf are null; the cost first exceeds the threshold at t=1: feasible return r_0.
    assert summary["return"] is None and summary["cost"] is None and summary["feasible_return"] == 2.0

    def no_constants(name):
        raise AssertionError(f"{name} written into JSON")

    with open(path, "rb") as f:
        messages = [
            json.loads(m.data, parse_constant=no_constants) for _, _, m in make_reader(f).iter_messages()
        ]
    assert messages[0]["observation"] == [None, None, 1.0] and messages[0]["action"] == [None]
    assert (
        messages[1]["reward"] is None
        and messages[1]["cost"] is None
        and messages[1]["cumulative_cost"] is None
    )
    assert messages[2]["return"] is None and messages[2]["cost"] is None
    r = read_rollouts(path)
    assert math.isnan(r.steps["observation"][0, 0, 0]) and math.isnan(r.steps["observation"][0, 0, 1])
    assert math.isnan(r.steps["action"][0, 0, 0]) and math.isnan(r.steps["next", "reward"][0, 1, 0])
    assert math.isnan(r.episodes["return"][0]) and r.episodes["feasible_return"][0] == 2.0


def _chunk_ends(path: Path) -> list[int]:
    with open(path, "rb") as f:
        return sorted(
            c.chunk_start_offset + c.chunk_length for c in make_reader(f).get_summary().chunk_indexes
        )


def test_salvage_of_files_cut_mid_write(tmp_path):
    full = tmp_path / "full.mcap"
    write_file(full)
    data = full.read_bytes()
    ends = _chunk_ends(full)
    assert len(ends) == len(EPISODES)  # one chunk per episode (flushed at each episode end)
    first_chunk = ends[0] - 100
    cuts = {8, 20, first_chunk, len(data) - 1, len(data) - 20, (ends[-1] + len(data)) // 2}
    for end in ends:
        cuts |= {end - 1, end, end + 1, end - 200}
    for cut in sorted(cuts):
        cut_file = tmp_path / f"cut_{cut}.mcap"
        cut_file.write_bytes(data[:cut])
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # a clean cut leaves no half episode to warn about
            r = read_rollouts(cut_file)
        expected = [i for i, end in enumerate(ends) if end <= cut]
        check_episodes(r, expected)
        assert r.skipped == 0
        assert r.finished == (cut >= len(data) - 8), cut  # only the closing magic may be missing
        if not r.finished:
            assert "ends before the MCAP footer" in r.stop_reason
        if cut >= first_chunk:  # metadata precede the first chunk
            assert r.metadata["seed"] == "7"
    for cut in (0, 5):
        (tmp_path / "tiny.mcap").write_bytes(data[:cut])
        with pytest.raises(RolloutFileError, match="not an MCAP file"):
            read_rollouts(tmp_path / "tiny.mcap")


def test_salvage_stops_at_a_corrupt_chunk(tmp_path):
    path = tmp_path / "corrupt.mcap"
    write_file(path, compression="none")
    ends = _chunk_ends(path)
    data = bytearray(path.read_bytes())
    data[ends[2] - 30] ^= 0xFF  # inside episode 2's chunk: CRC mismatch
    path.write_bytes(bytes(data))
    r = read_rollouts(path)
    check_episodes(r, [0, 1])
    assert not r.finished and "crc" in r.stop_reason.lower()


KILLED_WRITER = """
import os, signal, sys
sys.path.insert(0, {root!r})
from tests.eval.test_mcap_io import EPISODES, METADATA, THRESHOLD
from spoil_torchrl.eval import RolloutWriter
writer = RolloutWriter({path!r}, cost_threshold=THRESHOLD, metadata=METADATA)
for i, ep in enumerate(EPISODES[:3]):
    writer.write_episode(ep, evaluation_step=1000 * (i // 2))
for t in range(3):  # a fourth episode in progress
    writer.add_step([0.0] * 3, [0.0] * 2, reward=1.0, cost=0.0, evaluation_step=1000)
os.kill(os.getpid(), signal.SIGKILL)
"""


def test_salvage_after_the_writer_is_killed(tmp_path):
    path = tmp_path / "killed.mcap"
    proc = subprocess.run([sys.executable, "-c", KILLED_WRITER.format(root=str(ROOT), path=str(path))])
    assert proc.returncode == -signal.SIGKILL
    r = read_rollouts(path)
    assert not r.finished
    check_episodes(r, [0, 1, 2])
    assert r.metadata["task"] == METADATA["task"]


def test_finish_with_an_episode_in_progress(tmp_path):
    path = tmp_path / "partial.mcap"
    writer = write_file(path, EPISODES[:2], finish=False)
    writer.add_step([0.0] * 3, [0.0] * 2, reward=1.0, cost=0.0)
    with pytest.warns(UserWarning, match="no end_episode"):
        writer.finish()
    with pytest.warns(UserWarning, match="skipped 1 incomplete"):
        r = read_rollouts(path)
    assert r.finished and r.skipped == 1
    check_episodes(r, [0, 1])


def test_exception_inside_the_with_block_keeps_complete_episodes(tmp_path):
    path = tmp_path / "raised.mcap"
    with pytest.raises(RuntimeError, match="boom"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with RolloutWriter(path, cost_threshold=THRESHOLD) as writer:
            writer.write_episode(EPISODES[0])
            writer.add_step([0.0] * 3, [0.0] * 2, reward=1.0, cost=0.0)
            raise RuntimeError("boom")
    with pytest.warns(UserWarning, match="incomplete"):
        r = read_rollouts(path)
    assert r.finished and r.episodes["episode"].tolist() == [0]


def test_writer_errors(tmp_path):
    with pytest.raises(ValueError, match="cost_threshold"):
        RolloutWriter(tmp_path / "a.mcap", cost_threshold=-1.0)
    with pytest.raises(ValueError, match="compression"):
        RolloutWriter(tmp_path / "b.mcap", cost_threshold=1.0, compression="gzip")
    with pytest.raises(ValueError, match="differs"):
        RolloutWriter(tmp_path / "c.mcap", cost_threshold=1.0, metadata={"cost_threshold": 2})
    with RolloutWriter(tmp_path / "d.mcap", cost_threshold=1.0) as writer:
        with pytest.raises(RuntimeError, match="without any add_step"):
            writer.end_episode()
        writer.add_step([0.0], [0.0], reward=0.0, cost=0.0, evaluation_step=5)
        with pytest.raises(ValueError, match="evaluation_step=5"):
            writer.add_step([0.0], [0.0], reward=0.0, cost=0.0, evaluation_step=6)
        with pytest.raises(RuntimeError, match="in progress"):
            writer.write_episode(EPISODES[0])
        writer.end_episode()
        with pytest.raises(KeyError, match="action"):
            writer.write_episode(EPISODES[0].exclude("action"))
        assert writer.episodes_written == 1
    with pytest.raises(RuntimeError, match="finished"):
        writer.add_step([0.0], [0.0], reward=0.0, cost=0.0)


def test_reader_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such rollout file"):
        read_rollouts(tmp_path / "missing.mcap")
    (tmp_path / "text.mcap").write_text("hello, not mcap")
    with pytest.raises(RolloutFileError, match="not an MCAP file"):
        read_rollouts(tmp_path / "text.mcap")


# -- files written with the plain mcap Writer API ---------------------------------------------------------------


def test_empty_file_from_our_writer(tmp_path):
    path = tmp_path / "empty.mcap"
    RolloutWriter(path, cost_threshold=0.0, metadata={"seed": 1}).finish()
    r = read_rollouts(path)
    assert r.finished and r.steps.batch_size == (0, 0) and r.episodes.batch_size == (0,)
    assert r.metadata["seed"] == "1" and os.path.getsize(path) > 0
