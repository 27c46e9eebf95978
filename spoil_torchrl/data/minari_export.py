"""Exporting episodes as a Minari dataset: :func:`write_minari`, in the layout that
:mod:`~spoil_torchrl.data.minari_io` documents and reads back (costs as ``infos``, policy types and IL-SP roles
as episode metadata, the return range as Minari's reference scores).
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

from spoil_torchrl.data.episodes import CONSTRAINTS_KEY, DatasetError
from spoil_torchrl.data.minari_io import METADATA_KEY, ROLE_PREFIX, import_minari
from spoil_torchrl.envs.cost_components import COMPONENT_PREFIX


def _episode_bounds(episodes: TensorDict) -> list[torch.Tensor]:
    """Row indices of each episode, in episode-id order (rows of one episode keep their order)."""
    ids = episodes["episode"]
    order = torch.sort(ids, stable=True).indices
    counts = torch.bincount(ids[order] - ids.min()).tolist()
    return [part for part in torch.split(order, counts) if part.numel()]


def _policy_types(metadata: Mapping, n_episodes: int) -> list[str | None]:
    """The segment label of every episode id, from a collected file's ``segments`` (None where unknown)."""
    labels: list[str | None] = [None] * n_episodes
    for segment in metadata.get("segments", []):
        for e in range(int(segment["start"]), min(int(segment["stop"]), n_episodes)):
            labels[e] = str(segment["label"])
    return labels


def write_minari(
    episodes: TensorDict,
    dataset_id: str,
    *,
    metadata: Mapping | None = None,
    roles: Mapping[str, torch.Tensor] | None = None,
    return_range: tuple[float, float] | None = None,
    description: str | None = None,
    author: str | None = None,
    author_email: str | None = None,
    code_permalink: str | None = None,
    overwrite: bool = False,
):
    """Export TED-layout ``episodes`` (as :func:`~spoil_torchrl.data.load_episodes` returns them) as the local
    Minari dataset ``dataset_id`` (HDF5 storage), with costs, policy types and roles (the layout:
    :mod:`~spoil_torchrl.data.minari_io`).

    Args:
        episodes: transitions with ``episode`` ids; every episode is exported, in id order, as Minari episode
            ``0, 1, ...`` (so ids are kept when they are ``0..n-1``, as after loading).
        dataset_id: Minari id, ``[namespace/]name-v<version>``.
        metadata: the source's metadata (``env_id``, ``cost_threshold``, ``segments``, ...; stored under
            ``spoil_torchrl``; ``segments`` also give each episode's ``policy_type``).
        roles: episode ids per IL-SP role (e.g. ``PreparedDataset.roles``), stored as ``role_<name>`` flags.
        return_range: ``(R_min, R_max)``, stored as Minari's ``ref_min_score`` / ``ref_max_score``.
        description, author, author_email, code_permalink: Minari's descriptive metadata (optional).
        overwrite: replace an existing local dataset of that id (otherwise it is an error).

    Returns:
        the :class:`minari.MinariDataset`.

    Examples:
        >>> import os, tempfile; from unittest import mock
        >>> where = mock.patch.dict(os.environ, {"MINARI_DATASETS_PATH": tempfile.mkdtemp()}); _ = where.start()
        >>> arrays = {"observations": np.zeros((3, 2), np.float32), "next_observations": np.zeros((3, 2), np.float32),
        ...           "actions": np.zeros((3, 1), np.float32), "rewards": np.ones(3, np.float32),
        ...           "costs": np.array([0, 1, 0], np.float32), "terminals": np.zeros(3, bool),
        ...           "timeouts": np.array([0, 1, 1], bool)}
        >>> from spoil_torchrl.data.episodes import episodes_from_arrays
        >>> from spoil_torchrl.data.minari_io import read_minari, read_minari_roles
        >>> episodes = episodes_from_arrays(arrays)
        >>> dataset = write_minari(episodes, "demo/tiny-v0", roles={"safe": torch.tensor([1])})
        >>> dataset.total_episodes, dataset.total_steps
        (2, 3)
        >>> (read_minari("demo/tiny-v0") == episodes).all(), read_minari_roles("demo/tiny-v0")
        (True, {'safe': tensor([1])})
        >>> _ = where.stop()
    """
    minari = import_minari()
    from minari.data_collector.episode_buffer import EpisodeBuffer
    from minari.storage import get_dataset_path

    if "episode" not in episodes.keys():
        raise DatasetError(
            "write_minari needs TED-layout transitions with 'episode' ids (load_episodes' output)"
        )
    path = Path(get_dataset_path(dataset_id))
    if path.exists():
        if not overwrite:
            raise FileExistsError(
                f"Minari dataset {dataset_id!r} already exists at {path}; pass overwrite=True"
            )
        minari.delete_dataset(dataset_id)
    # roles travel as episode flags (below), and the reference scores as Minari's own entries
    metadata = {k: v for k, v in (metadata or {}).items() if k not in ("roles", "return_range")}
    parts = _episode_bounds(episodes)
    episode_ids = [int(episodes["episode"][rows[0]]) for rows in parts]
    labels = _policy_types(metadata, max(episode_ids) + 1)
    if episode_ids != list(range(len(episode_ids))):
        # a subset: the segments' episode ranges no longer hold; each episode keeps its policy_type instead
        metadata.pop("segments", None)
    buffers = [_episode_buffer(EpisodeBuffer, k, episodes[rows]) for k, rows in enumerate(parts)]
    info = {
        "algorithm_name": str(metadata.get("name", "spoil_torchrl export")),
        "description": description or str(metadata.get("description", "exported by spoil_torchrl")),
        "author": author,
        "author_email": author_email,
        "code_permalink": code_permalink,
    }
    with warnings.catch_warnings():
        # Minari recommends (by warnings) an author, e-mail, code link and env spec; they are optional, and the
        # task is recorded in our metadata (env_id) and as eval_env where gymnasium knows it
        warnings.filterwarnings("ignore", category=UserWarning, module="minari.utils")
        dataset = _create(minari, dataset_id, buffers, episodes, metadata, info)
    per_episode = _exported_episode_metadata(episode_ids, roles or {}, labels)
    if any(per_episode):
        dataset.storage.update_episode_metadata(per_episode, range(len(per_episode)))
    extra = {METADATA_KEY: metadata}
    if return_range is not None:
        extra.update(ref_min_score=float(return_range[0]), ref_max_score=float(return_range[1]))
    dataset.storage.update_metadata(extra)
    return dataset


def _episode_buffer(buffer_class, k: int, step: TensorDict):
    """Minari's episode buffer ``k`` for one episode's TED transitions ``step``: observations with the last next
    observation appended, the per-step costs (and each constraint's) as ``infos`` with a leading 0 for the reset,
    and the next observations themselves only where they differ from the following observations."""
    obs = step["observation"].numpy()
    next_obs = step["next", "observation"].numpy()
    cost = step["next", "cost"].reshape(-1).numpy()
    infos = {"cost": np.concatenate([np.zeros(1, cost.dtype), cost])}
    constraints = step.get(("next", CONSTRAINTS_KEY), None)
    for name in [] if constraints is None else constraints.keys():
        part = constraints[name].reshape(-1).numpy()
        infos[COMPONENT_PREFIX + name] = np.concatenate([np.zeros(1, part.dtype), part])
    if not np.array_equal(next_obs[:-1], obs[1:]):
        infos["next_observation"] = np.concatenate([np.zeros_like(next_obs[:1]), next_obs])
    return buffer_class(
        id=k,
        observations=np.concatenate([obs, next_obs[-1:]]),
        actions=step["action"].numpy(),
        rewards=step["next", "reward"].reshape(-1).numpy(),
        terminations=step["next", "terminated"].reshape(-1).numpy(),
        truncations=step["next", "truncated"].reshape(-1).numpy(),
        infos=infos,
    )


def _exported_episode_metadata(
    episode_ids: list[int], roles: Mapping[str, torch.Tensor], labels: list[str | None]
) -> list[dict]:
    """Each exported episode's metadata: a ``role_<name>`` flag per role, and its ``policy_type`` if known."""
    role_sets = {name: set(torch.as_tensor(ids).tolist()) for name, ids in roles.items()}
    per_episode = []
    for e in episode_ids:
        entry = {ROLE_PREFIX + name: e in ids for name, ids in role_sets.items()}
        if labels[e] is not None:
            entry["policy_type"] = labels[e]
        per_episode.append(entry)
    return per_episode


def _env_spec(env_id: str | None):
    """gymnasium's spec of ``env_id`` (importing Safety-Gymnasium for its tasks), or None when unknown."""
    import gymnasium

    if env_id is None:
        return None
    try:
        from spoil_torchrl.envs.compat import import_safety_gymnasium
        from spoil_torchrl.tasks import ENV_TASKS

        if env_id in ENV_TASKS:
            import_safety_gymnasium()
        return gymnasium.spec(env_id)
    except Exception:  # noqa: BLE001 - not installed / not registered: the dataset simply has no env spec
        return None


def _create(minari, dataset_id, buffers, episodes, metadata, info):
    """``minari.create_dataset_from_buffers`` with Box spaces of the data's sizes (HDF5 storage)."""
    import gymnasium

    def box(x: torch.Tensor) -> gymnasium.spaces.Box:
        return gymnasium.spaces.Box(-np.inf, np.inf, shape=tuple(x.shape[1:]), dtype=np.float32)

    return minari.create_dataset_from_buffers(
        dataset_id,
        buffers,
        eval_env=_env_spec(metadata.get("env_id")),
        observation_space=box(episodes["observation"]),
        action_space=box(episodes["action"]),
        data_format="hdf5",
        **info,
    )
