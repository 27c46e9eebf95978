"""Minari datasets both ways: :func:`write_minari` exports episodes, :func:`read_minari` loads them.

`Minari <https://minari.farama.org>`_ is Farama's standard format for offline-RL datasets. A dataset the
library loads (a DSRL file, a generated dataset, another Minari dataset) can be exported so that others load
it with ``minari.load_dataset``; a Minari dataset with per-step costs can be trained on with the source
``"minari:<dataset id>"``. The mapping (a table for other tools in ``docs/usage.md``, "Minari datasets"):

* an episode of ``T`` steps has ``observations`` of ``T + 1`` rows (the last is the final next observation),
  ``actions``, ``rewards``, ``terminations``, ``truncations`` of ``T`` rows -- Minari's own layout;
* the per-step cost is ``infos["cost"]`` with ``T + 1`` entries as Minari's ``DataCollector`` records infos
  (entry 0 belongs to the reset and is 0; entry ``t + 1`` is the cost of step ``t``). A dataset whose
  ``infos["cost"]`` has ``T`` entries is read too; one without costs cannot be used (IL-SP evaluates and
  labels by the true cost) and is refused with a clear error;
* each constraint's own cost, when the data carry several (``docs/several_constraints.md``), is
  ``infos["cost_<name>"]``, laid out as ``infos["cost"]``, and loads as the ``cost_<name>`` arrays of a
  DSRL-layout file; Safety-Gymnasium's ``cost_sum`` (the total, the task's cost) is not a constraint and is
  skipped. Every episode must carry the same constraints;
* an episode whose next observation differs from the following observation within the episode (not the case
  for data collected step by step) also carries ``infos["next_observation"]`` (``T + 1`` rows, row 0 unused);
* the episode metadata holds ``policy_type`` (the label of the policy that collected the episode, when the
  source records it) and one boolean ``role_<name>`` per IL-SP role exported with the data
  (``role_safe``, ``role_performant``, ``role_unlabeled``, ...);
* the dataset metadata holds ``ref_min_score`` / ``ref_max_score`` (the return range of the normalised
  return, so ``minari.get_normalized_score`` matches the library's) and ``spoil_torchrl`` (this library's
  metadata: ``env_id``, ``cost_threshold``, the collection segments, ...).

We use the ``minari`` package itself (extra ``[minari]``) rather than TorchRL's ``MinariExperienceReplay``: the
replay buffer drops ``infos`` and the episode metadata that carry the costs and roles, while the package reads
them episode by episode, and it is also the only writer.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

from spoil_torchrl.data.episodes import CONSTRAINTS_KEY, DSRL_KEYS, DatasetError, episodes_from_arrays
from spoil_torchrl.envs.cost_components import COMPONENT_PREFIX

#: Safety-Gymnasium's info entry for the sum of a task's costs: the task's cost, not one constraint's.
TOTAL_COST_INFO = "cost_sum"
INSTALL_HINT = "the minari package is not installed: pip install 'spoil_torchrl[minari]'"
#: Key of this library's entry in a Minari dataset's metadata.
METADATA_KEY = "spoil_torchrl"
ROLE_PREFIX = "role_"


def import_minari():
    """The ``minari`` module, or a :class:`ModuleNotFoundError` that says how to install it."""
    try:
        import minari
    except ModuleNotFoundError as err:
        raise ModuleNotFoundError(INSTALL_HINT) from err
    return minari


def minari_dataset_path(dataset_id: str) -> Path:
    """Where Minari keeps ``dataset_id`` locally (``$MINARI_DATASETS_PATH`` or ``~/.minari/datasets``)."""
    import_minari()
    from minari.storage import get_dataset_path

    return Path(get_dataset_path(dataset_id))


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


def _segments(labels: list[str | None]) -> list[dict]:
    """Runs of equal ``policy_type`` as collector-style segments (``label``, ``start``, ``stop``).

    Examples:
        >>> _segments(["a", "a", "b", None, "a"])
        [{'label': 'a', 'start': 0, 'stop': 2}, {'label': 'b', 'start': 2, 'stop': 3}, \
{'label': 'a', 'start': 4, 'stop': 5}]
    """
    out: list[dict] = []
    for e, label in enumerate(labels):
        if label is None:
            continue
        if out and out[-1]["label"] == label and out[-1]["stop"] == e:
            out[-1]["stop"] = e + 1
        else:
            out.append({"label": label, "start": e, "stop": e + 1})
    return out


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
    Minari dataset ``dataset_id`` (HDF5 storage), with costs, policy types and roles (see module docstring).

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


def _load(dataset_id: str, download: bool):
    """The :class:`minari.MinariDataset` ``dataset_id``, downloading it (Minari's remote) when not local."""
    minari = import_minari()
    path = minari_dataset_path(dataset_id)
    if not (path / "data").exists():
        if not download:
            raise DatasetError(f"Minari dataset {dataset_id!r} not found at {path}")
        try:
            minari.download_dataset(dataset_id)
        except Exception as err:  # noqa: BLE001 - network, unknown id, server: all end the same way
            raise DatasetError(
                f"Minari dataset {dataset_id!r} is not in {path.parent} and could not be downloaded "
                f"({type(err).__name__}: {err}); export it there with write_minari or set MINARI_DATASETS_PATH"
            ) from err
    try:
        return minari.load_dataset(dataset_id)
    except Exception as err:  # noqa: BLE001 - minari raises assorted errors for damaged folders
        raise DatasetError(f"Minari dataset {dataset_id!r} at {path} cannot be read ({err})") from err


def _per_step(values, length: int, name: str, source: str) -> np.ndarray:
    """An ``infos`` entry as one row per step: ``T + 1`` rows (DataCollector layout) lose row 0."""
    values = np.asarray(values)
    if values.ndim == 0:
        raise DatasetError(f"{source}: infos['{name}'] is one value, not one per step")
    if values.shape[0] == length + 1:
        return values[1:]
    if values.shape[0] == length:
        return values
    raise DatasetError(
        f"{source}: infos['{name}'] has {values.shape[0]} rows for an episode of {length} steps"
    )


def read_minari_episodes(dataset_id: str, *, download: bool = True) -> dict[str, np.ndarray]:
    """The DSRL-layout arrays of a Minari dataset (episodes back to back).

    An episode whose last step has neither flag (a collection cut short) gets ``timeouts`` at its last step, so
    that episodes stay apart.
    """
    dataset = _load(dataset_id, download)
    source = f"minari:{dataset_id}"
    import gymnasium

    for name, space in (("observation", dataset.observation_space), ("action", dataset.action_space)):
        if not isinstance(space, gymnasium.spaces.Box):
            raise DatasetError(
                f"{source}: the {name} space is {type(space).__name__}; only Box spaces are supported"
            )
    columns: dict[str, list[np.ndarray]] = {k: [] for k in DSRL_KEYS}
    constraints = None
    for episode in dataset.iterate_episodes():
        n = len(episode)
        infos = episode.infos or {}
        if "cost" not in infos:
            raise DatasetError(
                f"{source}: episode {episode.id} has no infos['cost']; IL-SP needs the per-step cost "
                "(record it as info['cost'] when collecting)"
            )
        keys = sorted(k for k in infos if k.startswith(COMPONENT_PREFIX) and k != TOTAL_COST_INFO)
        if constraints is None:
            constraints = keys
            columns |= {k: [] for k in keys}
        elif keys != constraints:
            raise DatasetError(
                f"{source}: episode {episode.id} carries the constraint costs {keys}, the first episode "
                f"{constraints}; every episode needs the same"
            )
        for key in keys:
            columns[key].append(_per_step(infos[key], n, key, source).reshape(n))
        obs = np.asarray(episode.observations).reshape(n + 1, -1)
        columns["observations"].append(obs[:-1])
        if "next_observation" in infos:
            next_obs = _per_step(infos["next_observation"], n, "next_observation", source).reshape(n, -1)
        else:
            next_obs = obs[1:]
        columns["next_observations"].append(next_obs)
        columns["actions"].append(np.asarray(episode.actions).reshape(n, -1))
        columns["rewards"].append(np.asarray(episode.rewards).reshape(n))
        columns["costs"].append(_per_step(infos["cost"], n, "cost", source).reshape(n))
        terminals = np.asarray(episode.terminations, dtype=bool).reshape(n)
        timeouts = np.asarray(episode.truncations, dtype=bool).reshape(n).copy()
        if n and not (terminals[-1] or timeouts[-1]):
            timeouts[-1] = True
        columns["terminals"].append(terminals)
        columns["timeouts"].append(timeouts)
    if not columns["rewards"]:
        raise DatasetError(f"{source}: the dataset has no episodes")
    return {k: np.concatenate(v) for k, v in columns.items()}


def read_minari(
    dataset_id: str,
    *,
    observation_dim: int | None = None,
    action_dim: int | None = None,
    download: bool = True,
) -> TensorDict:
    """Load the Minari dataset ``dataset_id`` as TED-layout transitions (like
    :func:`~spoil_torchrl.data.read_dsrl_file`), downloading it from Minari's remote when it is not local.

    Every problem is a :class:`~spoil_torchrl.data.DatasetError` naming the dataset: not found / not
    downloadable, non-Box spaces, no per-step cost, inconsistent lengths, NaN, wrong dimensions.
    """
    arrays = read_minari_episodes(dataset_id, download=download)
    return episodes_from_arrays(
        arrays, source=f"minari:{dataset_id}", observation_dim=observation_dim, action_dim=action_dim
    )


def read_minari_metadata(dataset_id: str) -> dict:
    """This library's metadata of a local Minari dataset (``{}`` for a plain one without roles or policy types).

    The ``spoil_torchrl`` entry, plus: ``segments`` rebuilt from the episodes' ``policy_type`` when the entry
    has none (:func:`_segments`), ``roles`` from the ``role_<name>`` flags (:func:`read_minari_roles`, as lists
    of episode ids), and Minari's ``ref_min_score`` / ``ref_max_score`` as ``return_range``.
    """
    dataset = _load(dataset_id, download=False)
    raw = dataset.storage.metadata
    metadata = dict(raw.get(METADATA_KEY) or {})
    per_episode = _episode_metadata(dataset)
    labels = [entry.get("policy_type") for entry in per_episode]
    if "segments" not in metadata and any(label is not None for label in labels):
        metadata["segments"] = _segments([None if v is None else str(v) for v in labels])
    roles = _roles(per_episode)
    if roles:
        metadata["roles"] = {name: ids.tolist() for name, ids in roles.items()}
    if "ref_min_score" in raw and "ref_max_score" in raw and "return_range" not in metadata:
        metadata["return_range"] = [float(raw["ref_min_score"]), float(raw["ref_max_score"])]
    return metadata


def _episode_metadata(dataset) -> list[dict]:
    """The metadata of every episode of a :class:`minari.MinariDataset`, in episode order."""
    return list(dataset.storage.get_episode_metadata(dataset.episode_indices))


def _roles(per_episode: list[dict]) -> dict[str, torch.Tensor]:
    """Episode ids per role from the ``role_<name>`` flags of the episodes' metadata."""
    flags: dict[str, list[int]] = {}
    for e, entry in enumerate(per_episode):
        for key, value in entry.items():
            if key.startswith(ROLE_PREFIX):
                ids = flags.setdefault(key[len(ROLE_PREFIX) :], [])
                if bool(value):
                    ids.append(e)
    return {name: torch.tensor(ids, dtype=torch.int64) for name, ids in flags.items()}


def read_minari_roles(dataset_id: str) -> dict[str, torch.Tensor]:
    """Episode ids per role from the episodes' ``role_<name>`` flags (``{}`` when the dataset has none).

    Examples are in :func:`write_minari`.
    """
    return _roles(_episode_metadata(_load(dataset_id, download=False)))
