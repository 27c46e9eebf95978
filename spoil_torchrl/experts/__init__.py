"""Expert training: PPO and PPO-Lagrangian (:func:`train_ppo`), resumable, with the trajectory buffer of replay
datasets. The policies it produced for the paper's tasks are committed in :mod:`spoil_torchrl.zoo`."""

from spoil_torchrl.experts.ppo import train_ppo
from spoil_torchrl.experts.ppo_config import PPOConfig

__all__ = ["PPOConfig", "train_ppo"]
