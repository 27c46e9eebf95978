"""Rollout messages into episodes: the step and summary messages of a rollout file, checked against their
schemas, gathered per episode in whatever order they arrive, and packed into the tensors of
:class:`~spoil_torchrl.eval.mcap_reader.Rollouts` (:func:`~spoil_torchrl.eval.mcap_reader.read_rollouts`
reads the records and hands them here). Summary fields a file lacks are recomputed from the steps with
:mod:`spoil_torchrl.eval.metrics`.
"""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from mcap.records import Channel, Message
from mcap.well_known import MessageEncoding
from tensordict import TensorDict

from spoil_torchrl.eval.mcap_schemas import EPISODE_SCHEMA, STEP_SCHEMA, SUMMARY_FLOATS, RolloutFileError
from spoil_torchrl.eval.metrics import episode_cost, episode_return, feasible_return, strict_feasible_return

_LOG_TIME = "\0log_time"  # where a decoded message keeps its record's log time (not a JSON field name)


def _type_ok(value: Any, spec: Mapping[str, Any]) -> bool:
    kind = spec["type"]
    if kind == "number":
        return value is None or (isinstance(value, (int, float)) and not isinstance(value, bool))
    if kind == "integer":
        return isinstance(value, int) and not isinstance(value, bool) and value >= 0
    if kind == "boolean":
        return isinstance(value, bool)
    return isinstance(value, list) and all(_type_ok(v, spec["items"]) for v in value)


def _validate(message: Any, schema: Mapping[str, Any], where: str) -> dict:
    """``message`` checked against ``schema``: required fields present, known fields of the declared type."""
    if not isinstance(message, dict):
        raise RolloutFileError(f"{where}: expected a JSON object, got {type(message).__name__}")
    missing = [k for k in schema["required"] if k not in message]
    if missing:
        raise RolloutFileError(f"{where}: missing required field(s) {missing} (schema {schema['title']})")
    for name, spec in schema["properties"].items():
        if name in message and not _type_ok(message[name], spec):
            raise RolloutFileError(
                f"{where}: field {name!r} = {str(message[name])[:60]} is not of type {spec['type']}"
                + (" (or null)" if spec["type"] == "number" else "")
            )
    return message


def _float(value) -> float:
    return math.nan if value is None else float(value)


class EpisodeAssembly:
    """The step and episode messages of a rollout file, gathered into episodes as they arrive (in any order):
    an episode is packed into tensors once its summary and all its steps are in."""

    def __init__(self, path: Path, step_topic: str, episode_topic: str) -> None:
        self.path, self.step_topic, self.episode_topic = path, step_topic, episode_topic
        self.channels: dict[int, str] = {}  # channel id -> "step" | "episode"
        self.pending: dict[
            tuple[int, int], dict[int, dict]
        ] = {}  # step messages of episodes not complete yet
        self.summaries: dict[tuple[int, int], dict] = {}
        self.packed: dict[tuple[int, int], _Episode] = {}
        self.inconsistent: dict[tuple[int, int], str] = {}

    def add_channel(self, record: Channel) -> None:
        if record.message_encoding != MessageEncoding.JSON:
            raise RolloutFileError(
                f"{self.path}: channel {record.topic} has message encoding {record.message_encoding!r}, "
                "expected 'json'"
            )
        self.channels[record.id] = "step" if record.topic == self.step_topic else "episode"

    def add_message(self, record: Message) -> None:
        kind = self.channels[record.channel_id]
        topic = self.step_topic if kind == "step" else self.episode_topic
        where = f"{self.path}: {topic} message at log time {record.log_time}"
        try:
            message = json.loads(record.data)
        except (json.JSONDecodeError, UnicodeDecodeError) as err:
            raise RolloutFileError(f"{where}: not valid JSON ({err})") from err
        _validate(message, STEP_SCHEMA if kind == "step" else EPISODE_SCHEMA, where)
        message[_LOG_TIME] = record.log_time
        key = (int(message.get("evaluation_step", 0)), int(message["episode"]))
        if kind == "step":
            t = message["step"]
            if key in self.packed:
                self.inconsistent[key] = (
                    f"step {t} arrived after all {len(self.packed[key])} steps of its summary"
                )
            elif t in self.pending.get(key, {}):
                self.inconsistent[key] = f"step {t} appears twice"
            self.pending.setdefault(key, {})[t] = message
        elif key in self.summaries:
            raise RolloutFileError(f"{where}: episode {key[1]} has two summaries")
        else:
            self.summaries[key] = message
        steps = self.pending.get(key, {})
        n = self.summaries[key]["length"] if key in self.summaries else -1
        if len(steps) == n and max(steps, default=-1) == n - 1 and key not in self.inconsistent:
            self.packed[key] = _pack(self.path, [steps[t] for t in sorted(steps)], n)
            self.pending.pop(key, None)

    def drop_incomplete(self, finished: bool) -> int:
        """Drop the episodes whose steps do not match their summary (an error in a ``finished`` file, else a
        warning) and count them with those that never got a summary."""
        no_summary = sorted(set(self.pending) - set(self.summaries))  # in progress when the writer stopped
        skipped = len(no_summary)
        for key in sorted(self.summaries):
            n, have = self.summaries[key]["length"], sorted(self.pending.get(key, {}))
            if key in self.inconsistent or (key not in self.packed and have != list(range(n))):
                problem = (
                    f"{self.path}: episode {key[1]} (evaluation step {key[0]}): "
                    + self.inconsistent.get(
                        key, f"a summary of length {n} but steps {have[:10]}{'...' if len(have) > 10 else ''}"
                    )
                )
                if finished:
                    raise RolloutFileError(problem)
                warnings.warn(problem + " (skipped)", stacklevel=3)
                self.packed.pop(key, None)
                skipped += 1
        if no_summary:
            warnings.warn(
                f"{self.path}: skipped {len(no_summary)} incomplete episode(s) (steps without a summary)",
                stacklevel=3,
            )
        return skipped


@dataclass
class _Episode:
    """One episode's steps as tensors: observation / action ``[n, d]`` float32, the rest ``[n]``."""

    observation: torch.Tensor
    action: torch.Tensor
    reward: torch.Tensor  # float64
    cost: torch.Tensor  # float64
    cumulative_cost: torch.Tensor  # float64
    terminated: torch.Tensor  # bool
    truncated: torch.Tensor  # bool
    log_time: torch.Tensor  # int64

    def __len__(self) -> int:
        return self.reward.shape[0]


def _pack(path: Path, messages: list[dict], length: int) -> _Episode:
    """The step messages ``0..length-1`` of one episode (already validated) as an :class:`_Episode`."""

    def array(name: str) -> torch.Tensor:
        rows = [[_float(v) for v in m[name]] for m in messages]
        if len({len(r) for r in rows}) > 1:
            raise RolloutFileError(f"{path}: '{name}' arrays of one episode have different lengths")
        return torch.tensor(rows, dtype=torch.float32).reshape(length, -1) if length else torch.zeros(0, 0)

    def scalars(name: str, dtype=torch.float64) -> torch.Tensor:
        return torch.tensor([_float(m[name]) for m in messages], dtype=dtype).reshape(length)

    cost = scalars("cost")
    running = cost.cumsum(0)
    if all("cumulative_cost" in m for m in messages):
        cumulative = scalars("cumulative_cost")
    else:
        cumulative = running
    return _Episode(
        observation=array("observation"),
        action=array("action"),
        reward=scalars("reward"),
        cost=cost,
        cumulative_cost=cumulative,
        terminated=torch.tensor([m["terminated"] for m in messages], dtype=torch.bool).reshape(length),
        truncated=torch.tensor([m["truncated"] for m in messages], dtype=torch.bool).reshape(length),
        log_time=torch.tensor([m[_LOG_TIME] for m in messages], dtype=torch.int64).reshape(length),
    )


def steps_tensordict(path: Path, keys: list[tuple[int, int]], episodes: list[_Episode]) -> TensorDict:
    n_ep, horizon = len(episodes), max((len(e) for e in episodes), default=0)
    dims = {}
    for name in ("observation", "action"):
        sizes = {getattr(e, name).shape[-1] for e in episodes if len(e)}
        if len(sizes) > 1:
            raise RolloutFileError(f"{path}: '{name}' arrays have different lengths {sorted(sizes)}")
        dims[name] = sizes.pop() if sizes else 0
    obs = torch.zeros(n_ep, horizon, dims["observation"], dtype=torch.float32)
    act = torch.zeros(n_ep, horizon, dims["action"], dtype=torch.float32)
    scalars = {
        k: torch.zeros(n_ep, horizon, 1, dtype=torch.float32) for k in ("reward", "cost", "cumulative_cost")
    }
    flags = {k: torch.zeros(n_ep, horizon, 1, dtype=torch.bool) for k in ("terminated", "truncated")}
    mask = torch.zeros(n_ep, horizon, dtype=torch.bool)
    log_time = torch.zeros(n_ep, horizon, dtype=torch.int64)
    for e, episode in enumerate(episodes):
        n = len(episode)
        if n == 0:
            continue
        obs[e, :n], act[e, :n] = episode.observation, episode.action
        for name, out in (*scalars.items(), *flags.items()):
            out[e, :n, 0] = getattr(episode, name)
        mask[e, :n] = True
        log_time[e, :n] = episode.log_time

    def per_row(values: list[int]) -> torch.Tensor:
        return torch.tensor(values, dtype=torch.int64).reshape(n_ep, 1).expand(n_ep, horizon).clone()

    return TensorDict(
        {
            "observation": obs,
            "action": act,
            "next": {**scalars, **flags, "done": flags["terminated"] | flags["truncated"]},
            "step": torch.arange(horizon).expand(n_ep, horizon).clone(),
            "episode": per_row([k[1] for k in keys]),
            "evaluation_step": per_row([k[0] for k in keys]),
            "mask": mask,
            "log_time": log_time,
        },
        batch_size=[n_ep, horizon],
    )


def _summary_value(name: str, summary: Mapping[str, Any], episode: _Episode, threshold: float) -> float:
    """A summary field as stored, or recomputed from the steps when the file lacks it (NaN if undefined)."""
    if name in summary:
        return _float(summary[name])
    if name == "return":
        return episode_return(episode.reward)
    if name == "cost":
        return episode_cost(episode.cost)
    if bool(torch.isnan(episode.cost).any()) or (name == "feasible_return" and math.isnan(threshold)):
        return math.nan
    if name == "feasible_return":
        return feasible_return(episode.reward, episode.cost, threshold)
    return strict_feasible_return(episode.reward, episode.cost)


def episodes_tensordict(
    keys: list[tuple[int, int]], summaries: list[dict], episodes: list[_Episode], default_threshold: float
) -> TensorDict:
    n = len(keys)
    floats, flags = [], []
    for summary, episode in zip(summaries, episodes, strict=True):
        threshold = _float(summary["cost_threshold"]) if "cost_threshold" in summary else default_threshold
        floats.append([_summary_value(name, summary, episode, threshold) for name in SUMMARY_FLOATS[:-1]])
        floats[-1].append(threshold)
        flags.append(
            [
                bool(summary[name]) if name in summary else bool(len(episode) and getattr(episode, name)[-1])
                for name in ("terminated", "truncated")
            ]
        )
    floats = torch.tensor(floats, dtype=torch.float64).reshape(n, len(SUMMARY_FLOATS))
    flags = torch.tensor(flags, dtype=torch.bool).reshape(n, 2)
    out = {name: floats[:, i] for i, name in enumerate(SUMMARY_FLOATS)}
    out["terminated"], out["truncated"] = flags[:, 0], flags[:, 1]
    out["episode"] = torch.tensor([k[1] for k in keys], dtype=torch.int64).reshape(n)
    out["evaluation_step"] = torch.tensor([k[0] for k in keys], dtype=torch.int64).reshape(n)
    out["length"] = torch.tensor([len(e) for e in episodes], dtype=torch.int64).reshape(n)
    out["log_time"] = torch.tensor([s[_LOG_TIME] for s in summaries], dtype=torch.int64).reshape(n)
    return TensorDict(out, batch_size=[n])
