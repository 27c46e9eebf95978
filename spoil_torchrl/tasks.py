"""Task registry: the 38 DSRL datasets and the paper's IL-SP thresholds, and the Safety-Gymnasium tasks the
project simulates.

The datasets are a table shipped with the package (``spoil_torchrl/dsrl_datasets.csv``, one row per dataset,
columns named by :class:`DSRLDataset`'s fields). Per-dataset constants (file name, episode length, R_max / R_min
used for return normalisation, max episode cost, trajectory count) are those of DSRL's ``dsrl/infos.py``
(liuzuxin/DSRL, commit 6cb1763); observation / action sizes and the IL-SP cost and return thresholds are the
paper's Table C, for the 21 tasks it used. Where no reliable source gives the sizes the cells are empty and a
loaded file's sizes are taken as they are. Nothing in the library hard-codes a task: look it up here.
"""

from __future__ import annotations

import csv
import difflib
import io
from dataclasses import dataclass, fields
from importlib import resources

#: Where DSRL hosts its files since Nov 2025 (the DSRL repository's README); ``<file>`` is appended.
DSRL_BASE_URL = "https://huggingface.co/datasets/YYY-45/DSRL/resolve/main/"


@dataclass(frozen=True)
class DSRLDataset:
    """One DSRL dataset and the constants needed to use it.

    Attributes:
        dataset_id: gym id of the offline environment, e.g. ``"OfflinePointCircle1Gymnasium-v0"``.
        file_name: the HDF5 file name, ``<EnvName>-<max cost>-<n traj>.hdf5``.
        episode_length: maximum episode length T.
        max_return, min_return: DSRL's normalisation constants, normalised return = (R - min) / (max - min).
        max_cost: largest episode cost in the dataset.
        n_trajectories: number of trajectories in the file.
        observation_dim, action_dim: sizes, or ``None`` where unknown.
        cost_threshold, return_threshold: the paper's Table C values (``None`` for tasks it did not use).
        paper_name: the task's name in the paper's tables, if it used it.
        suite: the benchmark the task comes from (Bullet-Safety-Gym, Safety-Gymnasium navigation / velocity,
            Safe MetaDrive).
        note: what a reader of the table should know about the row (a disagreement between the sources).
    """

    dataset_id: str
    file_name: str
    episode_length: int
    max_return: float
    min_return: float
    max_cost: float
    observation_dim: int | None = None
    action_dim: int | None = None
    cost_threshold: float | None = None
    return_threshold: float | None = None
    paper_name: str | None = None
    suite: str = ""
    note: str = ""

    @property
    def n_trajectories(self) -> int:
        return int(self.file_name.rsplit("-", 1)[1].split(".")[0])

    @property
    def url(self) -> str:
        return DSRL_BASE_URL + self.file_name


#: The table of DSRL datasets shipped with the package: a header row naming :class:`DSRLDataset`'s fields, one row
#: per dataset (an empty cell: ``None`` / no note).
DSRL_TABLE = "dsrl_datasets.csv"


def _cell(text: str) -> int | float | str:
    """A table cell as the value it writes: an integer -> ``int``, another number -> ``float``, else the text."""
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def read_table(text: str, kind: type) -> list:
    r"""The rows of a table (CSV with a header row naming fields of the dataclass ``kind``) as ``kind``s; an empty
    cell takes the field's default, and a cell of a ``str`` field stays text (never read as a number).

    Examples:
        >>> rows = read_table(
        ...     "dataset_id,file_name,episode_length,max_return,min_return,max_cost\n"
        ...     "OfflineX-v0,SafetyX-v0-10-5.hdf5,100,10.5,0.0,10.0\n", DSRLDataset)
        >>> rows[0].max_return, rows[0].min_return, rows[0].n_trajectories, rows[0].cost_threshold
        (10.5, 0.0, 5, None)
        >>> read_table("dataset_id,file_name,length\n", DSRLDataset)
        Traceback (most recent call last):
        ...
        ValueError: DSRLDataset table: unknown columns ['length']; the columns are DSRLDataset's fields
    """
    name = kind.__name__
    reader = csv.DictReader(io.StringIO(text))
    known = {f.name for f in fields(kind)}
    unknown = [column for column in reader.fieldnames or [] if column not in known]
    if unknown:
        raise ValueError(f"{name} table: unknown columns {unknown}; the columns are {name}'s fields")
    text = {f.name for f in fields(kind) if str(f.type).startswith("str")}
    rows = []
    for line, row in enumerate(reader, start=2):
        values = {key: value if key in text else _cell(value) for key, value in row.items() if value != ""}
        try:
            rows.append(kind(**values))
        except TypeError as err:
            raise ValueError(f"{name} table, line {line}: {err}") from None
    return rows


def _packaged_table(file_name: str, kind: type, key: str) -> dict:
    """A table shipped with the package, by its ``key`` field (an id listed twice is an error)."""
    rows = read_table(resources.files("spoil_torchrl").joinpath(file_name).read_text(), kind)
    ids = [getattr(row, key) for row in rows]
    if len(set(ids)) != len(ids):
        raise ValueError(f"{file_name}: ids listed twice: {sorted({i for i in ids if ids.count(i) > 1})}")
    return dict(zip(ids, rows, strict=True))


DSRL_DATASETS: dict[str, DSRLDataset] = _packaged_table(DSRL_TABLE, DSRLDataset, "dataset_id")


class UnknownDatasetError(KeyError):
    """A dataset id that is not in :data:`DSRL_DATASETS`."""

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0])


def _match_key(name: str) -> str:
    """A name reduced to what tells datasets apart, for suggestions ("OfflinePointCircle1Gymnasium-v0" ->
    "pointcircle1")."""
    key = name.lower().removeprefix("offline").replace("gymnasium", "").replace("safety", "")
    return key.rsplit("-v", 1)[0].strip("-")


def get_dsrl_dataset(dataset_id: str) -> DSRLDataset:
    """Look up a DSRL dataset by id; an unknown id raises with the closest valid ids.

    Examples:
        >>> get_dsrl_dataset("OfflineCarCircle-v0").n_trajectories
        1450
        >>> get_dsrl_dataset("OfflinePointCircle1-v0")
        Traceback (most recent call last):
        ...
        spoil_torchrl.tasks.UnknownDatasetError: unknown DSRL dataset 'OfflinePointCircle1-v0'; did you mean \
'OfflinePointCircle1Gymnasium-v0', 'OfflinePointCircle2Gymnasium-v0', 'OfflineAntCircle-v0'?
    """
    if dataset_id in DSRL_DATASETS:
        return DSRL_DATASETS[dataset_id]
    by_key = {_match_key(d): d for d in DSRL_DATASETS}
    close = difflib.get_close_matches(_match_key(dataset_id), list(by_key), n=3, cutoff=0.0)
    suggestion = ", ".join(repr(by_key[c]) for c in close)
    raise UnknownDatasetError(f"unknown DSRL dataset {dataset_id!r}; did you mean {suggestion}?")


@dataclass(frozen=True)
class EnvTask:
    """A Safety-Gymnasium task the project simulates (collection, experts, evaluation).

    Attributes:
        env_id: Safety-Gymnasium id, e.g. ``"SafetyPointCircle1-v0"``.
        episode_length: time limit T of the registered environment.
        cost_limit: episode-cost limit of the constrained experts (paper Table G: 25).
        observation_dim, action_dim: sizes of the flat observation and action.
        cost_rule: the task's cost in words (checked by the tests).
        velocity_threshold: speed above which a velocity task costs 1 (``None`` for navigation tasks).
        dsrl_id: the matching DSRL dataset, for its normalisation constants.
        action_bound: every action coordinate lies in ``[-action_bound, action_bound]`` (the simulator's box,
            which the tanh-squashed policies span).
    """

    env_id: str
    episode_length: int
    cost_limit: float
    observation_dim: int
    action_dim: int
    cost_rule: str
    velocity_threshold: float | None = None
    dsrl_id: str | None = None
    action_bound: float = 1.0


#: The simulated tasks (a table shipped with the package, columns named by :class:`EnvTask`'s fields). Sizes
#: and cost rules: measured with safety-gymnasium 1.0.0; cost limit: the paper's Table G.
ENV_TABLE = "env_tasks.csv"
ENV_TASKS: dict[str, EnvTask] = _packaged_table(ENV_TABLE, EnvTask, "env_id")


def get_env_task(env_id: str) -> EnvTask:
    """Look up a simulated task; an unknown id raises with the closest ids.

    Examples:
        >>> get_env_task("SafetyPointCircle1-v0").episode_length
        500
    """
    if env_id in ENV_TASKS:
        return ENV_TASKS[env_id]
    close = difflib.get_close_matches(env_id, list(ENV_TASKS), n=3, cutoff=0.0)
    raise UnknownDatasetError(f"unknown task {env_id!r}; did you mean {', '.join(map(repr, close))}?")
