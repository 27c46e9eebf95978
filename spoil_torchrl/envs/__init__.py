"""Environments: Safety-Gymnasium tasks as TorchRL envs with a cost entry.

The names are loaded on first use, so that ``spoil_torchrl.envs.compat`` (the import-time fixes of
Safety-Gymnasium) loads without torch and TorchRL.
"""

from __future__ import annotations

import importlib

_WHERE = {
    "applied_patches": "compat",
    "import_safety_gymnasium": "compat",
    "enable_fast_reset": "fast_reset",
    "fast_reset_enabled": "fast_reset",
    "CostInInfo": "safety",
    "log_mujoco_warnings": "safety",
    "make_env": "safety",
    "make_safety_gymnasium": "safety",
}

__all__ = sorted(_WHERE)


def __getattr__(name: str):
    if name not in _WHERE:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_WHERE[name]}"), name)
    globals()[name] = value  # loaded once
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_WHERE))
