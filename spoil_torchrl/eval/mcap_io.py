"""Evaluation rollouts as MCAP files: :class:`RolloutWriter` and :func:`read_rollouts`.

File layout (any MCAP writer that follows it can be read, not only :class:`RolloutWriter`):

* topic ``/eval/step`` (:data:`STEP_TOPIC`), message encoding ``json``, schema :data:`STEP_SCHEMA`
  (``jsonschema`` encoding): one message per environment step with ``evaluation_step``, ``episode``, ``step``,
  ``observation`` and ``action`` (flat number arrays), ``reward``, ``cost``, ``cumulative_cost`` (the
  episode's cost up to and including this step), ``terminated`` and ``truncated``;
* topic ``/eval/episode`` (:data:`EPISODE_TOPIC`), schema :data:`EPISODE_SCHEMA`: one summary per finished
  episode (``return``, ``cost``, ``feasible_return``, ``strict_feasible_return``, ``length``, the
  ``cost_threshold`` used, the final ``terminated`` / ``truncated`` flags), computed with
  :mod:`spoil_torchrl.eval.metrics`;
* an MCAP metadata record named ``spoil_torchrl.run`` (:data:`METADATA_NAME`) with the run's metadata
  (task, algo, seed, config hash, ...; string values).

An episode is identified by ``(evaluation_step, episode)`` and is *complete* iff its summary message exists:
the reader returns complete episodes only. Log and publish times are nanoseconds since the Unix epoch.

**No NaN in JSON.** NaN is not valid JSON, so every non-finite number (NaN, +inf, -inf) is written as
``null`` and read back as NaN (the sign of an infinity is lost). The schemas still declare plain ``number``
types, because Foxglove's JSON-schema parser rejects type unions such as ``["number", "null"]``: a ``null``
is the one value outside the declared schema, and plots show it as a gap.

**Crash safety.** :class:`RolloutWriter` closes the current chunk and flushes the file at every episode end
(an episode's messages never share a chunk with the next episode's), so a run killed at any point leaves a
file whose complete episodes :func:`read_rollouts` salvages: it reads the file with mcap's
:class:`~mcap.stream_reader.StreamReader` (chunk CRCs checked) and stops at the first truncated or corrupt
record, so it needs neither the footer nor the summary section. The flush hands the data to the operating
system (it survives a killed process); it does not ``fsync`` (a power loss may still lose recent episodes).
"""

from __future__ import annotations

import json
import math
import os
import struct
import time
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from mcap.exceptions import EndOfFile
from mcap.records import Channel, Footer, Message, Metadata
from mcap.stream_reader import StreamReader
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import CompressionType, Writer
from tensordict import TensorDict, TensorDictBase

import spoil_torchrl
from spoil_torchrl.eval.metrics import (
    episode_cost,
    episode_return,
    feasible_return,
    strict_feasible_return,
)

STEP_TOPIC = "/eval/step"
EPISODE_TOPIC = "/eval/episode"
METADATA_NAME = "spoil_torchrl.run"
MCAP_MAGIC = b"\x89MCAP0\r\n"

_NUMBER = {"type": "number"}
_INTEGER = {"type": "integer", "minimum": 0}
_BOOLEAN = {"type": "boolean"}

#: JSON schema of a ``/eval/step`` message (non-finite numbers are written as ``null``; see the module doc).
STEP_SCHEMA: dict[str, Any] = {
    "title": "spoil_torchrl.EvalStep",
    "description": "One environment step of an evaluation episode.",
    "type": "object",
    "properties": {
        "evaluation_step": {**_INTEGER, "description": "training step at which the evaluation ran"},
        "episode": {**_INTEGER, "description": "episode index in the file"},
        "step": {**_INTEGER, "description": "time step t within the episode, from 0"},
        "observation": {"type": "array", "items": _NUMBER, "description": "s_t, flattened"},
        "action": {"type": "array", "items": _NUMBER, "description": "a_t, flattened"},
        "reward": {**_NUMBER, "description": "r_t"},
        "cost": {**_NUMBER, "description": "c_t"},
        "cumulative_cost": {**_NUMBER, "description": "sum of c_0..c_t"},
        "terminated": {**_BOOLEAN, "description": "the episode ended in a terminal state after this step"},
        "truncated": {**_BOOLEAN, "description": "the episode was cut (time limit) after this step"},
    },
    "required": ["episode", "step", "observation", "action", "reward", "cost", "terminated", "truncated"],
}

#: JSON schema of a ``/eval/episode`` summary message.
EPISODE_SCHEMA: dict[str, Any] = {
    "title": "spoil_torchrl.EvalEpisode",
    "description": "Summary of one finished evaluation episode (spoil_torchrl.eval.metrics).",
    "type": "object",
    "properties": {
        "evaluation_step": _INTEGER,
        "episode": _INTEGER,
        "length": {**_INTEGER, "description": "number of steps"},
        "return": {**_NUMBER, "description": "undiscounted return"},
        "cost": {**_NUMBER, "description": "undiscounted episode cost"},
        "feasible_return": {
            **_NUMBER,
            "description": "reward before the cumulative cost exceeds the threshold",
        },
        "strict_feasible_return": {**_NUMBER, "description": "reward before the first positive cost"},
        "cost_threshold": {**_NUMBER, "description": "threshold used for feasible_return"},
        "terminated": _BOOLEAN,
        "truncated": _BOOLEAN,
    },
    "required": ["episode", "length"],
}

SUMMARY_FLOATS = ("return", "cost", "feasible_return", "strict_feasible_return", "cost_threshold")


class RolloutFileError(ValueError):
    """A rollout file that cannot be read: missing, not MCAP, or with messages that do not follow the schemas."""


def _finite(x: float) -> float | None:
    """``x`` as a float, or ``None`` (JSON ``null``) when it is NaN or infinite."""
    x = float(x)
    return x if math.isfinite(x) else None


def _numbers(values) -> list[float | None]:
    return [_finite(v) for v in torch.as_tensor(values, dtype=torch.float64).reshape(-1).tolist()]


def _dumps(obj: Mapping[str, Any]) -> bytes:
    return json.dumps(obj, allow_nan=False, separators=(",", ":")).encode()


def _metadata_value(value: Any) -> str:
    return value if isinstance(value, str) else json.dumps(value, allow_nan=False, default=str)


class RolloutWriter:
    """Writes evaluation episodes to an MCAP file (see the module doc for the layout); a context manager.

    Step by step with :meth:`add_step` then :meth:`end_episode`, or a whole TorchRL rollout with
    :meth:`write_episode`. Every :meth:`end_episode` writes the summary and flushes, so a killed run keeps its
    complete episodes. Leaving the ``with`` block (also through an exception) calls :meth:`finish`; an episode
    in progress is then left without a summary, and readers skip it.

    Args:
        path: the ``.mcap`` file to create (overwritten; parent folders are created).
        cost_threshold: the task's cost threshold, used for the summaries' feasible return.
        metadata: run metadata (task, algo, seed, config hash, ...); non-string values are stored as JSON
            text. ``cost_threshold`` and ``writer`` entries are added.
        clock: returns the log time in ns (default: wall clock, kept non-decreasing).
        compression: ``"zstd"`` (default), ``"lz4"`` or ``"none"``.

    Episode indices run over the whole file (0, 1, 2, ... across evaluations); each episode also carries the
    ``evaluation_step`` given to its steps.

    Examples:
        >>> import tempfile
        >>> path = Path(tempfile.mkdtemp()) / "rollouts.mcap"
        >>> with RolloutWriter(path, cost_threshold=1.0, metadata={"task": "demo", "seed": 0}) as writer:
        ...     for t in range(3):
        ...         writer.add_step([0.1 * t, 0.2], [1.0], reward=1.0, cost=float(t > 0), evaluation_step=500)
        ...     writer.end_episode()["feasible_return"]  # cumulative cost 0, 1, 2 exceeds 1 at t=2
        2.0
        >>> rollouts = read_rollouts(path)
        >>> rollouts.steps.batch_size, rollouts.episodes["return"].tolist(), rollouts.metadata["seed"]
        (torch.Size([1, 3]), [3.0], '0')
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        cost_threshold: float,
        metadata: Mapping[str, Any] | None = None,
        clock: Callable[[], int] = time.time_ns,
        compression: str = "zstd",
    ):
        cost_threshold = float(cost_threshold)
        if not math.isfinite(cost_threshold) or cost_threshold < 0:
            raise ValueError(f"cost_threshold must be a finite number >= 0, got {cost_threshold}")
        compressions = {
            "zstd": CompressionType.ZSTD,
            "lz4": CompressionType.LZ4,
            "none": CompressionType.NONE,
        }
        if compression not in compressions:
            raise ValueError(f"compression must be one of {sorted(compressions)}, got {compression!r}")
        meta = {str(k): _metadata_value(v) for k, v in (metadata or {}).items()}
        if "cost_threshold" in meta and float(meta["cost_threshold"]) != cost_threshold:
            raise ValueError(
                f"metadata cost_threshold={meta['cost_threshold']} differs from {cost_threshold}"
            )
        meta["cost_threshold"] = json.dumps(cost_threshold)
        meta.setdefault("writer", f"spoil_torchrl {spoil_torchrl.__version__}")

        self.path = Path(path)
        self.cost_threshold = cost_threshold
        self.metadata = meta
        self._clock = clock
        self._last_time = 0
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._stream = open(self.path, "wb")  # closed by finish()
        try:
            self._writer = Writer(self._stream, compression=compressions[compression])
            self._writer.start(library=f"spoil_torchrl/{spoil_torchrl.__version__}")
            self._writer.add_metadata(METADATA_NAME, meta)
            self._channels = {}
            for topic, schema in ((STEP_TOPIC, STEP_SCHEMA), (EPISODE_TOPIC, EPISODE_SCHEMA)):
                schema_id = self._writer.register_schema(
                    schema["title"], SchemaEncoding.JSONSchema, json.dumps(schema).encode()
                )
                self._channels[topic] = self._writer.register_channel(topic, MessageEncoding.JSON, schema_id)
            self._writer.flush()  # header and metadata reach the disk before the first episode
        except BaseException:
            self._stream.close()
            raise
        self._finished = False
        self._episode = 0
        self._reset_episode()

    # -- episodes ---------------------------------------------------------------------------------------------

    def _reset_episode(self) -> None:
        self._rewards: list[float] = []
        self._costs: list[float] = []
        self._flags = (False, False)
        self._evaluation_step: int | None = None

    @property
    def episodes_written(self) -> int:
        """Number of complete episodes written so far."""
        return self._episode

    def _now(self) -> int:
        self._last_time = max(int(self._clock()), self._last_time)
        return self._last_time

    def _publish(self, topic: str, message: Mapping[str, Any]) -> None:
        now = self._now()
        self._writer.add_message(self._channels[topic], log_time=now, data=_dumps(message), publish_time=now)

    def add_step(
        self,
        observation,
        action,
        reward: float,
        cost: float,
        *,
        terminated: bool = False,
        truncated: bool = False,
        evaluation_step: int = 0,
    ) -> None:
        """Append one step (s_t, a_t, r_t, c_t, flags after the step) to the current episode."""
        if self._finished:
            raise RuntimeError(f"{self.path}: the writer is finished")
        evaluation_step = int(evaluation_step)
        if evaluation_step < 0:
            raise ValueError(f"evaluation_step must be >= 0, got {evaluation_step}")
        if self._evaluation_step is None:
            self._evaluation_step = evaluation_step
        elif evaluation_step != self._evaluation_step:
            raise ValueError(
                f"episode {self._episode} started at evaluation_step={self._evaluation_step}, "
                f"got a step with evaluation_step={evaluation_step}; call end_episode() first"
            )
        reward, cost = float(reward), float(cost)
        self._rewards.append(reward)
        self._costs.append(cost)
        self._flags = (bool(terminated), bool(truncated))
        self._publish(
            STEP_TOPIC,
            {
                "evaluation_step": evaluation_step,
                "episode": self._episode,
                "step": len(self._rewards) - 1,
                "observation": _numbers(observation),
                "action": _numbers(action),
                "reward": _finite(reward),
                "cost": _finite(cost),
                "cumulative_cost": _finite(math.fsum(self._costs)),
                "terminated": self._flags[0],
                "truncated": self._flags[1],
            },
        )

    def end_episode(self) -> dict[str, Any]:
        """Write the current episode's summary, flush to disk, and return the summary (``None`` = non-finite)."""
        if self._finished:
            raise RuntimeError(f"{self.path}: the writer is finished")
        if not self._rewards:
            raise RuntimeError("end_episode() without any add_step() since the last episode")
        reward = torch.tensor(self._rewards, dtype=torch.float64)
        cost = torch.tensor(self._costs, dtype=torch.float64)
        nan_cost = bool(torch.isnan(cost).any())  # the feasible returns are undefined then: null
        summary = {
            "evaluation_step": self._evaluation_step,
            "episode": self._episode,
            "length": len(self._rewards),
            "return": _finite(episode_return(reward)),
            "cost": _finite(episode_cost(cost)),
            "feasible_return": None
            if nan_cost
            else _finite(feasible_return(reward, cost, self.cost_threshold)),
            "strict_feasible_return": None if nan_cost else _finite(strict_feasible_return(reward, cost)),
            "cost_threshold": self.cost_threshold,
            "terminated": self._flags[0],
            "truncated": self._flags[1],
        }
        self._publish(EPISODE_TOPIC, summary)
        self._writer.flush()  # one chunk per episode, on disk: a killed run keeps it
        self._episode += 1
        self._reset_episode()
        return summary

    def write_episode(self, episode: TensorDictBase, *, evaluation_step: int = 0) -> dict[str, Any]:
        """Write a whole episode given as a TorchRL rollout (batch size ``[T]``) and return its summary.

        Reads ``observation``, ``action``, ``("next", "reward")``, ``("next", "cost")`` and, when present,
        ``("next", "terminated")`` / ``("next", "truncated")``.
        """
        if episode.batch_dims != 1 or episode.batch_size[0] == 0:
            raise ValueError(
                f"write_episode takes one episode with batch size [T > 0]; got {list(episode.batch_size)}"
            )
        if self._rewards:
            raise RuntimeError(f"episode {self._episode} is in progress: call end_episode() first")
        n = episode.batch_size[0]
        keys = set(episode.keys(include_nested=True))

        def column(key, required: bool = True) -> list[list[float]]:
            if not required and key not in keys:
                return [[0.0]] * n
            if key not in keys:
                raise KeyError(f"write_episode: the episode has no {key!r} entry")
            return episode.get(key).reshape(n, -1).to(torch.float64).tolist()

        obs, act = column("observation"), column("action")
        reward, cost = column(("next", "reward")), column(("next", "cost"))
        terminated, truncated = column(("next", "terminated"), False), column(("next", "truncated"), False)
        for t in range(n):
            self.add_step(
                obs[t],
                act[t],
                reward[t][0],
                cost[t][0],
                terminated=bool(terminated[t][0]),
                truncated=bool(truncated[t][0]),
                evaluation_step=evaluation_step,
            )
        return self.end_episode()

    # -- life cycle -------------------------------------------------------------------------------------------

    def finish(self) -> None:
        """Write the MCAP summary section and close the file (idempotent)."""
        if self._finished:
            return
        if self._rewards:
            warnings.warn(
                f"{self.path}: episode {self._episode} has {len(self._rewards)} steps but no end_episode(); "
                "it is written without a summary and readers skip it",
                stacklevel=2,
            )
        self._finished = True
        try:
            self._writer.finish()
        finally:
            self._stream.close()

    def __enter__(self) -> RolloutWriter:
        return self

    def __exit__(self, *exc_info) -> None:
        self.finish()


# -- reading --------------------------------------------------------------------------------------------------


@dataclass
class Rollouts:
    """What :func:`read_rollouts` returns.

    Attributes:
        steps: batch size ``[episodes, max_steps]``, padded with zeros after each episode: ``observation``,
            ``action`` (float32, NaN where the file has ``null``), ``("next", "reward" | "cost" |
            "cumulative_cost")`` (float32, ``[E, T, 1]``), ``("next", "terminated" | "truncated" | "done")``
            (bool, ``[E, T, 1]``), ``step``, ``episode``, ``evaluation_step`` (int64) and ``mask`` (bool,
            True on real steps; a prefix of each row).
        episodes: batch size ``[episodes]``, the summaries: ``episode``, ``evaluation_step``, ``length``
            (int64), ``return``, ``cost``, ``feasible_return``, ``strict_feasible_return``, ``cost_threshold``
            (float64; NaN where unknown or non-finite), ``terminated``, ``truncated`` (bool).
        metadata: the run metadata record (string values; empty if the file has none).
        finished: whether the writer finished the file (False: the complete episodes were salvaged).
        skipped: episodes left out: steps without a summary (in progress when the writer stopped), and in a
            file that was not finished, episodes whose steps do not match their summary.
        stop_reason: why reading stopped before the end of a file that was not finished, else ``None``.
    """

    steps: TensorDict
    episodes: TensorDict
    metadata: dict[str, str] = field(default_factory=dict)
    finished: bool = True
    skipped: int = 0
    stop_reason: str | None = None


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


def _records(path: Path):
    """Yield the file's records in order; at a truncated or corrupt record, yield ``("stop", reason)`` and end."""
    with open(path, "rb") as f:
        records = StreamReader(f, validate_crcs=True).records
        while True:
            try:
                record = next(records)
            except StopIteration:
                return
            except (EndOfFile, struct.error):  # a short read: the file stops at or inside a record
                yield ("stop", "the file ends before the MCAP footer (the writer did not finish it)")
                return
            except Exception as err:  # CRC mismatch, zstandard.ZstdError, a damaged length, ...
                name = f"{type(err).__module__}.{type(err).__qualname__}".removeprefix("builtins.")
                yield ("stop", f"corrupt record ({name}{': ' + str(err) if str(err) else ''})")
                return
            yield record


def read_rollouts(
    path: str | os.PathLike, *, step_topic: str = STEP_TOPIC, episode_topic: str = EPISODE_TOPIC
) -> Rollouts:
    """Read the complete episodes of a rollout file, also one whose writer died before finishing it.

    The file is read front to back with mcap's stream reader (chunk CRCs checked); at the first truncated or
    corrupt record reading stops and everything before it is used (``Rollouts.stop_reason`` says why). An
    episode counts iff its summary message was read; episodes with steps but no summary are skipped with a
    warning (``Rollouts.skipped``). Files from any MCAP writer work if they use the topics and JSON schemas of
    this module, in any message order; channels on other topics are ignored. Summary fields the file lacks
    are recomputed from the steps with :mod:`spoil_torchrl.eval.metrics` (``feasible_return`` needs a
    ``cost_threshold`` in the summary or the metadata, else it is NaN). Episodes are sorted by
    ``(evaluation_step, episode)``. Each episode's messages are packed into tensors as soon as it is complete.

    Raises:
        FileNotFoundError: no such file.
        RolloutFileError: not an MCAP file; or, in the readable part, messages that break the schemas, or (in
            a finished file) an episode whose steps do not match its summary's length.

    Examples:
        See :class:`RolloutWriter`.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such rollout file")
    with open(path, "rb") as f:
        magic = f.read(len(MCAP_MAGIC))
    if magic != MCAP_MAGIC:
        raise RolloutFileError(
            f"{path}: not an MCAP file (it does not start with the MCAP magic bytes"
            + (", it is empty" if not magic else "")
            + ")"
        )

    channels: dict[int, str] = {}  # channel id -> "step" | "episode"
    pending: dict[tuple[int, int], dict[int, dict]] = {}  # step messages of episodes not complete yet
    summaries: dict[tuple[int, int], dict] = {}
    packed: dict[tuple[int, int], _Episode] = {}
    inconsistent: dict[tuple[int, int], str] = {}
    metadata: dict[str, str] = {}
    finished, stop_reason = False, None
    for record in _records(path):
        if isinstance(record, tuple):
            stop_reason = record[1]
            break
        if isinstance(record, Channel) and record.topic in (step_topic, episode_topic):
            if record.message_encoding != MessageEncoding.JSON:
                raise RolloutFileError(
                    f"{path}: channel {record.topic} has message encoding {record.message_encoding!r}, "
                    "expected 'json'"
                )
            channels[record.id] = "step" if record.topic == step_topic else "episode"
        elif isinstance(record, Message) and record.channel_id in channels:
            kind = channels[record.channel_id]
            where = f"{path}: {step_topic if kind == 'step' else episode_topic} message at log time {record.log_time}"
            try:
                message = json.loads(record.data)
            except (json.JSONDecodeError, UnicodeDecodeError) as err:
                raise RolloutFileError(f"{where}: not valid JSON ({err})") from err
            _validate(message, STEP_SCHEMA if kind == "step" else EPISODE_SCHEMA, where)
            key = (int(message.get("evaluation_step", 0)), int(message["episode"]))
            if kind == "step":
                t = message["step"]
                if key in packed:
                    inconsistent[key] = f"step {t} arrived after all {len(packed[key])} steps of its summary"
                elif t in pending.get(key, {}):
                    inconsistent[key] = f"step {t} appears twice"
                pending.setdefault(key, {})[t] = message
            elif key in summaries:
                raise RolloutFileError(f"{where}: episode {key[1]} has two summaries")
            else:
                summaries[key] = message
            steps = pending.get(key, {})
            n = summaries[key]["length"] if key in summaries else -1
            if len(steps) == n and max(steps, default=-1) == n - 1 and key not in inconsistent:
                packed[key] = _pack(path, [steps[t] for t in sorted(steps)], summaries[key]["length"])
                pending.pop(key, None)
        elif isinstance(record, Metadata) and record.name == METADATA_NAME:
            metadata.update(record.metadata)
        elif isinstance(record, Footer):
            finished = True

    no_summary = sorted(set(pending) - set(summaries))  # episodes in progress when the writer stopped
    skipped = len(no_summary)
    for key in sorted(summaries):
        n, have = summaries[key]["length"], sorted(pending.get(key, {}))
        if key in inconsistent or (key not in packed and have != list(range(n))):
            problem = f"{path}: episode {key[1]} (evaluation step {key[0]}): " + inconsistent.get(
                key, f"a summary of length {n} but steps {have[:10]}{'...' if len(have) > 10 else ''}"
            )
            if finished:
                raise RolloutFileError(problem)
            warnings.warn(problem + " (skipped)", stacklevel=2)
            packed.pop(key, None)
            skipped += 1
    if no_summary:
        warnings.warn(
            f"{path}: skipped {len(no_summary)} incomplete episode(s) (steps without a summary)", stacklevel=2
        )

    try:
        default_threshold = float(metadata.get("cost_threshold", "nan"))
    except ValueError:
        default_threshold = math.nan
    keys = sorted(packed)
    episodes = [packed[k] for k in keys]
    return Rollouts(
        steps=_steps_tensordict(path, keys, episodes),
        episodes=_episodes_tensordict(keys, [summaries[k] for k in keys], episodes, default_threshold),
        metadata=metadata,
        finished=finished,
        skipped=skipped,
        stop_reason=None if finished else stop_reason or "the file ends before the MCAP footer",
    )


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
    )


def _steps_tensordict(path: Path, keys: list[tuple[int, int]], episodes: list[_Episode]) -> TensorDict:
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
    for e, episode in enumerate(episodes):
        n = len(episode)
        if n == 0:
            continue
        obs[e, :n], act[e, :n] = episode.observation, episode.action
        for name, out in (*scalars.items(), *flags.items()):
            out[e, :n, 0] = getattr(episode, name)
        mask[e, :n] = True

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


def _episodes_tensordict(
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
    return TensorDict(out, batch_size=[n])
