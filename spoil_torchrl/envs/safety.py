"""TorchRL environments for the Safety-Gymnasium tasks, with the cost at ``("next", "cost")``.

The gymnasium side (:func:`make_safety_gymnasium`, :class:`CostInInfo`) loads without torch; TorchRL is loaded
by :func:`make_env`, the one function that needs it.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import gymnasium
import numpy as np

from spoil_torchrl.envs.compat import import_safety_gymnasium
from spoil_torchrl.envs.fast_reset import disable_fast_reset, enable_fast_reset
from spoil_torchrl.tasks import get_env_task

if TYPE_CHECKING:
    from torchrl.envs import TransformedEnv


class CostInInfo(gymnasium.Wrapper):
    """Turns Safety-Gymnasium's 6-tuple ``step`` into gymnasium's 5-tuple, with the cost as ``info["cost"]``
    (a float32 array of shape ``(1,)``, the shape of TorchRL's reward). Actions are passed as float64 arrays
    (safety-gymnasium's ``step(list)`` fails under NumPy 2).

    Examples:
        >>> env = CostInInfo(import_safety_gymnasium().make("SafetyHopperVelocity-v1"))
        >>> obs, info = env.reset(seed=0)
        >>> obs, reward, terminated, truncated, info = env.step([0.0, 0.0, 0.0])  # five values, not six
        >>> info["cost"], obs.shape
        (array([0.], dtype=float32), (11,))
    """

    def step(self, action):
        obs, reward, cost, terminated, truncated, info = self.env.step(np.asarray(action, dtype=np.float64))
        info = dict(info)
        info["cost"] = np.array([cost], dtype=np.float32)
        return obs, reward, terminated, truncated, info

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        info = dict(info)
        info["cost"] = np.zeros(1, dtype=np.float32)
        return obs, info


def log_mujoco_warnings(logger: logging.Logger | None = None) -> None:
    """Send MuJoCo's warnings (e.g. "Nan, Inf or huge value in QACC") to ``logger`` (default this module's),
    and so into a run's log, instead of MuJoCo's default: a ``MUJOCO_LOG.TXT`` file in the working directory.

    Examples:
        >>> log_mujoco_warnings()
    """
    try:
        import mujoco
    except ImportError:  # no simulator installed: nothing to route
        return
    target = logger or logging.getLogger(__name__)
    mujoco.set_mju_user_warning(lambda message: target.warning(f"MuJoCo: {message}"))


def make_safety_gymnasium(env_id: str, *, fast_reset: bool = True, **kwargs) -> gymnasium.Env:
    """The raw Safety-Gymnasium environment wrapped in :class:`CostInInfo` (a plain gymnasium env).

    ``fast_reset`` switches the skybox patch on or off for the environments built from now on.

    Use it for NumPy-speed loops (collection, evaluation); :func:`make_env` wraps it for TorchRL.

    Examples:
        >>> env = make_safety_gymnasium("SafetyPointCircle1-v0")
        >>> obs, info = env.reset(seed=0)
        >>> obs.shape, info["cost"]
        ((28,), array([0.], dtype=float32))
        >>> obs, reward, terminated, truncated, info = env.step(np.zeros(2))
        >>> float(info["cost"][0]), terminated, truncated  # the agent starts inside the safe band
        (0.0, False, False)
    """
    task = get_env_task(env_id)
    safety_gymnasium = import_safety_gymnasium()
    (enable_fast_reset if fast_reset else disable_fast_reset)()
    return CostInInfo(safety_gymnasium.make(task.env_id, **kwargs))


def make_env(
    env_id: str, *, seed: int | None = None, fast_reset: bool = True, device="cpu"
) -> TransformedEnv:
    """A TorchRL environment for a task of :data:`spoil_torchrl.tasks.ENV_TASKS`.

    Observations are float32; ``("next", "cost")`` is float32 with a trailing dim of 1, like the reward.
    ``fast_reset`` swaps the navigation tasks' skybox texture (rendering only, see
    :mod:`spoil_torchrl.envs.fast_reset`).

    Examples:
        >>> env = make_env("SafetyPointCircle1-v0", seed=0)
        >>> env.rollout(3)["next", "cost"].shape
        torch.Size([3, 1])
    """
    import torch
    from torchrl.data import Composite, Unbounded
    from torchrl.envs import DoubleToFloat, GymWrapper, TransformedEnv, default_info_dict_reader

    task = get_env_task(env_id)
    env = GymWrapper(make_safety_gymnasium(env_id, fast_reset=fast_reset), device=device)
    spec = Composite(cost=Unbounded(shape=(1,), dtype=torch.float32, device=device), shape=[])
    env.set_info_dict_reader(default_info_dict_reader(["cost"], spec=spec))
    env = TransformedEnv(env, DoubleToFloat())
    if seed is not None:
        env.set_seed(seed)
    if env.observation_spec["observation"].shape[-1] != task.observation_dim:
        raise RuntimeError(
            f"{env_id}: observation size {env.observation_spec['observation'].shape[-1]} differs from the task "
            f"table's {task.observation_dim}; the installed safety-gymnasium is not the expected 1.0.0"
        )
    return env
