"""The trajectory buffer an expert's training leaves behind: the raw material of the replay datasets (paper F.2).

The paper's replay datasets come from PPO-Lagrangian training: "at every epoch we rolled out trajectories using
the current policy and stored a fixed amount of trajectories into a replay buffer". :class:`ReplayRecorder`
does that inside :func:`~spoil_torchrl.experts.train_ppo` (``PPOConfig.record_episodes``): from every batch the
first ``episodes`` episodes that finished in it (complete trajectories only: one cut by the batch's end is not
kept) go into ``replay/batch_<index>.pt``, written atomically, in the DSRL field layout. A resumed training
rewrites the files of the batches it repeats with the same content. :func:`read_replay` joins them, in training
order, into one set of arrays with each transition's batch index.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

from spoil_torchrl.files import save_atomic

#: The DSRL fields a replay file holds, and the batch key each comes from.
REPLAY_FIELDS = {
    "observations": "observation",
    "actions": "action",
    "next_observations": ("next", "observation"),
    "rewards": ("next", "reward"),
    "costs": ("next", "cost"),
    "terminals": ("next", "terminated"),
    "timeouts": ("next", "truncated"),
}


class ReplayRecorder:
    """Keeps the first ``episodes`` finished episodes of every training batch under ``directory``.

    Examples:
        >>> import tempfile
        >>> done = torch.tensor([False, True, False, True, False]).unsqueeze(-1)
        >>> batch = TensorDict({"observation": torch.arange(5.).unsqueeze(-1), "action": torch.zeros(5, 1),
        ...     "next": {"observation": torch.arange(1., 6.).unsqueeze(-1), "reward": torch.ones(5, 1),
        ...              "cost": torch.zeros(5, 1), "terminated": torch.zeros_like(done), "truncated": done,
        ...              "done": done}}, [5])
        >>> directory = Path(tempfile.mkdtemp())
        >>> ReplayRecorder(directory, episodes=1).record(batch, 0)  # the first of its two finished episodes
        1
        >>> read_replay(directory)["observations"].ravel().tolist()
        [0.0, 1.0]
    """

    def __init__(self, directory: str | os.PathLike, episodes: int) -> None:
        if episodes < 1:
            raise ValueError(f"episodes = {episodes}: expected an integer >= 1")
        self.directory = Path(directory)
        self.episodes = episodes

    def record(self, batch: TensorDict, index: int) -> int:
        """Store up to ``episodes`` of ``batch``'s finished episodes as ``batch_<index>.pt``; returns how many.
        A ``[num_envs, T]`` batch gives its first environment's finished episodes first, then the next's."""
        rows = batch.unbind(0) if batch.ndim == 2 else [batch]
        kept, count = [], 0
        for row in rows:
            ends = (row["next", "done"].reshape(-1).nonzero().squeeze(-1) + 1).tolist()[
                : self.episodes - count
            ]
            if ends:
                kept.append(row[: ends[-1]])
                count += len(ends)
        stop = sum(part.shape[0] for part in kept)
        arrays = {
            name: torch.cat([part.get(key).reshape(part.shape[0], -1) for part in kept]).squeeze(-1)
            if kept
            else batch.reshape(-1).get(key)[:0]
            for name, key in REPLAY_FIELDS.items()
        }
        if stop and not bool((arrays["terminals"] | arrays["timeouts"])[stop - 1]):
            raise RuntimeError(
                f"batch {index}: an episode ends with done but neither terminated nor truncated"
            )
        save_atomic(
            {**{k: v.clone() for k, v in arrays.items()}, "batch": index},
            self.directory / f"batch_{index:06d}.pt",
        )
        return count


def read_replay(directory: str | os.PathLike) -> dict[str, np.ndarray]:
    """Every recorded batch of ``directory`` joined in training order (the DSRL fields plus ``batch``: each
    transition's training-batch index). A folder with no recorded batch is an error, not an empty buffer."""
    directory = Path(directory)
    files = sorted(directory.glob("batch_*.pt"))
    if not files:
        raise FileNotFoundError(
            f"{directory}: no recorded batch (batch_<index>.pt); train with ppo.record_episodes > 0"
        )
    indices = [int(path.stem.split("_")[1]) for path in files]
    missing = sorted(set(range(indices[-1] + 1)) - set(indices))
    if missing:  # e.g. a training resumed on a machine without the earlier batches' files
        raise ValueError(
            f"{directory}: the buffer is incomplete: {len(missing)} of {indices[-1] + 1} batches are missing "
            f"(first {missing[0]}); a replay dataset needs the whole training's buffer"
        )
    parts: dict[str, list[np.ndarray]] = {name: [] for name in [*REPLAY_FIELDS, "batch"]}
    for path in files:
        stored = torch.load(path, weights_only=True)
        for name in REPLAY_FIELDS:
            parts[name].append(stored[name].numpy())
        parts["batch"].append(np.full(len(stored["rewards"]), int(stored["batch"]), dtype=np.int64))
    return {name: np.concatenate(values) for name, values in parts.items()}


def write_replay_dataset(
    directory: str | os.PathLike,
    path: str | os.PathLike,
    env_id: str,
    *,
    reference_episodes: int = 10,
    seed: int = 0,
    metadata: dict | None = None,
) -> Path:
    """A replay dataset file (DSRL layout, atomic, :func:`~spoil_torchrl.data.hdf5.write_dsrl_file`) from the
    trajectory buffer ``directory`` of an expert's training in ``env_id``.

    Its metadata holds what the ``replay`` labelling scheme and the normalisation need: ``env_id``, the task's
    ``cost_threshold``, the ``random_return`` and ``safe_high_return`` of the reference policies
    (:func:`~spoil_torchrl.data.collect.reference_jobs`: the committed ``safe-high`` policy's mean return is the
    safe-optimal return that labels performant trajectories), ``replay`` (the buffer's folder, its batches and
    episodes, and each episode's training batch in ``episode_batches``), the software ``stack`` and
    ``metadata``'s entries.
    """
    from spoil_torchrl.data.collect import reference_jobs
    from spoil_torchrl.data.hdf5 import write_dsrl_file
    from spoil_torchrl.envs.rollout import episode_bounds, episode_totals
    from spoil_torchrl.stack import current_stack
    from spoil_torchrl.tasks import get_env_task

    task = get_env_task(env_id)
    arrays = read_replay(directory)
    batch = arrays.pop("batch")
    if (
        arrays["observations"].shape[-1] != task.observation_dim
        or arrays["actions"].shape[-1] != task.action_dim
    ):
        raise ValueError(
            f"{directory}: observation/action sizes {arrays['observations'].shape[-1]}/"
            f"{arrays['actions'].shape[-1]}, but {env_id} has {task.observation_dim}/{task.action_dim}: the "
            "buffer belongs to another task"
        )
    starts, _ = episode_bounds(arrays)
    references = {
        name: float(episode_totals(job())[0].mean())
        for name, job in reference_jobs(env_id, episodes=reference_episodes, seed=seed).items()
    }
    returns, costs = episode_totals(arrays)
    meta = {
        "env_id": env_id,
        "cost_threshold": task.cost_limit,
        "random_return": references.get("random_return"),
        "safe_high_return": references.get("safe_high_return"),
        "replay": {
            "source": str(Path(directory).resolve()),
            "batches": int(batch.max()) + 1,
            "episodes": len(starts),
            "episode_batches": batch[starts].tolist(),
            "mean_return": float(returns.mean()),
            "mean_cost": float(costs.mean()),
        },
        "steps": int(arrays["rewards"].shape[0]),
        "stack": current_stack(),
        **(metadata or {}),
    }
    return write_dsrl_file(path, arrays, metadata=meta)
