"""Make a named demonstration dataset from the committed expert policies (paper appendix F.2).

    python recipes/collect_demos.py                                     # the main recipe's embedded default
    python recipes/collect_demos.py name=point-circle1-controlled    # the four typed pools, 500 each
    python recipes/collect_demos.py name=point-circle2-replay replay=runs/experts/pc2-ppolag \
        env_id=SafetyPointCircle2-v0                                    # a replay dataset (F.2, Table H)

The file lands in ``$SPOIL_TORCHRL_DATA_DIR`` (default ``~/.cache/spoil_torchrl/generated``) as
``<dataset>.hdf5`` and loads with ``load_episodes("generated:<dataset>")``. A cached file is reused unless
``force=true``. At the end a Table-I-style summary (return, feasible return, cost per policy label) is printed.
With ``replay=<expert run directory>`` the dataset ``name`` is the trajectory buffer an expert's training
recorded (``ppo.record_episodes``), and the summary is the paper's Table H for it (safe-replay: the safe
trajectories, performance-replay: those above 90 % of the safe-optimal return, replay: all).
"""

from __future__ import annotations

import logging
import sys
import time

import hydra
import torch
from omegaconf import DictConfig

from spoil_torchrl.data import ensure_generated, get_generated, load_episodes, read_metadata, segment_pools
from spoil_torchrl.eval import policy_table
from spoil_torchrl.runs.settings import SettingsError, check_settings
from spoil_torchrl.tasks import UnknownDatasetError

log = logging.getLogger(__name__)


@hydra.main(config_path="../configs", config_name="collect_demos", version_base="1.3")
def main(cfg: DictConfig) -> None:
    try:
        check_settings({"threads": cfg.threads, "progress": cfg.progress, "force": cfg.force})
        if not (isinstance(cfg.num_envs, int) and cfg.num_envs >= 1):
            raise SettingsError(f"num_envs = {cfg.num_envs!r}: expected an integer >= 1")
        if cfg.get("replay"):
            torch.set_num_threads(cfg.threads)
            return replay_dataset(cfg)
        spec = get_generated(cfg.name)
    except (SettingsError, UnknownDatasetError, FileNotFoundError, ValueError) as err:
        sys.exit(f"error: {err}")
    torch.set_num_threads(cfg.threads)
    start = time.perf_counter()
    path = ensure_generated(cfg.name, force=cfg.force, num_envs=cfg.num_envs, progress=cfg.progress)
    meta = read_metadata(path)
    episodes = load_episodes(f"generated:{cfg.name}")
    log.info(
        f"{cfg.name}: {spec.episodes} episodes of {spec.env_id}, {meta['steps']} steps, in {path}\n"
        f"(made in {meta['seconds']:.0f} s = {meta['steps'] / meta['seconds']:.0f} steps/s; this call "
        f"{time.perf_counter() - start:.0f} s); random-policy return {meta['random_return']}, "
        f"safe-high return {meta['safe_high_return']}\n"
    )
    log.info(policy_table(episodes, segment_pools(meta), cost_threshold=meta["cost_threshold"]))


def replay_dataset(cfg: DictConfig) -> None:
    """``replay=<run dir>``: the expert training's trajectory buffer as the dataset ``name``, and its Table H."""
    from pathlib import Path

    from spoil_torchrl.data import (
        GENERATED_DATASETS,
        episode_stats,
        generated_path,
        replay_subsets,
        stats_table,
    )
    from spoil_torchrl.experts.replay import write_replay_dataset
    from spoil_torchrl.tasks import get_env_task
    from spoil_torchrl.zoo import zoo_names

    if not cfg.get("env_id"):
        raise SettingsError("replay=... needs env_id=<the task the expert was trained in>")
    task = get_env_task(cfg.env_id)
    if cfg.name in GENERATED_DATASETS:
        raise SettingsError(
            f"name={cfg.name} is a dataset made from the committed policies; name the replay dataset"
        )
    if "safe-high" not in zoo_names(task.env_id):  # its return is the safe-optimal return of the labels
        raise SettingsError(f"{task.env_id} has no committed safe-high policy: no safe-optimal return")
    run = Path(cfg.replay)
    buffer = run / "replay" if (run / "replay").is_dir() else run
    path = generated_path(cfg.name)
    if path.exists() and not cfg.force:
        if "replay" not in read_metadata(path):
            raise SettingsError(f"{path} exists and is not a replay dataset; choose another name")
        log.info(f"{path} exists; force=true makes it again")
    else:
        write_replay_dataset(buffer, path, task.env_id, metadata={"name": cfg.name})
    meta = read_metadata(path)
    episodes = load_episodes(f"generated:{cfg.name}")
    optimal = meta["safe_high_return"]
    subsets = replay_subsets(episodes, meta["cost_threshold"], optimal)
    roles = {
        "safe-replay": subsets["safe"],
        "performance-replay": subsets["performant"],
        "replay": subsets["unlabeled"],
    }
    log.info(
        f"{cfg.name}: {meta['replay']['episodes']} trajectories of {meta['replay']['batches']} training batches "
        f"({meta['steps']} steps) in {path}; safe-optimal return {optimal:.2f}, cost limit {meta['cost_threshold']}\n"
    )
    log.info(stats_table(episode_stats(episodes), roles, meta["cost_threshold"], 0.9 * optimal))


if __name__ == "__main__":
    main()
