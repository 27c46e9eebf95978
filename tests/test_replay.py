"""Replay datasets: the trajectory buffer an expert training records, read back only when complete, made into a
dataset (``collect_demos.py replay=...``, its Table H) that the main recipe trains on (``dataset.scheme=replay``)."""

from __future__ import annotations

import json
import os

import pytest
import torch

from tests.experts.helpers import needs_safety_gymnasium, tiny_config, train


def test_an_incomplete_replay_buffer_is_refused(tmp_path):
    from spoil_torchrl.experts.replay import read_replay

    with pytest.raises(FileNotFoundError, match="no recorded batch"):
        read_replay(tmp_path)
    empty = {k: torch.zeros(0) for k in ("observations", "actions", "next_observations", "rewards", "costs")}
    empty |= {"terminals": torch.zeros(0, dtype=torch.bool), "timeouts": torch.zeros(0, dtype=torch.bool)}
    for index in (0, 1, 3):
        torch.save({**empty, "batch": index}, tmp_path / f"batch_{index:06d}.pt")
    with pytest.raises(ValueError, match="1 of 4 batches are missing \\(first 2\\)"):
        read_replay(tmp_path)


@needs_safety_gymnasium
def test_a_recorded_training_becomes_a_replay_dataset_that_trains(tmp_path):
    """The trajectory buffer of a (tiny) expert training -> ``collect_demos.py replay=...`` (its Table H) ->
    the main recipe with ``dataset.scheme=replay`` on it."""
    from spoil_torchrl.data import episode_stats, load_episodes, read_metadata, replay_subsets
    from tests.cli import run_command

    run = tmp_path / "expert"
    train(
        run, tiny_config(record_episodes=2, frames_per_batch=1000, total_frames=3000)
    )  # 2 episodes per batch
    env = {**os.environ, "SPOIL_TORCHRL_DATA_DIR": str(tmp_path / "data")}
    made = run_command(
        [
            "recipes/collect_demos.py",
            "name=tiny-replay",
            f"replay={run}",
            "env_id=SafetyPointCircle1-v0",
            f"hydra.run.dir={tmp_path / 'collect'}",
        ],
        env=env,
    )
    assert made.returncode == 0, made.stderr[-3000:]
    path = tmp_path / "data" / "tiny-replay.hdf5"
    meta = read_metadata(path)
    assert meta["replay"]["batches"] == 3 and meta["replay"]["episodes"] == 6
    assert meta["replay"]["episode_batches"] == [0, 0, 1, 1, 2, 2]
    assert meta["env_id"] == "SafetyPointCircle1-v0" and meta["cost_threshold"] == 25.0
    assert meta["safe_high_return"] > 30  # the committed safe-high policy's return: the safe-optimal return
    episodes = load_episodes(f"file:{path}")
    stats = episode_stats(episodes)
    subsets = replay_subsets(episodes, 25.0, meta["safe_high_return"])
    assert "| replay |" in made.stdout and f"| {len(stats['cost'])} |" in made.stdout  # Table H, all 6
    assert subsets["safe"].numel() > 0 and "| safe-replay | 1.00 |" in made.stdout
    # the main recipe trains on it (R_max -500: every trajectory counts as performant at this size), D_U all
    trained = run_command(
        [
            "recipes/spoildice_dsrl.py",
            "preset=smoke",
            "algo=bc",
            "logger=none",
            "progress=false",
            f"dataset.source=file:{path}",
            "dataset.scheme=replay",
            "dataset.n_safe=1",
            "dataset.n_performant=1",
            "dataset.n_unlabeled=null",
            "dataset.return_range=[-1000,-500]",
            f"hydra.run.dir={tmp_path / 'run'}",
        ],
        env=env,
    )
    assert trained.returncode == 0, trained.stderr[-3000:]
    results = json.loads((tmp_path / "run" / "results.json").read_text())
    assert results["status"] == "finished" and results["data"]["unlabeled"]["episodes"] == 6
