"""Evaluate a policy in the task's real environment: deterministic episodes, the paper's metrics, MCAP output."""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.modules import ProbabilisticActor

from spoil_torchrl.envs.cost_components import COMPONENT_PREFIX, cost_components
from spoil_torchrl.envs.rollout import episode_bounds, rollout
from spoil_torchrl.eval.env_scene import agent_pose, make_render_env, replay_episodes, task_view
from spoil_torchrl.eval.mcap_writer import RolloutWriter
from spoil_torchrl.eval.metrics import episode_metrics

#: Per-evaluation metrics (means over the evaluation's episodes) that :class:`Evaluator` reports.
METRICS = (
    "return",
    "cost",
    "feasible_return",
    "strict_feasible_return",
    "normalized_return",
    "normalized_feasible_return",
    "normalized_cost",
)


def pad_episodes(arrays: Mapping[str, np.ndarray]) -> TensorDict:
    """DSRL arrays (episodes back to back) as a padded ``[episodes, steps]`` TensorDict with a ``mask``.

    Examples:
        >>> arrays = {"observations": np.zeros((3, 1)), "actions": np.zeros((3, 1)),
        ...           "rewards": np.array([1.0, 2.0, 3.0]), "costs": np.zeros(3),
        ...           "terminals": np.array([False, True, False]), "timeouts": np.array([False, False, True])}
        >>> pad_episodes(arrays)["mask"].tolist()
        [[True, True], [True, False]]
    """

    starts, ends = episode_bounds(arrays)
    if ends.size == 0 or ends[-1] != len(arrays["rewards"]):
        raise ValueError("the arrays do not end with a finished episode")
    lengths = ends - starts
    n, t = len(lengths), int(lengths.max())
    index = torch.arange(t).expand(n, t)
    mask = index < torch.as_tensor(lengths).unsqueeze(-1)
    first = torch.as_tensor(starts).unsqueeze(-1)
    rows = torch.where(mask, first + index, first)  # padding rows point at the episode's first step

    def gather(key: str, dtype) -> torch.Tensor:
        values = torch.as_tensor(np.asarray(arrays[key]), dtype=dtype)[rows]
        valid = mask.reshape(*mask.shape, *[1] * (values.ndim - 2))
        return torch.where(valid, values, torch.zeros((), dtype=dtype))

    return TensorDict(
        {
            "observation": gather("observations", torch.float32),
            "action": gather("actions", torch.float32),
            "next": {
                "reward": gather("rewards", torch.float64),
                "cost": gather("costs", torch.float64),
                "terminated": gather("terminals", torch.bool),
                "truncated": gather("timeouts", torch.bool),
            },
            "mask": mask,
        },
        batch_size=[n, t],
    )


def evaluation_rollout(
    env_id: str,
    policy: ProbabilisticActor,
    episodes: int,
    *,
    seed: int,
    num_envs: int,
    record: Callable[[Any], np.ndarray] | None = None,
    components: Callable[[Any], dict[str, float]] | None = None,
) -> dict[str, np.ndarray]:
    """The deterministic episodes of an evaluation (:func:`spoil_torchrl.envs.rollout.rollout`), the policy in
    eval mode meanwhile."""

    was_training = policy.training
    policy.eval()
    try:
        return rollout(
            env_id,
            policy,
            episodes,
            seed=seed,
            num_envs=num_envs,
            deterministic=True,
            progress=False,
            record=record,
            components=components,
        )
    finally:
        policy.train(was_training)


class Evaluator:
    """Runs ``episodes`` deterministic episodes of a policy in ``env_id`` and reports the paper's metrics.

    Each call rolls the policy out (:func:`spoil_torchrl.envs.rollout.rollout` with the policy's deterministic
    action, the same ``seed`` every time and, as every rollout, IEEE float32 products on one thread whatever the
    caller's :func:`torch.set_float32_matmul_precision` and threads, so that evaluations differ only by the
    policy), computes the per-episode
    metrics with :func:`~spoil_torchrl.eval.episode_metrics` (return, cost, feasible return and its strict
    variant, normalised return / feasible return / cost), writes every episode to ``writer`` (an MCAP
    :class:`~spoil_torchrl.eval.RolloutWriter`) when given, and returns the means over episodes.

    In the file, steps are logged on simulation time (the task's control timestep), each episode starts with
    the task's constraint geometry (``/eval/scene``), and with ``poses`` every step carries the agent's pose
    (``/tf``), with ``frames`` a rendered JPEG frame (``/eval/camera``). Poses are read from the simulator
    during the rollout (reading does not change it); with frames, poses and frames come from replaying the
    episodes' actions in a rendering environment (:func:`~spoil_torchrl.eval.env_scene.replay_episodes`), so
    the metrics' rollout is the same with or without them.

    Args:
        env_id: task of :data:`spoil_torchrl.tasks.ENV_TASKS`.
        cost_threshold: threshold of the feasible return and the normalised cost.
        return_range: ``(R_min, R_max)`` of the normalised return.
        episodes: episodes per evaluation.
        seed: environment seed of every evaluation.
        writer: where to write the episodes (optional).
        poses: write the agent's pose at every step (default on).
        frames: write a rendered ``frame_size`` square frame at every step (default off; needs an off-screen
            OpenGL context, checked here: :func:`~spoil_torchrl.eval.env_scene.make_render_env`).
        frame_size: width and height of the frames in pixels.
        constraints: several constraints' thresholds (name -> episode-cost limit) of a task with per-constraint
            costs (:mod:`spoil_torchrl.envs.cost_components`): each evaluation also reports ``cost_<name>`` (the
            mean episode cost on that constraint) and ``feasible_all`` (the share of episodes within every
            constraint's limit).

    Examples:
        An untrained policy in SafetyHopperVelocity-v1 (it falls within a few steps, which ends the episode):

        >>> from spoil_torchrl.modules import make_actor
        >>> evaluator = Evaluator("SafetyHopperVelocity-v1", cost_threshold=25.0, return_range=(0.0, 1600.0),
        ...                       episodes=3, num_envs=3)
        >>> policy = make_actor(11, 3, hidden_cells=(8,))
        >>> result = evaluator(policy, step=1000)
        >>> result["step"], result["cost"], len(result["episodes"]["return"])  # means, and per episode
        (1000, 0.0, 3)
        >>> evaluator(policy)["return"] == result["return"]  # the same episodes for the same policy
        True
    """

    def __init__(
        self,
        env_id: str,
        *,
        cost_threshold: float,
        return_range: tuple[float, float],
        episodes: int = 10,
        seed: int = 0,
        num_envs: int = 10,
        writer: RolloutWriter | None = None,
        poses: bool = True,
        frames: bool = False,
        frame_size: int = 256,
        constraints: Mapping[str, float] | None = None,
    ) -> None:
        self.constraints = dict(constraints or {})
        self.components = cost_components(env_id) if self.constraints else None  # raises without them
        if episodes < 1:
            raise ValueError(f"episodes must be >= 1, got {episodes}")
        lo, hi = (float(v) for v in return_range)
        if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
            raise ValueError(
                f"return_range must be two finite numbers with R_max > R_min, got {return_range}"
            )
        self.env_id = env_id
        self.cost_threshold = float(cost_threshold)
        self.return_range = (lo, hi)
        self.episodes = int(episodes)
        self.seed = int(seed)
        self.num_envs = int(num_envs)
        self.writer = writer
        self.poses, self.frames, self.frame_size = bool(poses), bool(frames), int(frame_size)
        if self.frames:  # fail now, not at the first evaluation
            make_render_env(env_id, self.frame_size).close()

    def __call__(self, policy: ProbabilisticActor, step: int = 0) -> dict:
        """Evaluate ``policy``; returns ``{"step", <metric>: mean over episodes, "episodes": per-episode lists}``."""
        return self.report(self.rollout_job(policy)(), step)

    def rollout_job(self, policy: ProbabilisticActor) -> functools.partial:
        """The evaluation's rollout of ``policy`` as a picklable call (no argument; returns the DSRL arrays
        :meth:`report` reads): run it here, or in another process
        (:class:`~spoil_torchrl.data.parallel.RolloutPool`) with a copy of the policy -- the arrays are the same.
        """
        record_poses = self.writer is not None and self.poses and not self.frames
        return functools.partial(
            evaluation_rollout,
            self.env_id,
            policy,
            self.episodes,
            seed=self.seed,
            num_envs=self.num_envs,
            record=agent_pose if record_poses else None,  # frames need the replay's rendering instead
            components=self.components,
        )

    def report(self, arrays: dict[str, np.ndarray], step: int = 0) -> dict:
        """The metrics of an evaluation's rollout (:meth:`rollout_job`), its episodes written to the writer."""

        arrays = dict(arrays)
        recorded = arrays.pop("recorded", None)
        parts = {
            k.removeprefix(COMPONENT_PREFIX): arrays.pop(k)
            for k in list(arrays)
            if k.startswith(COMPONENT_PREFIX)
        }
        padded = pad_episodes(arrays)
        metrics = episode_metrics(padded, self.cost_threshold, return_range=self.return_range)
        if self.writer is not None:
            view = task_view(self.env_id)
            poses = frames = [None] * padded.shape[0]
            if recorded is not None:  # one pose per step, recorded during the rollout
                poses = np.split(recorded, episode_bounds(arrays)[1][:-1])
            elif self.frames:
                poses, frames = replay_episodes(
                    self.env_id,
                    arrays,
                    seed=self.seed,
                    num_envs=self.num_envs,
                    frames=self.frames,
                    frame_size=self.frame_size,
                )
            for e in range(padded.shape[0]):
                n = int(metrics["length"][e])
                self.writer.write_episode(
                    padded[e, :n],
                    evaluation_step=step,
                    dt=view.dt,
                    scene=view.scene,
                    poses=poses[e] if self.poses else None,
                    frames=frames[e],
                )
        result = {"step": int(step)}
        result.update({key: float(metrics[key].mean()) for key in METRICS})
        result["episodes"] = {key: metrics[key].tolist() for key in (*METRICS, "length")}
        if self.constraints:
            per_episode = self._constraint_metrics(arrays, parts)
            result |= {key: float(np.mean(values)) for key, values in per_episode.items()}
            result["episodes"] |= {key: [float(v) for v in values] for key, values in per_episode.items()}
        return result

    def _constraint_metrics(self, arrays: dict, parts: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Per episode: each constraint's cost (``cost_<name>``) and whether it is within every constraint's
        limit (``feasible_all``, 1 or 0)."""
        missing = sorted(set(self.constraints) - set(parts))
        if missing:
            raise ValueError(
                f"{self.env_id}'s per-constraint costs are {sorted(parts)}; the evaluation's constraints {missing} "
                "are not among them"
            )
        starts, _ = episode_bounds(arrays)
        costs = {name: np.add.reduceat(parts[name].astype(np.float64), starts) for name in self.constraints}
        within = np.all([costs[name] <= limit for name, limit in self.constraints.items()], axis=0)
        return {f"cost_{name}": c for name, c in costs.items()} | {"feasible_all": within.astype(np.float64)}
