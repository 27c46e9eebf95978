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
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from tensordict.nn import TensorDictModule
from torchrl.modules import ProbabilisticActor
from tqdm.auto import tqdm

from spoil_torchrl.data.hdf5 import write_dsrl_file
from spoil_torchrl.data.parallel import RolloutPool, available_cores
from spoil_torchrl.envs.cost_components import cost_components
from spoil_torchrl.envs.rollout import derive_seed, episode_totals, rollout
from spoil_torchrl.stack import current_stack
from spoil_torchrl.tasks import get_env_task

#: ``policy`` value of a :class:`Segment` that acts uniformly at random.
RANDOM_POLICY = "random"

#: From this many simulator steps on (about 10 s on one core), :func:`collect` shares its rollouts with worker
#: processes by default.
SHARED_STEPS = 50_000

#: What a rollout worker imports when it starts (:class:`~spoil_torchrl.data.parallel.RolloutPool`'s
#: ``warm_up``): this module and the simulators.
ROLLOUT_MODULES = ("spoil_torchrl.data.collect", "spoil_torchrl.envs", "spoil_torchrl.envs.rollout")


@dataclass(frozen=True)
class Segment:
    """``episodes`` episodes of one policy in a collected dataset.

    Attributes:
        label: the policy type or pool name, e.g. ``"safe-high"`` (several segments may share a label).
        policy: ``"random"``, ``"zoo:<name>"`` (a committed policy of the task, see
            :func:`spoil_torchrl.zoo.zoo_policy`), the path of a policy / PPO checkpoint file, or, in a circle
            task, ``"ellipse:<a>,<b>"`` (the scripted :class:`~spoil_torchrl.zoo.path_follower.EllipseFollower`
            round the ellipse with those half-axes; it is not a policy file, so the commands that load policy
            files, such as ``recipes/score_checkpoints.py``, do not take it).
        episodes: how many episodes to roll out.

    Examples:
        >>> segments = [Segment("safe-high", "zoo:safe-high", 500), Segment("random", RANDOM_POLICY, 45)]
        >>> sum(segment.episodes for segment in segments)
        545
        >>> Segment("random", RANDOM_POLICY, 0)
        Traceback (most recent call last):
        ...
        ValueError: segment 'random': episodes must be >= 1, got 0
    """

    label: str
    policy: str
    episodes: int

    def __post_init__(self) -> None:
        if self.episodes < 1:
            raise ValueError(f"segment {self.label!r}: episodes must be >= 1, got {self.episodes}")


def resolve_policy(spec: str, env_id: str) -> ProbabilisticActor | TensorDictModule | None:
    """The actor a :class:`Segment` ``policy`` names (``None`` for the random policy)."""
    from spoil_torchrl.zoo.path_follower import ELLIPSE_PREFIX, ellipse_policy
    from spoil_torchrl.zoo.policy_files import load_policy, policy_path

    if spec == RANDOM_POLICY:
        return None
    if spec.startswith(ELLIPSE_PREFIX):
        if not env_id.startswith("SafetyPointCircle"):
            raise ValueError(
                f"{spec!r}: the ellipse follower drives a circle task's point robot, not {env_id}"
            )
        return ellipse_policy(spec)
    return load_policy(policy_path(spec, env_id), env_id=env_id)[0]


def reference_policies(env_id: str) -> dict[str, str | None]:
    """The policies whose mean returns normalise a generated dataset's returns: the random policy, and the
    committed ``safe-high`` policy where the task has one (``None`` where it has not)."""
    from spoil_torchrl.zoo.policy_files import zoo_names

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
            seed=derive_seed(seed, 99),
            progress=False,
            desc=f"reference {spec}",
        )
        for name, spec in reference_policies(env_id).items()
        if spec is not None
    }


#: The metadata entries :func:`collect` writes itself (a caller's ``metadata`` may not override them).
COLLECTOR_ENTRIES = frozenset(
    {
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
)


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
    components: bool = False,
) -> Path:
    """Roll out every segment's policy and write all episodes to ``path`` (DSRL layout, atomic).

    With ``components`` each constraint's own cost is recorded too, as ``cost_<name>`` arrays
    (:func:`~spoil_torchrl.envs.cost_components.cost_components` of the task; a task without them raises).

    The segments' and reference policies' rollouts are shared with ``workers`` worker processes
    (:class:`~spoil_torchrl.data.parallel.RolloutPool`; default: one per spare core once the rollouts reach
    :data:`SHARED_STEPS` steps, else none); the file is the same either way.

    The metadata (see :func:`~spoil_torchrl.data.read_metadata`) holds ``env_id``, ``seed``, ``num_envs``,
    ``cost_threshold`` (the task's episode-cost limit), ``segments`` (label, policy, episode range
    ``[start, stop)``, mean return and cost), ``random_return`` / ``safe_high_return``, the wall time, the
    software stack it was made on (``stack``: :func:`spoil_torchrl.stack.current_stack`), and ``metadata``'s
    entries.

    Examples:
        Three short random episodes of SafetyWalker2dVelocity-v1 (a walker that falls ends its episode), in
        two segments; the reference rollouts run one episode each:

        >>> import tempfile
        >>> from spoil_torchrl.data import load_episodes, read_metadata
        >>> segments = [Segment("random-a", RANDOM_POLICY, 2), Segment("random-b", RANDOM_POLICY, 1)]
        >>> path = collect("SafetyWalker2dVelocity-v1", segments, Path(tempfile.mkdtemp()) / "demo.hdf5",
        ...                num_envs=1, reference_episodes=1, progress=False, metadata={"note": "demo"})
        >>> meta = read_metadata(path)
        >>> {label: ids.tolist() for label, ids in segment_pools(meta).items()}
        {'random-a': [0, 1], 'random-b': [2]}
        >>> meta["cost_threshold"], meta["note"], meta["random_return"] < meta["safe_high_return"]
        (25.0, 'demo', True)
        >>> load_episodes(f"file:{path}")["episode"].unique().tolist()
        [0, 1, 2]
    """
    task = get_env_task(env_id)
    if not segments:
        raise ValueError("collect needs at least one segment")
    clash = COLLECTOR_ENTRIES & set(metadata or {})
    if clash:
        raise ValueError(f"metadata may not override the collector's own entries {sorted(clash)}")
    start_time = time.perf_counter()
    split = cost_components(env_id) if components else None
    jobs = [
        functools.partial(
            rollout,
            env_id,
            resolve_policy(segment.policy, env_id),
            segment.episodes,
            seed=derive_seed(seed, 10, k),
            num_envs=num_envs,
            progress=False,
            desc=f"{segment.label} ({segment.policy})",
            components=split,
        )
        for k, segment in enumerate(segments)
    ]
    references = reference_jobs(env_id, episodes=reference_episodes, seed=seed)
    jobs += references.values()
    results = _run_all(jobs, f"collecting {env_id}", task.episode_length, progress, workers)
    parts = results[: len(segments)]
    records = _segment_records(segments, parts)
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


def _run_all(
    jobs: list[functools.partial], desc: str, episode_length: int, progress: bool, workers: int | None
) -> list[dict[str, np.ndarray]]:
    """Every rollout job's arrays, in order, from this process and ``workers`` worker processes, under one
    progress bar over all of them (so that its estimate is the whole job's)."""
    total = sum(job.args[2] for job in jobs) * episode_length
    bar = tqdm(total=total, desc=desc, disable=not progress, unit="step", dynamic_ncols=True)
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
                bar.update(job.args[2] * episode_length)
            results.append(arrays)
    bar.close()
    return results


def _segment_records(segments: Sequence[Segment], parts: list[dict[str, np.ndarray]]) -> list[dict]:
    """Each segment's metadata record: its episode range in the file, mean return and cost (``parts``: its
    arrays)."""
    records, first = [], 0
    for segment, arrays in zip(segments, parts, strict=True):
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
    return records


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
