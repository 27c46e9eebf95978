"""Reading evaluation rollout files: :func:`read_rollouts`, which also salvages files whose writer died.

The layout is :mod:`spoil_torchrl.eval.mcap_schemas`'s. Only the step and summary topics are read (the
Foxglove topics, ``/tf``, ``/eval/scene``, ``/eval/camera``, and any other channel are skipped), so files
written before those topics existed read the same.

**Salvage.** A file whose writer was killed has no footer and no summary section, and may end inside a
record. :func:`read_rollouts` reads it with mcap's :class:`~mcap.stream_reader.StreamReader` (chunk CRCs
checked) and stops at the first truncated or corrupt record, keeping every complete episode before it.
"""

from __future__ import annotations

import math
import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from mcap.exceptions import EndOfFile
from mcap.records import Channel, Footer, Message, Metadata
from mcap.stream_reader import StreamReader
from tensordict import TensorDict

from spoil_torchrl.eval.mcap_episodes import EpisodeAssembly, episodes_tensordict, steps_tensordict
from spoil_torchrl.eval.mcap_schemas import (
    EPISODE_TOPIC,
    MCAP_MAGIC,
    METADATA_NAME,
    STEP_TOPIC,
    RolloutFileError,
)


@dataclass
class Rollouts:
    """What :func:`read_rollouts` returns.

    Attributes:
        steps: batch size ``[episodes, max_steps]``, padded with zeros after each episode: ``observation``,
            ``action`` (float32, NaN where the file has ``null``), ``("next", "reward" | "cost" |
            "cumulative_cost")`` (float32, ``[E, T, 1]``), ``("next", "terminated" | "truncated" | "done")``
            (bool, ``[E, T, 1]``), ``step``, ``episode``, ``evaluation_step`` (int64) and ``mask`` (bool,
            True on real steps; a prefix of each row), ``log_time`` (int64 ns, 0 on padding).
        episodes: batch size ``[episodes]``, the summaries: ``episode``, ``evaluation_step``, ``length``
            (int64), ``return``, ``cost``, ``feasible_return``, ``strict_feasible_return``, ``cost_threshold``
            (float64; NaN where unknown or non-finite), ``terminated``, ``truncated`` (bool), ``log_time``
            (int64 ns: the summary's, the episode's end).
        metadata: the run metadata record (string values; empty if the file has none).
        finished: whether the writer finished the file (False: the complete episodes were salvaged).
        skipped: episodes left out: steps without a summary (in progress when the writer stopped), and in a
            file that was not finished, episodes whose steps do not match their summary.
        stop_reason: why reading stopped before the end of a file that was not finished, else ``None``.

    Examples:
        >>> import tempfile
        >>> from spoil_torchrl.eval import RolloutWriter
        >>> path = Path(tempfile.mkdtemp()) / "rollouts.mcap"
        >>> with RolloutWriter(path, cost_threshold=1.0) as writer:
        ...     for length in (3, 4):
        ...         for t in range(length):
        ...             writer.add_step([0.0, 1.0], [0.5], reward=1.0, cost=0.0, evaluation_step=100)
        ...         _ = writer.end_episode()
        >>> rollouts = read_rollouts(path)
        >>> rollouts.steps.batch_size, rollouts.steps["mask"].sum(-1).tolist()  # padded to the longest
        (torch.Size([2, 4]), [3, 4])
        >>> rollouts.episodes["length"].tolist(), rollouts.episodes["return"].tolist()
        ([3, 4], [3.0, 4.0])
        >>> rollouts.finished, rollouts.skipped, rollouts.stop_reason
        (True, 0, None)
    """

    steps: TensorDict
    episodes: TensorDict
    metadata: dict[str, str] = field(default_factory=dict)
    finished: bool = True
    skipped: int = 0
    stop_reason: str | None = None


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


def iter_messages(path: str | os.PathLike) -> Iterator[tuple[str, Message]]:
    """``(topic, message)`` of every message of an MCAP file in file order, up to the first truncated or
    corrupt record (a file whose writer died ends there, without an error)."""
    topics: dict[int, str] = {}
    for record in _records(Path(path)):
        if isinstance(record, tuple):
            return
        if isinstance(record, Channel):
            topics[record.id] = record.topic
        elif isinstance(record, Message) and record.channel_id in topics:
            yield topics[record.channel_id], record


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
        A copy of a file taken while its writer was in the middle of the third episode (as a killed run leaves
        it) gives the two complete episodes; writing and reading a whole file is shown at
        :class:`~spoil_torchrl.eval.RolloutWriter`.

        >>> import tempfile
        >>> from spoil_torchrl.eval import RolloutWriter
        >>> folder = Path(tempfile.mkdtemp())
        >>> with RolloutWriter(folder / "rollouts.mcap", cost_threshold=1.0) as writer:
        ...     for episode in range(3):
        ...         for t in range(4):
        ...             writer.add_step([0.0, 1.0], [0.5], reward=1.0, cost=float(t == 3), evaluation_step=5)
        ...             if (episode, t) == (2, 1):  # a snapshot as a killed writer would leave the file
        ...                 _ = (folder / "killed.mcap").write_bytes((folder / "rollouts.mcap").read_bytes())
        ...         _ = writer.end_episode()
        >>> read_rollouts(folder / "rollouts.mcap").episodes["cost"].tolist()
        [1.0, 1.0, 1.0]
        >>> salvaged = read_rollouts(folder / "killed.mcap")
        >>> salvaged.finished, salvaged.episodes["return"].tolist(), salvaged.stop_reason
        (False, [4.0, 4.0], 'the file ends before the MCAP footer (the writer did not finish it)')
    """
    path = Path(path)
    _check_magic(path)
    found = EpisodeAssembly(path, step_topic, episode_topic)
    metadata: dict[str, str] = {}
    finished, stop_reason = False, None
    for record in _records(path):
        if isinstance(record, tuple):
            stop_reason = record[1]
            break
        if isinstance(record, Channel) and record.topic in (step_topic, episode_topic):
            found.add_channel(record)
        elif isinstance(record, Message) and record.channel_id in found.channels:
            found.add_message(record)
        elif isinstance(record, Metadata) and record.name == METADATA_NAME:
            metadata.update(record.metadata)
        elif isinstance(record, Footer):
            finished = True
    skipped = found.drop_incomplete(finished)

    try:
        default_threshold = float(metadata.get("cost_threshold", "nan"))
    except ValueError:
        default_threshold = math.nan
    keys = sorted(found.packed)
    episodes = [found.packed[k] for k in keys]
    return Rollouts(
        steps=steps_tensordict(path, keys, episodes),
        episodes=episodes_tensordict(keys, [found.summaries[k] for k in keys], episodes, default_threshold),
        metadata=metadata,
        finished=finished,
        skipped=skipped,
        stop_reason=None if finished else stop_reason or "the file ends before the MCAP footer",
    )


def _check_magic(path: Path) -> None:
    """Refuse a missing file, or one that does not start with the MCAP magic bytes."""
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
