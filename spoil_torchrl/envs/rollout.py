"""Rolling a policy out in a task's environments: :func:`rollout` (seeded, batched over several environments,
deterministic or sampled actions, every action checked finite before the simulator sees it) returns the
episodes as DSRL arrays, and :func:`episode_bounds` / :func:`episode_totals` read those arrays back per
episode. The data layer collects datasets with it, the evaluator evaluates policies with it."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor
from tqdm.auto import tqdm

from spoil_torchrl.divergence import check_finite
from spoil_torchrl.envs.cost_components import COMPONENT_PREFIX
from spoil_torchrl.envs.safety import make_safety_gymnasium
from spoil_torchrl.precision import intra_op_threads, matmul_precision
from spoil_torchrl.tasks import get_env_task


def derive_seed(seed: int, *keys: int) -> int:
    return int(np.random.SeedSequence([seed, *keys]).generate_state(1)[0])


def reset_seed(seed: int, env_index: int) -> int:
    """The seed :func:`rollout` (with ``seed``) resets its environment ``env_index`` with, once, at the start;
    later episodes of that environment continue its random stream unseeded. Replays of a rollout start here."""
    return derive_seed(seed, 3, env_index)


def rollout(
    env_id: str,
    policy: ProbabilisticActor | TensorDictModule | None,
    episodes: int,
    *,
    seed: int,
    num_envs: int = 8,
    deterministic: bool = False,
    progress: bool = True,
    desc: str | None = None,
    bar: tqdm | None = None,
    record: Callable[[Any], np.ndarray] | None = None,
    components: Callable[[Any], dict[str, float]] | None = None,
) -> dict[str, np.ndarray]:
    """Run ``episodes`` episodes of ``policy`` (``None``: uniform random actions) and return DSRL arrays.

    Args:
        env_id: a task of :data:`spoil_torchrl.tasks.ENV_TASKS`.
        policy: a TorchRL actor, or any module with a parameter (it gives the device), reading
            ``"observation"`` and writing ``"action"`` (e.g. the scripted
            :class:`~spoil_torchrl.zoo.path_follower.EllipseFollower`).
        episodes: number of complete episodes.
        seed: seeds the environments' resets and the action sampling.
        num_envs: environments stepped in lockstep (the policy runs once per step on all of them).
        deterministic: take the policy's deterministic action (evaluation) instead of sampling it.
        progress, desc: a progress bar of its own, labelled ``desc``;
        bar: or advance this (the caller's) bar instead, showing ``desc`` beside it (one bar over many calls).
        record: called with the environment before each step; its results, stacked, are returned as
            ``"recorded"`` (one row per transition), e.g. the agent's pose for the rollout file
            (:func:`~spoil_torchrl.eval.env_scene.agent_pose`).
        components: called with the environment after each step; its per-constraint costs (name -> cost) are
            returned as ``cost_<name>`` arrays (:mod:`spoil_torchrl.envs.cost_components`).

    The episodes depend on these arguments only: the rollout draws from its own random stream and computes the
    policy's float32 products in IEEE precision on one thread, whatever the caller's
    :func:`torch.set_float32_matmul_precision` and :func:`torch.set_num_threads` (a training's
    ``train.matmul_precision`` and ``threads`` change neither a generated dataset nor an evaluation, and a
    rollout in another process gives the same arrays).

    Returns:
        ``observations``, ``next_observations``, ``actions``, ``rewards``, ``costs`` (float32), ``terminals``,
        ``timeouts`` (bool), episodes back to back in the order they finished. Actions are clipped to the
        action bounds (a no-op for tanh-squashed policies).
    """

    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if num_envs < 1:
        raise ValueError(f"num_envs must be >= 1, got {num_envs}")
    task = get_env_task(env_id)
    envs = [make_safety_gymnasium(env_id) for _ in range(min(num_envs, episodes))]
    rng = np.random.default_rng(derive_seed(seed, 1))
    device = next(iter(policy.parameters())).device if policy is not None else torch.device("cpu")
    obs = [env.reset(seed=reset_seed(seed, i))[0] for i, env in enumerate(envs)]
    steps: list[list[tuple]] = [[] for _ in envs]
    finished: list[list[tuple]] = []
    active, started = list(range(len(envs))), len(envs)
    own_bar = bar is None
    if own_bar:
        bar = tqdm(
            total=episodes * task.episode_length, desc=desc or env_id, disable=not progress, unit="step"
        )
    elif desc:
        bar.set_postfix_str(desc)
    mode = ExplorationType.DETERMINISTIC if deterministic else ExplorationType.RANDOM
    # The caller's random streams (the CPU's, and a GPU policy's), float32 matmul precision and threads (e.g. a
    # training's) leave the episodes untouched.
    with (
        torch.random.fork_rng(devices=[device] if device.type == "cuda" else []),
        matmul_precision("highest"),
        intra_op_threads(1),
        torch.no_grad(),
        set_exploration_type(mode),
    ):
        torch.manual_seed(derive_seed(seed, 4))
        while active:
            batch = np.stack([obs[i] for i in active]).astype(np.float32)
            actions = _actions(policy, batch, envs[0].action_space, rng, device, env_id)
            still = []
            for j, i in enumerate(active):
                seen = None if record is None else record(envs[i])
                next_obs, reward, terminated, truncated, info = envs[i].step(actions[j])
                parts = None if components is None else components(envs[i])
                steps[i].append(
                    (
                        batch[j],
                        next_obs,
                        actions[j],
                        reward,
                        float(info["cost"][0]),
                        terminated,
                        truncated,
                        seen,
                        parts,
                    )
                )
                if terminated or truncated:
                    finished.append(steps[i])
                    # the bar counts T steps per episode: an episode that ends early moves it by T as well
                    bar.update(task.episode_length)
                    steps[i] = []
                    if started < episodes:
                        obs[i] = envs[i].reset()[0]
                        started += 1
                        still.append(i)
                else:
                    obs[i] = next_obs
                    still.append(i)
            active = still
    if own_bar:
        bar.close()
    for env in envs:
        env.close()
    return _as_arrays(finished, record is not None, components is not None)


def _actions(policy, batch: np.ndarray, space, rng: np.random.Generator, device, env_id: str) -> np.ndarray:
    """One step's actions for the observations ``batch``: ``policy``'s (clipped to ``space``'s bounds, where an
    unbounded Normal policy can leave them, and stored clipped), or uniform random ones from ``rng`` without a
    policy. A non-finite action is refused: MuJoCo would reset the simulation and the episode look costless."""
    if policy is None:
        return rng.uniform(space.low, space.high, size=(len(batch), *space.low.shape)).astype(np.float32)
    td = TensorDict({"observation": torch.from_numpy(batch)}, batch_size=[len(batch)], device=device)
    actions = policy(td)["action"].cpu().numpy()
    check_finite("the policy's action", actions, f"{env_id} rollout", "the policy diverged")
    return np.clip(actions, space.low, space.high)


def _as_arrays(finished: list[list[tuple]], recorded: bool, components: bool) -> dict[str, np.ndarray]:
    """The DSRL arrays of the ``finished`` episodes (lists of step tuples), back to back."""
    flat = [s for episode in finished for s in episode]
    columns = list(zip(*flat, strict=True))
    return {
        "observations": np.stack(columns[0]).astype(np.float32),
        "next_observations": np.stack(columns[1]).astype(np.float32),
        "actions": np.stack(columns[2]).astype(np.float32),
        "rewards": np.asarray(columns[3], dtype=np.float32),
        "costs": np.asarray(columns[4], dtype=np.float32),
        "terminals": np.asarray(columns[5], dtype=bool),
        "timeouts": np.asarray(columns[6], dtype=bool),
        **({"recorded": np.stack(columns[7])} if recorded else {}),
        **(
            {
                f"{COMPONENT_PREFIX}{k}": np.asarray([p[k] for p in columns[8]], np.float32)
                for k in columns[8][0]
            }
            if components
            else {}
        ),
    }


def episode_bounds(arrays: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """``(starts, ends)`` row indices of the episodes of DSRL arrays (episodes back to back; an episode ends
    at a terminal or timeout flag, ``ends`` exclusive).

    Examples:
        >>> episode_bounds({"terminals": np.array([0, 1, 0, 0]), "timeouts": np.array([0, 0, 0, 1])})
        (array([0, 2]), array([2, 4]))
    """
    ends = np.flatnonzero(np.asarray(arrays["terminals"]) | np.asarray(arrays["timeouts"])) + 1
    return np.concatenate([[0], ends[:-1]]).astype(ends.dtype), ends


def episode_totals(arrays: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Per-episode undiscounted return and cost of DSRL arrays (float64)."""
    starts, _ = episode_bounds(arrays)
    rewards = np.add.reduceat(arrays["rewards"].astype(np.float64), starts)
    costs = np.add.reduceat(arrays["costs"].astype(np.float64), starts)
    return rewards, costs
