"""Environments: Safety-Gymnasium tasks as TorchRL envs with a cost entry."""

from spoil_torchrl.envs.compat import applied_patches, import_safety_gymnasium
from spoil_torchrl.envs.fast_reset import enable_fast_reset, fast_reset_enabled
from spoil_torchrl.envs.safety import CostInInfo, log_mujoco_warnings, make_env, make_safety_gymnasium

__all__ = [
    "CostInInfo",
    "applied_patches",
    "enable_fast_reset",
    "fast_reset_enabled",
    "import_safety_gymnasium",
    "log_mujoco_warnings",
    "make_env",
    "make_safety_gymnasium",
]
