"""Expert training (PPO, PPO-Lagrangian) and the committed policy zoo used to make demonstration data."""

from spoil_torchrl.experts.policies import (
    PolicyFileError,
    export_checkpoint,
    load_policy,
    save_policy,
    zoo_names,
    zoo_policy,
)
from spoil_torchrl.experts.ppo import PPOConfig, train_ppo

__all__ = [
    "PPOConfig",
    "PolicyFileError",
    "export_checkpoint",
    "load_policy",
    "save_policy",
    "train_ppo",
    "zoo_names",
    "zoo_policy",
]
