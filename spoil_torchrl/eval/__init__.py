"""Evaluation: metrics of the paper's section 5.2 and MCAP rollout files.

:class:`Evaluator` runs a policy in the task's real environment and reports them (and writes MCAP:
:mod:`~spoil_torchrl.eval.mcap_schemas` describes the file, which Foxglove opens with
``docs/foxglove/rollouts_layout.json``).
"""

from spoil_torchrl.eval.evaluator import Evaluator, pad_episodes
from spoil_torchrl.eval.mcap_reader import Rollouts, read_rollouts
from spoil_torchrl.eval.mcap_schemas import (
    EPISODE_SCHEMA,
    EPISODE_TOPIC,
    METADATA_NAME,
    STEP_SCHEMA,
    STEP_TOPIC,
    RolloutFileError,
)
from spoil_torchrl.eval.mcap_writer import RolloutWriter
from spoil_torchrl.eval.metrics import (
    SeedAggregate,
    aggregate_over_seeds,
    episode_cost,
    episode_metrics,
    episode_return,
    feasible_return,
    mean_of_last,
    normalized_cost,
    normalized_return,
    strict_feasible_return,
)
from spoil_torchrl.eval.tables import (
    format_mean_stderr,
    mean_stderr,
    policy_table,
    transition_episode_metrics,
)

__all__ = [
    "EPISODE_SCHEMA",
    "EPISODE_TOPIC",
    "Evaluator",
    "METADATA_NAME",
    "STEP_SCHEMA",
    "STEP_TOPIC",
    "RolloutFileError",
    "RolloutWriter",
    "Rollouts",
    "SeedAggregate",
    "aggregate_over_seeds",
    "episode_cost",
    "episode_metrics",
    "episode_return",
    "feasible_return",
    "mean_of_last",
    "format_mean_stderr",
    "mean_stderr",
    "normalized_cost",
    "normalized_return",
    "pad_episodes",
    "policy_table",
    "read_rollouts",
    "strict_feasible_return",
    "transition_episode_metrics",
]
