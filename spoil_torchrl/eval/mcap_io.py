"""Evaluation rollouts as MCAP files: one import for the writer, the reader and the layout.

The code lives in three modules: :mod:`~spoil_torchrl.eval.mcap_schemas` (topics, JSON schemas, the time
base), :mod:`~spoil_torchrl.eval.mcap_writer` (:class:`RolloutWriter`) and
:mod:`~spoil_torchrl.eval.mcap_reader` (:func:`read_rollouts` and the salvage of files whose writer died);
Foxglove's message types are in :mod:`~spoil_torchrl.eval.mcap_foxglove`.
"""

from spoil_torchrl.eval.mcap_reader import Rollouts, iter_messages, read_rollouts
from spoil_torchrl.eval.mcap_schemas import (
    DEFAULT_DT,
    EPISODE_GAP_NS,
    EPISODE_SCHEMA,
    EPISODE_TOPIC,
    IMAGE_TOPIC,
    MCAP_MAGIC,
    METADATA_NAME,
    SCENE_TOPIC,
    STEP_SCHEMA,
    STEP_TOPIC,
    SUMMARY_FLOATS,
    TF_TOPIC,
    RolloutFileError,
)
from spoil_torchrl.eval.mcap_writer import TOPIC_SCHEMAS, RolloutWriter

__all__ = [
    "DEFAULT_DT",
    "EPISODE_GAP_NS",
    "EPISODE_SCHEMA",
    "EPISODE_TOPIC",
    "IMAGE_TOPIC",
    "MCAP_MAGIC",
    "METADATA_NAME",
    "SCENE_TOPIC",
    "STEP_SCHEMA",
    "STEP_TOPIC",
    "SUMMARY_FLOATS",
    "TF_TOPIC",
    "TOPIC_SCHEMAS",
    "RolloutFileError",
    "RolloutWriter",
    "Rollouts",
    "iter_messages",
    "read_rollouts",
]
