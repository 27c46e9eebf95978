"""The layout of an evaluation rollout file: topics, our JSON schemas, and the time base.

File layout (any MCAP writer that follows it can be read, not only :class:`~spoil_torchrl.eval.RolloutWriter`):

* topic ``/eval/step`` (:data:`STEP_TOPIC`), message encoding ``json``, schema :data:`STEP_SCHEMA`
  (``jsonschema`` encoding): one message per environment step with ``evaluation_step``, ``episode``, ``step``,
  ``observation`` and ``action`` (flat number arrays), ``reward``, ``cost``, ``cumulative_cost`` (the
  episode's cost up to and including this step), ``terminated`` and ``truncated``;
* topic ``/eval/episode`` (:data:`EPISODE_TOPIC`), schema :data:`EPISODE_SCHEMA`: one summary per finished
  episode (``return``, ``cost``, ``feasible_return``, ``strict_feasible_return``, ``length``, the
  ``cost_threshold`` used, the final ``terminated`` / ``truncated`` flags, the control timestep ``dt``),
  computed with :mod:`spoil_torchrl.eval.metrics`;
* Foxglove's well-known messages (:mod:`spoil_torchrl.eval.mcap_foxglove`, JSON with Foxglove's JSON schemas):
  ``/tf`` (:data:`TF_TOPIC`, ``foxglove.FrameTransform``, frame ``world`` -> ``agent``: the agent's pose at
  every step), ``/eval/scene`` (:data:`SCENE_TOPIC`, ``foxglove.SceneUpdate``: the task's constraint
  geometry, at every episode start) and, when rendering is switched on, ``/eval/camera``
  (:data:`IMAGE_TOPIC`, ``foxglove.CompressedImage``: one JPEG or PNG frame per step);
* an MCAP metadata record named ``spoil_torchrl.run`` (:data:`METADATA_NAME`) with the run's metadata
  (task, algo, seed, config hash, ...; string values).

An episode is identified by ``(evaluation_step, episode)`` and is *complete* iff its summary message exists:
the reader returns complete episodes only.

**Time base.** Log and publish times are nanoseconds since the Unix epoch, on *simulation time*: the file
starts at the wall-clock time its writer was created; an episode that starts at ``t0`` logs step ``t`` (and
its pose and frame) at ``t0 + t * dt`` and its summary at ``t0 + T * dt`` (T steps), where ``dt`` is the
environment's control timestep (:func:`spoil_torchrl.eval.env_scene.control_timestep`; 0.02 s for the
navigation tasks, 0.05 s for HalfCheetah). The next episode starts :data:`EPISODE_GAP_NS` after that, so
times increase strictly across episodes and evaluations (which are written in order), and a resumed run's
file, which copies the earlier episodes with their times and continues after them, stays monotonic too.
A writer that is given no ``dt`` uses :data:`DEFAULT_DT` (recorded as ``dt: null`` in the summaries).
Files written before this time base have wall-clock times; they read the same.

**No NaN in JSON.** NaN is not valid JSON, so every non-finite number (NaN, +inf, -inf) is written as
``null`` and read back as NaN (the sign of an infinity is lost). The schemas still declare plain ``number``
types, because Foxglove's JSON-schema parser rejects type unions such as ``["number", "null"]``: a ``null``
is the one value outside the declared schema, and plots show it as a gap.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import Any

import torch

STEP_TOPIC = "/eval/step"
EPISODE_TOPIC = "/eval/episode"
TF_TOPIC = "/tf"
SCENE_TOPIC = "/eval/scene"
IMAGE_TOPIC = "/eval/camera"
METADATA_NAME = "spoil_torchrl.run"
MCAP_MAGIC = b"\x89MCAP0\r\n"

#: Time between one episode's summary and the next episode's first step (1 s of simulation time).
EPISODE_GAP_NS = 1_000_000_000
#: Control timestep (s) of a writer that is not told the environment's.
DEFAULT_DT = 0.001

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
        "dt": {**_NUMBER, "description": "control timestep in s: the log times' step (null: not known)"},
    },
    "required": ["episode", "length"],
}

SUMMARY_FLOATS = ("return", "cost", "feasible_return", "strict_feasible_return", "cost_threshold")


class RolloutFileError(ValueError):
    """A rollout file that cannot be read: missing, not MCAP, or with messages that do not follow the schemas.

    Examples:
        >>> import tempfile
        >>> from pathlib import Path
        >>> from spoil_torchrl.eval import read_rollouts
        >>> path = Path(tempfile.mkdtemp()) / "notes.mcap"
        >>> _ = path.write_text("not a rollout file")
        >>> try:
        ...     read_rollouts(path)
        ... except RolloutFileError as err:
        ...     print(str(err).removeprefix(f"{path}: "))
        not an MCAP file (it does not start with the MCAP magic bytes)
    """


def finite(x: float) -> float | None:
    """``x`` as a float, or ``None`` (JSON ``null``) when it is NaN or infinite.

    Examples:
        >>> finite(2), finite(float("nan"))
        (2.0, None)
    """
    x = float(x)
    return x if math.isfinite(x) else None


def numbers(values) -> list[float | None]:
    """A flat list of :func:`finite` numbers from anything ``torch.as_tensor`` takes."""
    return [finite(v) for v in torch.as_tensor(values, dtype=torch.float64).reshape(-1).tolist()]


def dumps(obj: Mapping[str, Any]) -> bytes:
    """Compact JSON bytes; raises on NaN (callers write ``null`` instead)."""
    return json.dumps(obj, allow_nan=False, separators=(",", ":")).encode()


def metadata_value(value: Any) -> str:
    """An MCAP metadata value: strings as they are, anything else as JSON text."""
    return value if isinstance(value, str) else json.dumps(value, allow_nan=False, default=str)
