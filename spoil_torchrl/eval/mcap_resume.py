"""Continuing the rollout file of a resumed run: one MCAP file per run, every complete episode kept once.

A run killed mid-way leaves ``rollouts.mcap`` without its footer; its complete episodes are salvageable
(:func:`~spoil_torchrl.eval.read_rollouts`). When the run resumes from its checkpoint at training step ``k``,
:func:`continue_rollouts` starts a new file in the same place that first holds the old file's complete
episodes of the evaluations up to ``k`` (those after ``k`` belong to an evaluation that the resumed run does
again), then takes the new episodes. The old file is kept as ``<name>.before-resume`` until the copy is
complete, so a run killed again while copying loses nothing either.

The copy is message for message: every topic the writer knows (steps, summaries, poses, scenes, frames) with
its log time, up to the end of the last episode kept; the new episodes continue the simulation-time axis
after it, so log times stay monotonic across the resume.
"""

from __future__ import annotations

import json
import os
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from spoil_torchrl.eval.mcap_reader import iter_messages, read_rollouts
from spoil_torchrl.eval.mcap_schemas import EPISODE_TOPIC, STEP_TOPIC
from spoil_torchrl.eval.mcap_writer import TOPIC_SCHEMAS, RolloutWriter

BACKUP_SUFFIX = ".before-resume"


def continue_rollouts(
    path: str | os.PathLike,
    *,
    until_step: int,
    cost_threshold: float,
    metadata: Mapping[str, Any] | None = None,
) -> RolloutWriter:
    """A :class:`RolloutWriter` on ``path`` that already holds the earlier file's complete episodes whose
    ``evaluation_step <= until_step`` (in their order, with the same content and log times); use it as a
    context manager.

    Examples:
        >>> import tempfile
        >>> path = Path(tempfile.mkdtemp()) / "rollouts.mcap"
        >>> writer = RolloutWriter(path, cost_threshold=1.0)
        >>> for step in (100, 200):
        ...     writer.add_step([0.0], [0.0], reward=1.0, cost=0.0, evaluation_step=step)
        ...     _ = writer.end_episode()
        >>> writer.add_step([0.0], [0.0], reward=1.0, cost=0.0, evaluation_step=300)  # then killed
        >>> with continue_rollouts(path, until_step=200, cost_threshold=1.0) as writer:
        ...     _ = writer.write_episode(read_rollouts(path).steps[0, :1], evaluation_step=300)
        >>> read_rollouts(path).episodes["evaluation_step"].tolist()
        [100, 200, 300]
    """
    path = Path(path)
    backup = path.with_name(path.name + BACKUP_SUFFIX)
    if not backup.exists() and path.exists():  # a backup left by an earlier resume is the complete one
        os.replace(path, backup)
    old = None
    if backup.exists():
        with warnings.catch_warnings():  # the killed evaluation's incomplete episode is expected here
            warnings.simplefilter("ignore")
            old = read_rollouts(backup)
    writer = RolloutWriter(path, cost_threshold=cost_threshold, metadata=metadata)
    try:
        if old is not None:
            _copy_episodes(backup, old, until_step, writer)
    except BaseException:
        writer.finish()
        raise
    backup.unlink(missing_ok=True)
    return writer


def _copy_episodes(source: Path, old, until_step: int, writer: RolloutWriter) -> None:
    """Copy ``source``'s messages of its complete episodes up to ``until_step`` into ``writer``, as they are."""
    episodes = old.episodes
    keep = episodes["evaluation_step"] <= until_step
    if not bool(keep.any()):
        return
    kept = set(
        zip(episodes["evaluation_step"][keep].tolist(), episodes["episode"][keep].tolist(), strict=True)
    )
    until = int(episodes["log_time"][keep].max())
    for topic, message in iter_messages(source):
        if message.log_time > until or topic not in TOPIC_SCHEMAS:
            continue
        if topic in (STEP_TOPIC, EPISODE_TOPIC):
            fields = json.loads(message.data)
            if (fields.get("evaluation_step", 0), fields["episode"]) not in kept:
                continue
        writer.write_raw(topic, message.log_time, message.data)
