"""Expert training (PPO, PPO-Lagrangian) used to make demonstration data."""

from spoil_torchrl.experts.ppo import PPOConfig, train_ppo

__all__ = ["PPOConfig", "train_ppo"]
