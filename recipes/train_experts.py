"""Train a PPO (``ppo.lagrangian=false``) or PPO-Lagrangian (``ppo.lagrangian=true``) expert on a Safety-Gymnasium
task and checkpoint it periodically (actor weights + the batch's mean episode return and cost).

    python recipes/train_experts.py env_id=SafetyPointCircle1-v0 ppo.lagrangian=true
"""

from __future__ import annotations

import functools
import logging
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from spoil_torchrl.envs import make_env
from spoil_torchrl.experts import PPOConfig, train_ppo
from spoil_torchrl.tasks import get_env_task

log = logging.getLogger(__name__)


@hydra.main(config_path="../configs", config_name="train_experts", version_base="1.3")
def main(cfg: DictConfig) -> None:
    torch.set_num_threads(cfg.threads)
    task = get_env_task(cfg.env_id)
    config = PPOConfig(**OmegaConf.to_container(cfg.ppo))
    config.hidden_cells = tuple(config.hidden_cells)
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    history = train_ppo(
        functools.partial(make_env, task.env_id, seed=config.seed),
        task.observation_dim,
        task.action_dim,
        config,
        run_dir,
        progress=cfg.progress,
    )
    last = history[-1]
    log.info(
        f"{task.env_id}: {last['frames']} frames in {last['seconds']:.0f} s "
        f"({last['frames'] / last['seconds']:.0f} frames/s); last batch: return {last['episode_return']:.2f}, "
        f"cost {last['episode_cost']:.2f}, lambda {last['lagrange']:.3f}; checkpoints in {run_dir}"
    )


if __name__ == "__main__":
    main()
