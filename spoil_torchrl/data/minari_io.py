"""Minari datasets both ways: :func:`read_minari` loads them; :func:`~spoil_torchrl.data.minari_export.write_minari`
(in :mod:`~spoil_torchrl.data.minari_export`) exports episodes in the same layout.

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

from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

from spoil_torchrl.data.episodes import DSRL_KEYS, DatasetError, episodes_from_arrays
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

    Examples are in :func:`~spoil_torchrl.data.minari_export.write_minari`.
    """
    return _roles(_episode_metadata(_load(dataset_id, download=False)))
