"""Rollout files written with the plain mcap API, as another tool would write them: read in any message order
and layout, and refused, with the reason, where their messages break the schemas, their steps do not match the
summary, or a channel on our topics is not JSON."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import CompressionType, Writer

from spoil_torchrl.eval import (
    EPISODE_SCHEMA,
    EPISODE_TOPIC,
    METADATA_NAME,
    STEP_SCHEMA,
    STEP_TOPIC,
    RolloutFileError,
    read_rollouts,
)


def _plain_writer(path: Path, chunked: bool):
    f = open(path, "wb")  # noqa: SIM115
    writer = Writer(
        f, use_chunking=chunked, compression=CompressionType.NONE if not chunked else CompressionType.LZ4
    )
    writer.start()
    step_schema = writer.register_schema("Step", SchemaEncoding.JSONSchema, json.dumps(STEP_SCHEMA).encode())
    episode_schema = writer.register_schema(
        "Episode", SchemaEncoding.JSONSchema, json.dumps(EPISODE_SCHEMA).encode()
    )
    channels = {
        "step": writer.register_channel(STEP_TOPIC, MessageEncoding.JSON, step_schema),
        "episode": writer.register_channel(EPISODE_TOPIC, MessageEncoding.JSON, episode_schema),
        "other": writer.register_channel("/camera", MessageEncoding.JSON, 0),
    }
    clock = iter(range(1, 10**6))

    def send(kind, message):
        t = next(clock)
        writer.add_message(channels[kind], log_time=t, data=json.dumps(message).encode(), publish_time=t)

    return f, writer, send


def _plain_step(episode, t, reward, cost, evaluation_step=None, done=False):
    message = {
        "episode": episode,
        "step": t,
        "observation": [float(t), float(episode)],
        "action": [0.5],
        "reward": reward,
        "cost": cost,
        "terminated": done,
        "truncated": False,
    }
    if evaluation_step is not None:
        message["evaluation_step"] = evaluation_step
    return message


@pytest.mark.parametrize("chunked", [True, False])
def test_reader_on_a_file_from_the_plain_mcap_writer(tmp_path, chunked):
    path = tmp_path / "plain.mcap"
    f, writer, send = _plain_writer(path, chunked)
    writer.add_metadata(METADATA_NAME, {"task": "handmade", "cost_threshold": "1"})
    writer.add_metadata("unrelated", {"x": "y"})
    # Episode 5 gives a minimal summary first (the reader recomputes the rest); episodes 5 and 2 interleave;
    # episode 9 never gets a summary; a message on another topic is ignored.
    send("episode", {"episode": 5, "length": 3})
    for t in range(3):
        send("step", _plain_step(5, t, reward=1.0, cost=[0.0, 1.0, 1.0][t], done=t == 2))
        send("step", _plain_step(2, t, reward=2.0, cost=0.0, evaluation_step=0))
        send("other", {"pixels": [1, 2, 3]})
    send("step", _plain_step(9, 0, reward=1.0, cost=0.0))
    send("episode", {"episode": 2, "evaluation_step": 0, "length": 3, "return": 6.0, "cost": 0.0})
    writer.finish()
    f.close()

    with pytest.warns(UserWarning, match="skipped 1 incomplete"):
        r = read_rollouts(path)
    assert r.finished and r.skipped == 1 and r.metadata == {"task": "handmade", "cost_threshold": "1"}
    s = r.episodes
    assert s["episode"].tolist() == [2, 5] and s["length"].tolist() == [3, 3]
    assert s["return"].tolist() == [6.0, 3.0] and s["cost"].tolist() == [0.0, 2.0]
    # episode 5 recomputed with the metadata's threshold 1: cumulative cost 0, 1, 2 exceeds it at t=2.
    assert s["feasible_return"].tolist() == [6.0, 2.0] and s["strict_feasible_return"].tolist() == [6.0, 1.0]
    assert s["terminated"].tolist() == [False, True]  # from the last step when the summary lacks it
    assert r.steps["observation"][1, :, 0].tolist() == [0.0, 1.0, 2.0]
    assert r.steps["next", "cumulative_cost"][1, :, 0].tolist() == [0.0, 1.0, 2.0]  # recomputed
    assert r.steps["action"].shape == (2, 3, 1)


def test_reader_rejects_messages_that_break_the_schema(tmp_path):
    cases = {
        "missing required field": ({"episode": 0, "step": 0, "reward": 1.0}, "missing required field"),
        "wrong type": ({**_plain_step(0, 0, 1.0, 0.0), "reward": "high"}, "'reward'"),
        "bad array": ({**_plain_step(0, 0, 1.0, 0.0), "observation": [1.0, "x"]}, "'observation'"),
        "negative step": ({**_plain_step(0, 0, 1.0, 0.0), "step": -1}, "'step'"),
    }
    for name, (message, match) in cases.items():
        path = tmp_path / f"{name.replace(' ', '_')}.mcap"
        f, writer, send = _plain_writer(path, chunked=True)
        send("step", message)
        writer.finish()
        f.close()
        with pytest.raises(RolloutFileError, match=match):
            read_rollouts(path)


@pytest.mark.parametrize(
    "messages, match",
    [
        ([("step", (0, 0)), ("episode", 2)], r"a summary of length 2 but steps \[0\]"),
        ([("step", (0, 0)), ("episode", 1), ("step", (0, 1))], "step 1 arrived after all 1 steps"),
        ([("step", (0, 0)), ("step", (0, 0)), ("episode", 1)], "step 0 appears twice"),
    ],
)
def test_reader_rejects_episodes_whose_steps_do_not_match_the_summary(tmp_path, messages, match):
    def write(path, finish):
        f, writer, send = _plain_writer(path, chunked=False)
        for kind, arg in messages:
            send(
                kind,
                _plain_step(*arg, reward=1.0, cost=0.0) if kind == "step" else {"episode": 0, "length": arg},
            )
        send("episode", {"episode": 1, "length": 0})  # a consistent (empty) episode
        if finish:
            writer.finish()
        f.close()

    write(tmp_path / "finished.mcap", finish=True)
    with pytest.raises(RolloutFileError, match=match):
        read_rollouts(tmp_path / "finished.mcap")
    # In a file that was not finished the bad episode is skipped, the others are kept.
    write(tmp_path / "unfinished.mcap", finish=False)
    with pytest.warns(UserWarning, match=match):
        r = read_rollouts(tmp_path / "unfinished.mcap")
    assert not r.finished and r.skipped == 1 and r.episodes["episode"].tolist() == [1]


def test_reader_rejects_a_non_json_channel_on_our_topic(tmp_path):
    path = tmp_path / "cdr.mcap"
    with open(path, "wb") as f:
        writer = Writer(f)
        writer.start()
        channel = writer.register_channel(STEP_TOPIC, "cdr", 0)
        writer.add_message(channel, log_time=0, data=b"\x00", publish_time=0)
        writer.finish()
    with pytest.raises(RolloutFileError, match="expected 'json'"):
        read_rollouts(path)
