"""Train a PPO (``ppo.lagrangian=false``) or PPO-Lagrangian (``ppo.lagrangian=true``) expert on a Safety-Gymnasium
task and checkpoint it periodically (actor weights + the batch's mean episode return and cost).

    python recipes/train_experts.py env_id=SafetyPointCircle1-v0 ppo.lagrangian=true
    python recipes/train_experts.py env_id=SafetyHopperVelocity-v1 hydra.run.dir=runs/experts/hopper-ppo resume=auto

Training is resumable: with ``resume=true`` (or ``auto``, which also starts a new run) and the run's
``hydra.run.dir``, a killed or interrupted run continues from its last training state (every
``ppo.checkpoint_every`` batches) and ends with the same policies as an uninterrupted run; ``resume=auto`` on a
finished run does nothing, so a list of runs can be started again until all have finished.
"""

from __future__ import annotations

import functools
import logging
import sys
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from spoil_torchrl.envs import log_mujoco_warnings, make_env
from spoil_torchrl.experts import PPOConfig, train_ppo
from spoil_torchrl.experts.ppo import resumable_state
from spoil_torchrl.runs.checkpoint import CheckpointError
from spoil_torchrl.runs.directory import (
    RunDirError,
    claim_run_dir,
    release_run_dir,
    run_status,
    write_hydra_record,
)
from spoil_torchrl.runs.outcome import ended_in_one_line
from spoil_torchrl.runs.settings import SettingsError, check_settings
from spoil_torchrl.tasks import UnknownDatasetError, get_env_task
from spoil_torchrl.trainers import stop_on_signals

log = logging.getLogger(__name__)


@hydra.main(config_path="../configs", config_name="train_experts", version_base="1.3")
def main(cfg: DictConfig) -> None:
    stop_on_signals()  # SIGTERM ends training like Ctrl-C, the last training state intact
    log_mujoco_warnings()  # into the run's log, not MUJOCO_LOG.TXT in the working directory
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        check_settings({"threads": cfg.threads})
        task = get_env_task(cfg.env_id)
        config = PPOConfig(**OmegaConf.to_container(cfg.ppo))
        if cfg.resume == "auto" and run_status(run_dir) == "finished":  # a re-run sweep skips finished runs
            log.info(f"{run_dir}: finished already; nothing to do")
            return
        # a resume with other settings is refused inside the claim: nothing is written into the run
        check = lambda resuming: resuming and resumable_state(run_dir, config)  # noqa: E731
        resuming = claim_run_dir(run_dir, resume=cfg.resume, check=check)
        if not resuming:
            write_hydra_record(run_dir, cfg)
    except (SettingsError, RunDirError, CheckpointError, UnknownDatasetError, ValueError) as err:
        sys.exit(f"error: {err}")
    torch.set_num_threads(cfg.threads)
    try:
        with ended_in_one_line("recipes/train_experts.py", run_dir):  # divergence, a full disk, Ctrl-C
            history = train_ppo(
                functools.partial(make_env, task.env_id),
                task.observation_dim,
                task.action_dim,
                config,
                run_dir,
                progress=cfg.progress,
                resume=resuming,
                env_id=task.env_id,
            )
    finally:
        release_run_dir(run_dir)
    last = history[-1]
    log.info(
        f"{task.env_id}: {last['frames']} frames in {last['seconds']:.0f} s "
        f"({last['frames'] / last['seconds']:.0f} frames/s); last batch: return {last['episode_return']:.2f}, "
        f"cost {last['episode_cost']:.2f}, lambda {last['lagrange']:.3f}; checkpoints in {run_dir}"
    )


if __name__ == "__main__":
    main()
