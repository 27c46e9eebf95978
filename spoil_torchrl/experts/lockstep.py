"""An expert's training batches from several environments stepped in lockstep (``PPOConfig.num_envs``).

With one environment, :func:`~spoil_torchrl.experts.ppo.collect_batch` steps a TorchRL environment, and
TorchRL's per-step work costs more than the simulator's own step. :class:`LockstepCollector` steps
``num_envs`` plain Safety-Gymnasium environments side by side instead, with one batched policy call per step,
as the dataset collector does (:func:`spoil_torchrl.envs.rollout.rollout`). A batch of ``frames_per_batch``
frames is then ``[num_envs, frames_per_batch / num_envs]``. Every environment starts the batch from a reset
seeded by the run's seed, the batch's index and its own index. Episodes end and reset inside the batch, and an
episode still running at the batch's end is cut there (not ``done``: GAE bootstraps it from the critic). So the
batch depends only on the policy's weights, the batch's index and the torch random state, and a resumed
training repeats an uninterrupted one exactly. The keys are those of a TorchRL rollout that PPO reads: the
``observation``, the ``action`` and its ``action_log_prob``, and under ``"next"`` the ``observation``,
``reward``, ``cost``, ``terminated``, ``truncated`` and ``done``.
"""

from __future__ import annotations

import numpy as np
import torch
from tensordict import TensorDict
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type

from spoil_torchrl.divergence import check_finite
from spoil_torchrl.envs.path_reward import check_half_axes, task_ellipse_reward


def env_seed(batch_seed: int, env_index: int) -> int:
    """The reset seed of environment ``env_index`` in a batch whose seed is ``batch_seed``.

    Examples:
        >>> len({env_seed(7, 0), env_seed(7, 1), env_seed(8, 0)})
        3
    """
    return int(np.random.SeedSequence([batch_seed, env_index]).generate_state(1)[0])


class LockstepCollector:
    """``num_envs`` environments of ``env_id`` that give an expert's batches (see the module docstring).

    Examples:
        >>> from spoil_torchrl.modules import make_actor
        >>> actor = make_actor(28, 2, hidden_cells=(8,), distribution="tanh_normal", return_log_prob=True)
        >>> collector = LockstepCollector("SafetyPointCircle1-v0", num_envs=2)
        >>> batch = collector.batch(actor, frames=10, seed=0)
        >>> batch.shape, batch["next", "cost"].shape
        (torch.Size([2, 5]), torch.Size([2, 5, 1]))
        >>> collector.close()
    """

    def __init__(
        self,
        env_id: str,
        num_envs: int,
        *,
        cost_component: str | None = None,
        track_ellipse: tuple[float, float] | None = None,
    ) -> None:
        from spoil_torchrl.envs import make_safety_gymnasium
        from spoil_torchrl.envs.cost_components import cost_components

        if num_envs < 1:
            raise ValueError(f"num_envs = {num_envs}: expected an integer >= 1")
        self.env_id = env_id
        #: with a component, the cost is that constraint's own (envs.cost_components), not the task's
        self.component = cost_component
        self.split = None if cost_component is None else cost_components(env_id)
        self.envs = [make_safety_gymnasium(env_id) for _ in range(num_envs)]
        #: with half-axes, the reward is the circle task's for that ellipse (envs.path_reward), not the task's
        self.ellipse = None if track_ellipse is None else check_half_axes(track_ellipse)
        if self.ellipse is not None:
            task_ellipse_reward(self.envs[0], self.ellipse)  # a task without a circle raises here
        space = self.envs[0].action_space
        self.low, self.high = space.low, space.high

    def _costs(self, step: list) -> list[float]:
        """The step's costs: the task's, or the chosen constraint's (after the step, from the simulator)."""
        if self.split is None:
            return [float(s[4]["cost"][0]) for s in step]
        parts = [self.split(env) for env in self.envs]
        if self.component not in parts[0]:
            raise ValueError(
                f"ppo.cost_component = {self.component!r}: {self.env_id}'s constraints are {sorted(parts[0])}"
            )
        return [p[self.component] for p in parts]

    def _rewards(self, step: list) -> list[float]:
        """The step's rewards: the task's, or its reward for the tracked ellipse (from the simulator)."""
        if self.ellipse is None:
            return [float(s[1]) for s in step]
        return [task_ellipse_reward(env, self.ellipse) for env in self.envs]

    def batch(self, actor: nn.Module, frames: int, seed: int) -> TensorDict:
        """``frames`` frames of ``actor``'s sampled actions, ``frames / num_envs`` per environment, each
        environment reset with :func:`env_seed` of ``seed`` first."""
        n = len(self.envs)
        if frames % n:
            raise ValueError(f"{frames} frames do not split over {n} environments")
        steps = frames // n
        obs = np.stack([env.reset(seed=env_seed(seed, i))[0] for i, env in enumerate(self.envs)])
        columns: dict[str, list] = {
            k: [] for k in ("obs", "action", "logp", "next", "reward", "cost", "term", "trunc")
        }
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):
            for _ in range(steps):
                observation = torch.as_tensor(obs, dtype=torch.float32)
                out = actor(TensorDict({"observation": observation}, batch_size=[n]))
                action = out["action"]
                check_finite(
                    "the policy's action", action, f"{self.env_id} training batch", "the policy diverged"
                )
                clipped = np.clip(action.numpy(), self.low, self.high)
                step = [env.step(a) for env, a in zip(self.envs, clipped, strict=True)]
                next_obs = np.stack([s[0] for s in step])
                terminated = np.array([s[2] for s in step])
                truncated = np.array([s[3] for s in step])
                for key, value in (
                    ("obs", observation),
                    ("action", action),
                    ("logp", out["action_log_prob"]),
                    ("next", torch.as_tensor(next_obs, dtype=torch.float32)),
                    ("reward", torch.tensor(self._rewards(step), dtype=torch.float32)),
                    ("cost", torch.tensor(self._costs(step), dtype=torch.float32)),
                    ("term", torch.as_tensor(terminated)),
                    ("trunc", torch.as_tensor(truncated)),
                ):
                    columns[key].append(value)
                obs = next_obs.copy()
                for i in np.flatnonzero(terminated | truncated):  # a new episode in the same batch
                    obs[i] = self.envs[i].reset()[0]
        stack = {k: torch.stack(v, dim=1) for k, v in columns.items()}  # [n, steps, ...]
        flag = lambda x: x.reshape(n, steps, 1)  # noqa: E731
        return TensorDict(
            {
                "observation": stack["obs"],
                "action": stack["action"],
                "action_log_prob": stack["logp"],
                "next": {
                    "observation": stack["next"],
                    "reward": stack["reward"].reshape(n, steps, 1),
                    "cost": stack["cost"].reshape(n, steps, 1),
                    "terminated": flag(stack["term"]),
                    "truncated": flag(stack["trunc"]),
                    "done": flag(stack["term"] | stack["trunc"]),
                },
            },
            batch_size=[n, steps],
        )

    def close(self) -> None:
        for env in self.envs:
            env.close()
