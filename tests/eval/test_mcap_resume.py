"""Continuing a killed run's rollout file."""

from __future__ import annotations

import os

import torch

from spoil_torchrl.eval import RolloutWriter, read_rollouts
from spoil_torchrl.eval.mcap_resume import BACKUP_SUFFIX, continue_rollouts


def _killed_file(path, steps=(100, 200, 300), partial=400):
    writer = RolloutWriter(path, cost_threshold=5.0, metadata={"seed": 0})
    for step in steps:
        for t in range(3):
            writer.add_step([float(step), float(t)], [0.5], reward=1.0, cost=float(t), evaluation_step=step)
        writer.end_episode()
    writer.add_step([0.0, 0.0], [0.0], reward=1.0, cost=0.0, evaluation_step=partial)  # never finished
    writer._stream.flush()
    return writer  # left open: the process "died"


def test_continue_keeps_complete_episodes_up_to_the_checkpoint(tmp_path):
    path = tmp_path / "rollouts.mcap"
    _killed_file(path)
    before = read_rollouts(path)
    with continue_rollouts(path, until_step=200, cost_threshold=5.0, metadata={"seed": 0}) as writer:
        writer.add_step([1.0, 1.0], [0.0], reward=2.0, cost=0.0, evaluation_step=300)
        writer.end_episode()
    after = read_rollouts(path)
    assert after.finished and after.episodes["evaluation_step"].tolist() == [100, 200, 300]
    assert torch.equal(after.steps["observation"][:2], before.steps["observation"][:2])
    assert after.episodes["return"].tolist() == [3.0, 3.0, 2.0]
    assert not (tmp_path / ("rollouts.mcap" + BACKUP_SUFFIX)).exists()


def test_a_backup_left_by_an_interrupted_copy_is_the_source(tmp_path):
    path = tmp_path / "rollouts.mcap"
    _killed_file(path)
    os.replace(path, tmp_path / ("rollouts.mcap" + BACKUP_SUFFIX))
    RolloutWriter(path, cost_threshold=5.0)._stream.flush()  # the half-made copy of that resume
    with continue_rollouts(path, until_step=1000, cost_threshold=5.0):
        pass
    assert read_rollouts(path).episodes["evaluation_step"].tolist() == [100, 200, 300]


def test_no_earlier_file_starts_an_empty_one(tmp_path):
    with continue_rollouts(tmp_path / "r.mcap", until_step=0, cost_threshold=1.0):
        pass
    assert read_rollouts(tmp_path / "r.mcap").episodes.batch_size[0] == 0
