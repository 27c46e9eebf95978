"""Roll policies out in a Safety-Gymnasium task and write the episodes as a DSRL-layout HDF5 file.

:func:`rollout` runs ``num_envs`` raw environments in lockstep and batches the policy over them (the per-step
cost is then the simulator's, ~1,500 steps/s for PointCircle1 on one core). Everything is seeded: the
environments' reset seeds and the action sampling come from ``seed``, so the same call gives the same
arrays (for the same ``num_envs``). :func:`collect` concatenates several policies' episodes into one file and
records which episodes came from which policy in the file's metadata (:func:`segment_pools` reads them back),
together with the random-policy and safe-high returns that normalise returns for the task; it shares the
rollouts with a worker process per spare core (:class:`~spoil_torchrl.data.parallel.RolloutPool`).
The file is written atomically: an interrupted collection leaves no file that loads.
"""

from __future__ import annotations

import functools
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import ProbabilisticActor
from tqdm.auto import tqdm

from spoil_torchrl.data.hdf5 import write_dsrl_file
from spoil_torchrl.data.parallel import RolloutPool, available_cores
from spoil_torchrl.divergence import check_finite
from spoil_torchrl.precision import intra_op_threads, matmul_precision
from spoil_torchrl.stack import current_stack
from spoil_torchrl.tasks import get_env_task

#: ``policy`` value of a :class:`Segment` that acts uniformly at random.
RANDOM_POLICY = "random"

#: From this many simulator steps on (about 10 s on one core), :func:`collect` shares its rollouts with worker
#: processes by default.
SHARED_STEPS = 50_000

#: What a rollout worker imports when it starts (:class:`~spoil_torchrl.data.parallel.RolloutPool`'s
#: ``warm_up``): this module and the simulators.
ROLLOUT_MODULES = ("spoil_torchrl.data.collect", "spoil_torchrl.envs")


@dataclass(frozen=True)
class Segment:
    """``episodes`` episodes of one policy in a collected dataset.

    Attributes:
        label: the policy type or pool name, e.g. ``"safe-high"`` (several segments may share a label).
        policy: ``"random"``, ``"zoo:<name>"`` (a committed policy of the task, see
            :func:`spoil_torchrl.experts.zoo_policy`) or the path of a policy / PPO checkpoint file.
        episodes: how many episodes to roll out.
    """

    label: str
    policy: str
    episodes: int

    def __post_init__(self) -> None:
        if self.episodes < 1:
            raise ValueError(f"segment {self.label!r}: episodes must be >= 1, got {self.episodes}")


def resolve_policy(spec: str, env_id: str) -> ProbabilisticActor | None:
    """The actor a :class:`Segment` ``policy`` names (``None`` for the random policy)."""
    from spoil_torchrl.experts.policies import load_policy, zoo_policy

    if spec == RANDOM_POLICY:
        return None
    path = zoo_policy(env_id, spec.removeprefix("zoo:")) if spec.startswith("zoo:") else Path(spec)
    return load_policy(path, env_id=env_id)[0]


def _derive_seed(seed: int, *keys: int) -> int:
    return int(np.random.SeedSequence([seed, *keys]).generate_state(1)[0])


def reset_seed(seed: int, env_index: int) -> int:
    """The seed :func:`rollout` (with ``seed``) resets its environment ``env_index`` with, once, at the start;
    later episodes of that environment continue its random stream unseeded. Replays of a rollout start here."""
    return _derive_seed(seed, 3, env_index)


def rollout(
    env_id: str,
    policy: ProbabilisticActor | None,
    episodes: int,
    *,
    seed: int,
    num_envs: int = 8,
    deterministic: bool = False,
    progress: bool = True,
    desc: str | None = None,
    bar: tqdm | None = None,
    record: Callable[[Any], np.ndarray] | None = None,
) -> dict[str, np.ndarray]:
    """Run ``episodes`` episodes of ``policy`` (``None``: uniform random actions) and return DSRL arrays.

    Args:
        env_id: a task of :data:`spoil_torchrl.tasks.ENV_TASKS`.
        policy: a TorchRL actor reading ``"observation"`` and writing ``"action"``.
        episodes: number of complete episodes.
        seed: seeds the environments' resets and the action sampling.
        num_envs: environments stepped in lockstep (the policy runs once per step on all of them).
        deterministic: take the policy's deterministic action (evaluation) instead of sampling it.
        progress, desc: a progress bar of its own, labelled ``desc``;
        bar: or advance this (the caller's) bar instead, showing ``desc`` beside it (one bar over many calls).
        record: called with the environment before each step; its results, stacked, are returned as
            ``"recorded"`` (one row per transition), e.g. the agent's pose for the rollout file
            (:func:`~spoil_torchrl.eval.env_scene.agent_pose`).

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
    from spoil_torchrl.envs import make_safety_gymnasium

    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if num_envs < 1:
        raise ValueError(f"num_envs must be >= 1, got {num_envs}")
    task = get_env_task(env_id)
    envs = [make_safety_gymnasium(env_id) for _ in range(min(num_envs, episodes))]
    rng = np.random.default_rng(_derive_seed(seed, 1))
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
    # The caller's random stream, float32 matmul precision and threads (e.g. a training's) leave the episodes
    # untouched.
    with (
        torch.random.fork_rng(devices=[]),
        matmul_precision("highest"),
        intra_op_threads(1),
        torch.no_grad(),
        set_exploration_type(mode),
    ):
        torch.manual_seed(_derive_seed(seed, 4))
        while active:
            batch = np.stack([obs[i] for i in active]).astype(np.float32)
            if policy is None:
                low, high = envs[0].action_space.low, envs[0].action_space.high
                actions = rng.uniform(low, high, size=(len(active), *low.shape)).astype(np.float32)
            else:
                td = TensorDict(
                    {"observation": torch.from_numpy(batch)}, batch_size=[len(active)], device=device
                )
                # an unbounded (Normal) policy's action is clipped to the bounds, and stored clipped
                space = envs[0].action_space
                actions = policy(td)["action"].cpu().numpy()
                # a NaN action makes MuJoCo reset the simulation: its episodes would look costless
                check_finite("the policy's action", actions, f"{env_id} rollout", "the policy diverged")
                actions = np.clip(actions, space.low, space.high)
            still = []
            for j, i in enumerate(active):
                seen = None if record is None else record(envs[i])
                next_obs, reward, terminated, truncated, info = envs[i].step(actions[j])
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
        **({} if record is None else {"recorded": np.stack(columns[7])}),
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


def reference_policies(env_id: str) -> dict[str, str | None]:
    """The policies whose mean returns normalise a generated dataset's returns: the random policy, and the
    committed ``safe-high`` policy where the task has one (``None`` where it has not)."""
    from spoil_torchrl.experts.policies import zoo_names

    safe_high = "zoo:safe-high" if "safe-high" in zoo_names(env_id) else None
    return {"random_return": RANDOM_POLICY, "safe_high_return": safe_high}


def reference_jobs(env_id: str, *, episodes: int = 10, seed: int = 0) -> dict[str, functools.partial]:
    """The rollouts of the :func:`reference_policies` that the task has, as picklable calls (see
    :class:`~spoil_torchrl.data.parallel.RolloutPool`); the means of their returns normalise the returns of
    generated data: ``(R - random) / (safe_high - random)``."""
    return {
        name: functools.partial(
            rollout,
            env_id,
            resolve_policy(spec, env_id),
            episodes,
            seed=_derive_seed(seed, 99),
            progress=False,
            desc=f"reference {spec}",
        )
        for name, spec in reference_policies(env_id).items()
        if spec is not None
    }


def collect(
    env_id: str,
    segments: Sequence[Segment],
    path: str | os.PathLike,
    *,
    seed: int = 0,
    num_envs: int = 8,
    reference_episodes: int = 10,
    progress: bool = True,
    metadata: dict | None = None,
    workers: int | None = None,
) -> Path:
    """Roll out every segment's policy and write all episodes to ``path`` (DSRL layout, atomic).

    The segments' and reference policies' rollouts are shared with ``workers`` worker processes
    (:class:`~spoil_torchrl.data.parallel.RolloutPool`; default: one per spare core once the rollouts reach
    :data:`SHARED_STEPS` steps, else none); the file is the same either way.

    The metadata (see :func:`~spoil_torchrl.data.read_metadata`) holds ``env_id``, ``seed``, ``num_envs``,
    ``cost_threshold`` (the task's episode-cost limit), ``segments`` (label, policy, episode range
    ``[start, stop)``, mean return and cost), ``random_return`` / ``safe_high_return``, the wall time, the
    software stack it was made on (``stack``: :func:`spoil_torchrl.stack.current_stack`), and ``metadata``'s
    entries.
    """
    task = get_env_task(env_id)
    if not segments:
        raise ValueError("collect needs at least one segment")
    reserved = {
        "env_id",
        "seed",
        "num_envs",
        "cost_threshold",
        "segments",
        "random_return",
        "safe_high_return",
        "seconds",
        "steps",
        "stack",
    }
    clash = reserved & set(metadata or {})
    if clash:
        raise ValueError(f"metadata may not override the collector's own entries {sorted(clash)}")
    start_time = time.perf_counter()
    parts, records, first = [], [], 0
    jobs = [
        functools.partial(
            rollout,
            env_id,
            resolve_policy(segment.policy, env_id),
            segment.episodes,
            seed=_derive_seed(seed, 10, k),
            num_envs=num_envs,
            progress=False,
            desc=f"{segment.label} ({segment.policy})",
        )
        for k, segment in enumerate(segments)
    ]
    references = reference_jobs(env_id, episodes=reference_episodes, seed=seed)
    jobs += references.values()
    # one bar over every segment and the reference rollouts, so that its estimate is the whole job's
    total = sum(job.args[2] for job in jobs) * task.episode_length
    bar = tqdm(
        total=total, desc=f"collecting {env_id}", disable=not progress, unit="step", dynamic_ncols=True
    )
    here: set[int] = set()  # the jobs this process runs, on the bar as they go

    def run_here(job: functools.partial) -> dict[str, np.ndarray]:
        here.add(id(job))
        return job(bar=bar)

    if workers is None:  # a worker's start (about 3 s of a core) pays from some 10 s of rollouts
        workers = 0 if total < SHARED_STEPS else min(len(jobs), available_cores()) - 1
    results = []
    with RolloutPool(workers, warm_up=ROLLOUT_MODULES) as pool:
        for job, arrays in zip(jobs, pool.map(jobs, run_here), strict=True):
            if id(job) not in here:  # a worker's: the bar moves when it is done
                bar.update(job.args[2] * task.episode_length)
            results.append(arrays)
    bar.close()
    for segment, arrays in zip(segments, results[: len(segments)], strict=True):
        returns, costs = episode_totals(arrays)
        records.append(
            {
                **asdict(segment),
                "start": first,
                "stop": first + segment.episodes,
                "mean_return": float(returns.mean()),
                "mean_cost": float(costs.mean()),
            }
        )
        first += segment.episodes
        parts.append(arrays)
    references = dict.fromkeys(reference_policies(env_id)) | {
        name: float(episode_totals(arrays)[0].mean())
        for name, arrays in zip(references, results[len(segments) :], strict=True)
    }
    arrays = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
    meta = {
        "env_id": env_id,
        "seed": seed,
        "num_envs": num_envs,
        "cost_threshold": task.cost_limit,
        "segments": records,
        **references,
        "seconds": time.perf_counter() - start_time,
        "steps": int(arrays["rewards"].shape[0]),
        "stack": current_stack(),
        **(metadata or {}),
    }
    return write_dsrl_file(path, arrays, metadata=meta)


def segment_pools(metadata: dict) -> dict[str, torch.Tensor]:
    """Episode ids per segment label from a collected file's metadata (labels shared by segments are merged).

    Examples:
        >>> meta = {"segments": [{"label": "safe-high", "start": 0, "stop": 2},
        ...                      {"label": "unsafe-high", "start": 2, "stop": 5}]}
        >>> {k: v.tolist() for k, v in segment_pools(meta).items()}
        {'safe-high': [0, 1], 'unsafe-high': [2, 3, 4]}
    """
    if "segments" not in metadata:
        raise ValueError("the metadata has no 'segments': not a file written by spoil_torchrl's collect()")
    pools: dict[str, list[torch.Tensor]] = {}
    for seg in metadata["segments"]:
        pools.setdefault(seg["label"], []).append(torch.arange(seg["start"], seg["stop"]))
    return {label: torch.cat(parts) for label, parts in pools.items()}
