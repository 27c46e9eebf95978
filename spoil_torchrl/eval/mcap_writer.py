"""Writing evaluation rollouts as MCAP files: :class:`RolloutWriter`.

The layout and the time base are :mod:`spoil_torchrl.eval.mcap_schemas`'s: step and summary messages with our
JSON schemas, and Foxglove's ``FrameTransform`` (agent pose), ``SceneUpdate`` (constraint geometry) and
``CompressedImage`` (rendered frames) when given; log times on simulation time.

**Crash safety.** The writer closes the current chunk and flushes the file at every episode end (an episode's
messages never share a chunk with the next episode's), so a run killed at any point leaves a file whose
complete episodes :func:`~spoil_torchrl.eval.read_rollouts` salvages. The flush hands the data to the
operating system (it survives a killed process); it does not ``fsync`` (a power loss may still lose recent
episodes).
"""

from __future__ import annotations

import json
import math
import os
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import CompressionType, Writer
from tensordict import TensorDictBase

import spoil_torchrl
from spoil_torchrl.eval import mcap_foxglove as fox
from spoil_torchrl.eval.mcap_schemas import (
    DEFAULT_DT,
    EPISODE_GAP_NS,
    EPISODE_SCHEMA,
    EPISODE_TOPIC,
    IMAGE_TOPIC,
    METADATA_NAME,
    SCENE_TOPIC,
    STEP_SCHEMA,
    STEP_TOPIC,
    TF_TOPIC,
    dumps,
    finite,
    metadata_value,
    numbers,
)
from spoil_torchrl.eval.metrics import episode_cost, episode_return, feasible_return, strict_feasible_return

#: topic -> JSON schema of every topic the writer may write (channels are registered on first use).
TOPIC_SCHEMAS: dict[str, dict[str, Any]] = {
    STEP_TOPIC: STEP_SCHEMA,
    EPISODE_TOPIC: EPISODE_SCHEMA,
    TF_TOPIC: fox.FRAME_TRANSFORM_SCHEMA,
    SCENE_TOPIC: fox.SCENE_UPDATE_SCHEMA,
    IMAGE_TOPIC: fox.COMPRESSED_IMAGE_SCHEMA,
}
_COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


def _dt_ns(dt: float) -> int:
    dt = float(dt)
    if not math.isfinite(dt) or dt <= 0:
        raise ValueError(f"dt must be a finite number of seconds > 0, got {dt}")
    return max(1, round(dt * 1e9))


class RolloutWriter:
    """Writes evaluation episodes to an MCAP file (see :mod:`~spoil_torchrl.eval.mcap_schemas` for the layout
    and the time base); a context manager.

    Step by step with :meth:`start_episode` (optional), :meth:`add_step` then :meth:`end_episode`, or a whole
    TorchRL rollout with :meth:`write_episode`. Every :meth:`end_episode` writes the summary and flushes, so a
    killed run keeps its complete episodes. Leaving the ``with`` block (also through an exception) calls
    :meth:`finish`; an episode in progress is then left without a summary, and readers skip it.

    Args:
        path: the ``.mcap`` file to create (overwritten; parent folders are created).
        cost_threshold: the task's cost threshold, used for the summaries' feasible return.
        metadata: run metadata (task, algo, seed, config hash, ...); non-string values are stored as JSON
            text. ``cost_threshold`` and ``writer`` entries are added.
        clock: returns the file's first log time in ns (default: the wall clock when the writer is made);
            later times are simulation time.
        compression: ``"zstd"`` (default), ``"lz4"`` or ``"none"``.
        dt: the environment's control timestep in s, for episodes not given their own (default
            :data:`~spoil_torchrl.eval.mcap_schemas.DEFAULT_DT`, summaries then say ``dt: null``).

    Episode indices run over the whole file (0, 1, 2, ... across evaluations); each episode also carries the
    ``evaluation_step`` given to its steps.

    Examples:
        >>> import tempfile
        >>> from spoil_torchrl.eval import read_rollouts
        >>> path = Path(tempfile.mkdtemp()) / "rollouts.mcap"
        >>> with RolloutWriter(path, cost_threshold=1.0, metadata={"task": "demo", "seed": 0}) as writer:
        ...     writer.start_episode(evaluation_step=500, dt=0.02)
        ...     for t in range(3):
        ...         writer.add_step([0.1 * t, 0.2], [1.0], reward=1.0, cost=float(t > 0), evaluation_step=500,
        ...                         pose=([0.1 * t, 0.0, 0.1], [0.0, 0.0, 0.0, 1.0]))
        ...     writer.end_episode()["feasible_return"]  # cumulative cost 0, 1, 2 exceeds 1 at t=2
        2.0
        >>> rollouts = read_rollouts(path)
        >>> rollouts.steps.batch_size, rollouts.episodes["return"].tolist(), rollouts.metadata["seed"]
        (torch.Size([1, 3]), [3.0], '0')
        >>> rollouts.steps["log_time"].diff().tolist()  # 20 ms of simulation time per step
        [[20000000, 20000000]]
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        cost_threshold: float,
        metadata: Mapping[str, Any] | None = None,
        clock: Callable[[], int] = time.time_ns,
        compression: str = "zstd",
        dt: float | None = None,
    ):
        cost_threshold = float(cost_threshold)
        if not math.isfinite(cost_threshold) or cost_threshold < 0:
            raise ValueError(f"cost_threshold must be a finite number >= 0, got {cost_threshold}")
        if compression not in _COMPRESSIONS:
            raise ValueError(f"compression must be one of {sorted(_COMPRESSIONS)}, got {compression!r}")
        self.dt = None if dt is None else float(dt)
        if dt is not None:
            _dt_ns(dt)
        meta = {str(k): metadata_value(v) for k, v in (metadata or {}).items()}
        if "cost_threshold" in meta and float(meta["cost_threshold"]) != cost_threshold:
            raise ValueError(
                f"metadata cost_threshold={meta['cost_threshold']} differs from {cost_threshold}"
            )
        meta["cost_threshold"] = json.dumps(cost_threshold)
        meta.setdefault("writer", f"spoil_torchrl {spoil_torchrl.__version__}")

        self.path = Path(path)
        self.cost_threshold = cost_threshold
        self.metadata = meta
        self._next_start = int(clock())  # the first episode's start; then after each summary + a gap
        self._last_time = 0
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._stream = open(self.path, "wb")  # closed by finish()
        try:
            self._writer = Writer(self._stream, compression=_COMPRESSIONS[compression])
            self._writer.start(library=f"spoil_torchrl/{spoil_torchrl.__version__}")
            self._writer.add_metadata(METADATA_NAME, meta)
            self._channels: dict[str, int] = {}
            self._channel(STEP_TOPIC)
            self._channel(EPISODE_TOPIC)
            self._writer.flush()  # header and metadata reach the disk before the first episode
        except BaseException:
            self._stream.close()
            raise
        self._finished = False
        self._episode = 0
        self._reset_episode()

    # -- time and channels ------------------------------------------------------------------------------------

    def _channel(self, topic: str) -> int:
        if topic not in self._channels:
            schema = TOPIC_SCHEMAS[topic]
            schema_id = self._writer.register_schema(
                schema["title"], SchemaEncoding.JSONSchema, json.dumps(schema).encode()
            )
            self._channels[topic] = self._writer.register_channel(topic, MessageEncoding.JSON, schema_id)
        return self._channels[topic]

    def _publish(self, topic: str, message: Mapping[str, Any], log_time: int) -> None:
        self.write_raw(topic, log_time, dumps(message))

    def write_raw(self, topic: str, log_time: int, data: bytes) -> None:
        """Write an already encoded message (e.g. copied from an earlier file) on one of the writer's topics.

        Log times may not go back. A summary (``/eval/episode``) counts as a complete episode: the file is
        flushed and the next episode starts after it.
        """
        if self._finished:
            raise RuntimeError(f"{self.path}: the writer is finished")
        if topic not in TOPIC_SCHEMAS:
            raise ValueError(f"unknown topic {topic!r}; the writer's topics are {sorted(TOPIC_SCHEMAS)}")
        log_time = int(log_time)
        if log_time < self._last_time:
            raise ValueError(
                f"{topic}: log time {log_time} is before the previous message's {self._last_time}"
            )
        self._last_time = log_time
        self._writer.add_message(self._channel(topic), log_time=log_time, data=data, publish_time=log_time)
        if topic == EPISODE_TOPIC and self._start is None:  # a copied summary (ours go through end_episode)
            self._episode += 1
            self._next_start = log_time + EPISODE_GAP_NS  # the copied time axis goes on
            self._writer.flush()

    # -- episodes ---------------------------------------------------------------------------------------------

    def _reset_episode(self) -> None:
        self._rewards: list[float] = []
        self._costs: list[float] = []
        self._flags = (False, False)
        self._evaluation_step: int | None = None
        self._start: int | None = None  # log time of step 0 of the episode in progress
        self._step_ns = 0
        self._episode_dt: float | None = None

    @property
    def episodes_written(self) -> int:
        """Number of complete episodes written so far."""
        return self._episode

    def start_episode(
        self, *, evaluation_step: int = 0, dt: float | None = None, scene: Sequence[Mapping] | None = None
    ) -> None:
        """Begin an episode (:meth:`add_step` does it with the writer's ``dt`` when not called).

        ``dt`` is the episode's control timestep in s (default: the writer's); ``scene`` a list of entities
        (``{"id": ..., "primitives": {"lines": [...], ...}}``, see
        :func:`~spoil_torchrl.eval.mcap_foxglove.scene_update`) published as a ``foxglove.SceneUpdate`` at the
        episode's first log time.
        """
        if self._finished:
            raise RuntimeError(f"{self.path}: the writer is finished")
        if self._start is not None:
            raise RuntimeError(f"episode {self._episode} is in progress: call end_episode() first")
        evaluation_step = int(evaluation_step)
        if evaluation_step < 0:
            raise ValueError(f"evaluation_step must be >= 0, got {evaluation_step}")
        dt = self.dt if dt is None else float(dt)
        self._step_ns = _dt_ns(DEFAULT_DT if dt is None else dt)
        self._episode_dt = dt
        self._evaluation_step = evaluation_step
        self._start = max(self._next_start, self._last_time)
        if scene:
            self._publish(SCENE_TOPIC, fox.scene_update(self._start, scene), self._start)

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
        pose: tuple[Sequence[float], Sequence[float]] | None = None,
        frame: np.ndarray | None = None,
        frame_format: str = "jpeg",
    ) -> None:
        """Append one step (s_t, a_t, r_t, c_t, flags after the step) to the current episode.

        ``pose``: the agent's ``(position xyz, quaternion xyzw)`` in state s_t, written as a
        ``foxglove.FrameTransform``; ``frame``: an ``H x W x 3`` uint8 rendering of s_t, written as a
        ``foxglove.CompressedImage`` in ``frame_format`` (``"jpeg"`` or ``"png"``).
        """
        if self._finished:
            raise RuntimeError(f"{self.path}: the writer is finished")
        if self._start is None:
            self.start_episode(evaluation_step=evaluation_step)
        elif int(evaluation_step) != self._evaluation_step:
            raise ValueError(
                f"episode {self._episode} started at evaluation_step={self._evaluation_step}, "
                f"got a step with evaluation_step={evaluation_step}; call end_episode() first"
            )
        reward, cost = float(reward), float(cost)
        self._rewards.append(reward)
        self._costs.append(cost)
        self._flags = (bool(terminated), bool(truncated))
        t = len(self._rewards) - 1
        now = self._start + t * self._step_ns
        message = {
            "evaluation_step": self._evaluation_step,
            "episode": self._episode,
            "step": t,
            "observation": numbers(observation),
            "action": numbers(action),
            "reward": finite(reward),
            "cost": finite(cost),
            "cumulative_cost": finite(math.fsum(self._costs)),
            "terminated": self._flags[0],
            "truncated": self._flags[1],
        }
        self._publish(STEP_TOPIC, message, now)
        if pose is not None:
            self._publish(TF_TOPIC, fox.frame_transform(now, pose[0], pose[1]), now)
        if frame is not None:
            data = fox.encode_image(frame, frame_format)
            self._publish(IMAGE_TOPIC, fox.compressed_image(now, data, frame_format), now)

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
            "return": finite(episode_return(reward)),
            "cost": finite(episode_cost(cost)),
            "feasible_return": None
            if nan_cost
            else finite(feasible_return(reward, cost, self.cost_threshold)),
            "strict_feasible_return": None if nan_cost else finite(strict_feasible_return(reward, cost)),
            "cost_threshold": self.cost_threshold,
            "terminated": self._flags[0],
            "truncated": self._flags[1],
            "dt": self._episode_dt,
        }
        end = self._start + len(self._rewards) * self._step_ns
        self._publish(EPISODE_TOPIC, summary, end)
        self._writer.flush()  # one chunk per episode, on disk: a killed run keeps it
        self._next_start = end + EPISODE_GAP_NS
        self._episode += 1
        self._reset_episode()
        return summary

    def write_episode(
        self,
        episode: TensorDictBase,
        *,
        evaluation_step: int = 0,
        dt: float | None = None,
        scene: Sequence[Mapping] | None = None,
        poses: np.ndarray | None = None,
        frames: Sequence[np.ndarray] | None = None,
        frame_format: str = "jpeg",
    ) -> dict[str, Any]:
        """Write a whole episode given as a TorchRL rollout (batch size ``[T]``) and return its summary.

        Reads ``observation``, ``action``, ``("next", "reward")``, ``("next", "cost")`` and, when present,
        ``("next", "terminated")`` / ``("next", "truncated")``. ``dt`` and ``scene`` as for
        :meth:`start_episode`; ``poses`` a ``[T, 7]`` array (position xyz, quaternion xyzw) and ``frames`` T
        images, as for :meth:`add_step`.
        """
        if episode.batch_dims != 1 or episode.batch_size[0] == 0:
            raise ValueError(
                f"write_episode takes one episode with batch size [T > 0]; got {list(episode.batch_size)}"
            )
        if self._rewards:
            raise RuntimeError(f"episode {self._episode} is in progress: call end_episode() first")
        n = episode.batch_size[0]
        for name, extra in (("poses", poses), ("frames", frames)):
            if extra is not None and len(extra) != n:
                raise ValueError(f"write_episode: {len(extra)} {name} for an episode of {n} steps")
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
        pose_rows = None if poses is None else np.asarray(poses, dtype=np.float64)
        if pose_rows is not None and pose_rows.shape != (n, 7):
            raise ValueError(
                f"write_episode: poses must be [T, 7] (xyz, quaternion xyzw), got {pose_rows.shape}"
            )
        pose_rows = None if pose_rows is None else pose_rows.tolist()
        self.start_episode(evaluation_step=evaluation_step, dt=dt, scene=scene)
        for t in range(n):
            self.add_step(
                obs[t],
                act[t],
                reward[t][0],
                cost[t][0],
                terminated=bool(terminated[t][0]),
                truncated=bool(truncated[t][0]),
                evaluation_step=evaluation_step,
                pose=None if pose_rows is None else (pose_rows[t][:3], pose_rows[t][3:]),
                frame=None if frames is None else frames[t],
                frame_format=frame_format,
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
