"""Flat DSRL-layout arrays -> one TensorDict of transitions in TorchRL's TED layout, with episode ids.

Keys of the result: ``observation``, ``action``, ``("next", "observation")``,
``("next", "reward")``, ``("next", "cost")`` (float32, trailing dim 1), ``("next", "terminated")``,
``("next", "truncated")``, ``("next", "done")`` (bool, trailing dim 1), ``episode`` (int64) and ``is_init``
(bool, trailing dim 1). A step cut by a time limit keeps its real next observation.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Mapping, Sequence

import numpy as np
import torch
from tensordict import TensorDict

from spoil_torchrl.envs.cost_components import COMPONENT_PREFIX
from spoil_torchrl.modules.normalization import ObservationNormalizer

#: The arrays of a DSRL HDF5 file (flat, episodes back to back).
DSRL_KEYS = ("observations", "next_observations", "actions", "rewards", "costs", "terminals", "timeouts")


class DatasetError(ValueError):
    """A dataset that cannot be used as it is (missing keys, bad shapes, non-finite values, ...).

    Its message names the dataset and the problem in one line, so a recipe can report it as it is.

    Examples:
        >>> from spoil_torchrl.data import load_episodes
        >>> try:
        ...     load_episodes("file:/no/such/data.hdf5")
        ... except DatasetError as err:
        ...     print(err)
        /no/such/data.hdf5: no such file
        >>> issubclass(DatasetError, ValueError)
        True
    """


def _tensor(x) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x
    return torch.from_numpy(np.asarray(x))


def _flag(x: torch.Tensor, name: str, source: str) -> torch.Tensor:
    if x.dtype == torch.bool:
        return x
    if not torch.isfinite(x.double() if x.is_floating_point() else x.to(torch.float64)).all():
        raise DatasetError(f"{source}: '{name}' contains NaN or infinite values")
    values = torch.unique(x)
    if not bool(((values == 0) | (values == 1)).all()):
        raise DatasetError(f"{source}: '{name}' must hold 0/1 flags, found values {values[:5].tolist()}")
    return x != 0


#: Where the components live in the transitions: ``("next", CONSTRAINTS_KEY, <name>)``.
CONSTRAINTS_KEY = "constraint_costs"
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


def check_constraint_name(name: str, source: str) -> None:
    """Refuse a constraint name that cannot be a key and a role suffix (``safe_<name>``).

    Examples:
        >>> check_constraint_name("x_wall", "demo.hdf5")
        >>> check_constraint_name("x wall", "demo.hdf5")
        Traceback (most recent call last):
        ...
        spoil_torchrl.data.episodes.DatasetError: demo.hdf5: constraint name 'x wall' must be letters, digits and _
    """
    if not isinstance(name, str) or not _NAME.match(name):
        raise DatasetError(f"{source}: constraint name {name!r} must be letters, digits and _")


def split_cost_components(
    arrays: Mapping[str, object], *, source: str = "arrays", names: Sequence[str] | None = None
) -> tuple[dict, dict[str, torch.Tensor]]:
    """``(arrays, components)``: the DSRL arrays with a one-column ``costs`` (the task's cost), and the
    constraints' own costs by name (``{}`` when the data have none), checked.

    ``names`` names the columns of a ``costs`` of shape ``[N, K]`` (the file's metadata ``constraints``);
    ``cost_<name>`` arrays name themselves.

    Examples:
        >>> arrays = {"costs": np.array([[0.0, 1.0], [2.0, 0.0]], np.float32)}
        >>> total, parts = split_cost_components(arrays, names=["x_wall", "y_wall"])
        >>> total["costs"].tolist(), {k: v.tolist() for k, v in parts.items()}
        ([1.0, 2.0], {'x_wall': [0.0, 2.0], 'y_wall': [1.0, 0.0]})
        >>> split_cost_components(arrays, names=["x_wall"])  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        spoil_torchrl.data.episodes.DatasetError: arrays: 'costs' has 2 columns, but 1 constraint names ...
    """
    out = dict(arrays)
    named = {
        k[len(COMPONENT_PREFIX) :]: _tensor(v) for k, v in arrays.items() if k.startswith(COMPONENT_PREFIX)
    }
    for key in [k for k in out if k.startswith(COMPONENT_PREFIX)]:
        del out[key]
    costs = _tensor(arrays["costs"]) if "costs" in arrays else None
    columns = costs.shape[1] if costs is not None and costs.ndim == 2 else 1
    if columns > 1:
        if named:
            raise DatasetError(
                f"{source}: 'costs' has {columns} columns and the file has {len(named)} cost_<name> arrays too; "
                "store the constraints' costs one way (docs/several_constraints.md)"
            )
        names = list(names) if names is not None else [f"c{k}" for k in range(columns)]
        if len(names) != columns:
            raise DatasetError(
                f"{source}: 'costs' has {columns} columns, but {len(names)} constraint names are given "
                f"({names}); name one constraint per column"
            )
        components = {name: costs[:, k] for k, name in enumerate(names)}
        out["costs"] = costs.double().sum(1).to(costs.dtype)
    else:
        components = named
    if len(set(components)) != len(components):
        raise DatasetError(f"{source}: constraint names repeat ({list(components)})")
    rows = None if costs is None else costs.shape[0]
    for name, value in components.items():
        check_constraint_name(name, source)
        value = value.squeeze(1) if value.ndim == 2 and value.shape[1] == 1 else value
        if value.ndim != 1 or (rows is not None and value.shape[0] != rows):
            raise DatasetError(
                f"{source}: constraint {name!r}'s costs have shape {tuple(value.shape)}; expected [{rows}], one per "
                "transition like 'costs'"
            )
        if not value.is_floating_point() or not bool(torch.isfinite(value).all()):
            raise DatasetError(f"{source}: constraint {name!r}'s costs must be finite floating-point numbers")
        if bool((value < 0).any()):
            raise DatasetError(f"{source}: constraint {name!r} has negative costs; costs must be >= 0")
        components[name] = value
    return out, components


def _first_non_finite_row(value: torch.Tensor, chunk_rows: int = 1 << 16) -> int:
    """Index of the first row holding NaN / inf, or -1. Works in row chunks: ``torch.isfinite`` on a whole
    multi-GB array would allocate temporaries as large as the array itself."""
    for start in range(0, value.shape[0], chunk_rows):
        ok = torch.isfinite(value[start : start + chunk_rows])
        if not bool(ok.all()):
            return start + int((~ok).reshape(ok.shape[0], -1).any(-1).nonzero()[0, 0])
    return -1


def validate_arrays(
    arrays: Mapping[str, object],
    *,
    source: str = "arrays",
    observation_dim: int | None = None,
    action_dim: int | None = None,
) -> dict[str, torch.Tensor]:
    """Check DSRL-layout arrays and return them as tensors (no copy where the input is already a tensor/array).

    Raises :class:`DatasetError` naming ``source`` for: a missing key, an empty dataset, arrays of different
    lengths, observations / actions that are not 2-D (or 1-D actions, taken as one action dim), NaN or infinite
    values, negative costs, non-0/1 flags, and sizes that differ from ``observation_dim`` / ``action_dim``.

    Examples:
        >>> arrays = {k: np.zeros((3, 2), np.float32) for k in ("observations", "next_observations", "actions")}
        >>> arrays.update({k: np.zeros(3, np.float32) for k in ("rewards", "costs", "terminals", "timeouts")})
        >>> del arrays["costs"]
        >>> validate_arrays(arrays, source="demo.hdf5")
        Traceback (most recent call last):
        ...
        spoil_torchrl.data.episodes.DatasetError: demo.hdf5: missing array 'costs' (a DSRL file has observations, \
next_observations, actions, rewards, costs, terminals, timeouts)
    """
    missing = [k for k in DSRL_KEYS if k not in arrays]
    if missing:
        raise DatasetError(f"{source}: missing array '{missing[0]}' (a DSRL file has {', '.join(DSRL_KEYS)})")
    for key in ("terminals", "timeouts"):  # text or objects cannot be flags (numbers and bools can)
        kind = getattr(getattr(arrays[key], "dtype", None), "kind", "f")
        if kind not in "biuf" and not isinstance(arrays[key], torch.Tensor):
            raise DatasetError(
                f"{source}: '{key}' must hold 0/1 flags (bool or numbers), got dtype {arrays[key].dtype}"
            )
    out = {k: _tensor(arrays[k]) for k in DSRL_KEYS}
    lengths = {k: v.shape[0] if v.ndim else 0 for k, v in out.items()}
    if len(set(lengths.values())) != 1:
        raise DatasetError(f"{source}: arrays have different lengths {lengths}")
    n = lengths["observations"]
    if n == 0:
        raise DatasetError(f"{source}: the dataset is empty")
    if out["actions"].ndim == 1:
        out["actions"] = out["actions"].unsqueeze(-1)
    for key in ("observations", "next_observations", "actions"):
        if out[key].ndim != 2:
            raise DatasetError(f"{source}: '{key}' must be 2-D [N, dim], got shape {tuple(out[key].shape)}")
    for key in ("rewards", "costs", "terminals", "timeouts"):
        if out[key].ndim == 2 and out[key].shape[1] == 1:
            out[key] = out[key].squeeze(1)
        if out[key].ndim != 1:
            raise DatasetError(f"{source}: '{key}' must be 1-D [N], got shape {tuple(out[key].shape)}")
    if out["observations"].shape != out["next_observations"].shape:
        raise DatasetError(
            f"{source}: observations {tuple(out['observations'].shape)} and next_observations "
            f"{tuple(out['next_observations'].shape)} differ in shape"
        )
    for key in ("observations", "next_observations", "actions", "rewards", "costs"):
        value = out[key]
        if not value.is_floating_point():
            raise DatasetError(f"{source}: '{key}' must be floating point, got {value.dtype}")
        bad = _first_non_finite_row(value)
        if bad >= 0:
            raise DatasetError(f"{source}: '{key}' contains NaN or infinite values (first at row {bad})")
    negative = (out["costs"] < 0).nonzero()
    if negative.numel():
        raise DatasetError(
            f"{source}: {negative.numel()} costs are negative (first at row {int(negative[0])}: "
            f"{float(out['costs'][negative[0]]):.4g}); costs must be >= 0, as the labelling (safe iff the episode "
            "cost is <= the threshold) and the normalised cost assume"
        )
    for key, expected, actual in (
        ("observation", observation_dim, out["observations"].shape[1]),
        ("action", action_dim, out["actions"].shape[1]),
    ):
        if expected is not None and expected != actual:
            raise DatasetError(f"{source}: {key} dimension is {actual}, but the task expects {expected}")
    out["terminals"] = _flag(out["terminals"], "terminals", source)
    out["timeouts"] = _flag(out["timeouts"], "timeouts", source)
    return out


def episodes_from_arrays(
    arrays: Mapping[str, object],
    *,
    source: str = "arrays",
    observation_dim: int | None = None,
    action_dim: int | None = None,
    constraints: Sequence[str] | None = None,
) -> TensorDict:
    """Build the TED-layout transition TensorDict from DSRL-layout arrays (see module docstring).

    Per-constraint costs (``cost_<name>`` arrays, or ``costs`` of shape ``[N, K]`` whose columns ``constraints``
    names) go to ``("next", "constraint_costs", <name>)`` (:mod:`spoil_torchrl.data.constraint_costs`).

    Episodes end where ``terminals`` or ``timeouts`` is set. Rows after the last end flag form a final episode
    cut short: it is kept, marked truncated at its last row, and a warning says so. Floating-point arrays that
    are already float32 are not copied.

    Examples:
        >>> n = 5
        >>> arrays = {"observations": np.arange(n, dtype=np.float32)[:, None],
        ...           "next_observations": np.arange(1, n + 1, dtype=np.float32)[:, None],
        ...           "actions": np.zeros((n, 1), np.float32), "rewards": np.ones(n, np.float32),
        ...           "costs": np.zeros(n, np.float32),
        ...           "terminals": np.array([0, 1, 0, 0, 0], np.float32),
        ...           "timeouts": np.array([0, 0, 0, 0, 1], np.float32)}
        >>> td = episodes_from_arrays(arrays)
        >>> td["episode"].tolist(), td["is_init"].squeeze(-1).tolist()
        ([0, 0, 1, 1, 1], [True, False, True, False, False])
        >>> td["next", "terminated"].squeeze(-1).tolist(), td["next", "truncated"].squeeze(-1).tolist()
        ([False, True, False, False, False], [False, False, False, False, True])
    """
    arrays, components = split_cost_components(arrays, source=source, names=constraints)
    t = validate_arrays(arrays, source=source, observation_dim=observation_dim, action_dim=action_dim)
    n = t["observations"].shape[0]
    terminated = t["terminals"]
    truncated = t["timeouts"] & ~terminated
    ends = terminated | truncated
    if not bool(ends[-1]):
        last_end = int(ends.nonzero()[-1, 0]) if bool(ends.any()) else -1
        warnings.warn(
            f"{source}: the last {n - 1 - last_end} rows follow the last terminal/timeout flag; they are kept as "
            "a final episode marked truncated at its last row",
            stacklevel=2,
        )
        truncated = truncated.clone()
        truncated[-1] = True
        ends = terminated | truncated
    episode = torch.zeros(n, dtype=torch.int64)
    episode[1:] = torch.cumsum(ends[:-1].to(torch.int64), 0)
    is_init = torch.ones(n, dtype=torch.bool)
    is_init[1:] = ends[:-1]
    out = TensorDict(
        {
            "observation": t["observations"].to(torch.float32),
            "action": t["actions"].to(torch.float32),
            "episode": episode,
            "is_init": is_init.unsqueeze(-1),
            "next": {
                "observation": t["next_observations"].to(torch.float32),
                "reward": t["rewards"].to(torch.float32).unsqueeze(-1),
                "cost": t["costs"].to(torch.float32).unsqueeze(-1),
                "terminated": terminated.unsqueeze(-1),
                "truncated": truncated.unsqueeze(-1),
                "done": ends.unsqueeze(-1),
            },
        },
        batch_size=[n],
    )
    if components:
        parts = {name: value.to(torch.float32).unsqueeze(-1) for name, value in components.items()}
        out["next", CONSTRAINTS_KEY] = TensorDict(parts, batch_size=[n])
    return out


def select_episodes(episodes: TensorDict, ids) -> TensorDict:
    """The transitions of the episodes ``ids`` (a copy, in dataset order).

    Examples:
        >>> td = TensorDict({"episode": torch.tensor([0, 0, 1, 2, 2])}, [5])
        >>> select_episodes(td, [2, 0])["episode"].tolist()
        [0, 0, 2, 2]
    """
    ids = torch.as_tensor(ids, dtype=torch.int64)
    n_episodes = int(episodes["episode"].max()) + 1
    if ids.numel() and (ids.min() < 0 or ids.max() >= n_episodes):
        raise ValueError(f"episode ids must lie in [0, {n_episodes}), got {ids.tolist()[:10]}")
    return episodes[torch.isin(episodes["episode"], ids)]


def fit_observation_normalizer(episodes: TensorDict, ids=None) -> ObservationNormalizer:
    """Standardisation statistics (mean, std + 1e-3) of the observations of the episodes ``ids`` (all when
    ``None``). The recipe fits them on D_U, the union data, as the DICE reference codes do.

    Examples:
        >>> td = TensorDict({"episode": torch.tensor([0, 0, 1]), "observation": torch.tensor([[0.0], [2.0], [9.0]])}, [3])
        >>> fit_observation_normalizer(td, [0]).loc.tolist()
        [1.0]
    """
    observations = episodes["observation"] if ids is None else select_episodes(episodes, ids)["observation"]
    warn_erased_features(observations)
    return ObservationNormalizer.from_observations(observations)


#: A column whose standard deviation exceeds this many robust spreads (median absolute deviation) is dominated
#: by a few extreme values: standardising by it squeezes every other row of that feature to about 0.
ERASE_RATIO = 1e3


def warn_erased_features(observations: torch.Tensor) -> list[int]:
    """Warn, naming each column, where a few extreme values dominate the standard deviation the standardiser
    would divide by (std > :data:`ERASE_RATIO` x the median absolute deviation), so that the feature is erased
    for every other row; returns those columns.

    Examples:
        >>> import warnings
        >>> x = torch.randn(1000, 2); x[3, 1] = 1e30
        >>> with warnings.catch_warnings(record=True) as caught:
        ...     warnings.simplefilter("always")
        ...     warn_erased_features(x)
        [1]
        >>> "observation column 1" in str(caught[0].message)
        True
    """
    x = observations.double()
    median = x.median(0).values
    mad = (x - median).abs().median(0).values
    std = x.std(0) if x.shape[0] > 1 else torch.zeros_like(median)
    erased = ((mad > 0) & (std > ERASE_RATIO * mad)).nonzero().reshape(-1).tolist()
    for column in erased:
        row = int((x[:, column] - median[column]).abs().argmax())
        warnings.warn(
            f"observation column {column}: its standard deviation {float(std[column]):.3g} is "
            f"{float(std[column] / mad[column]):.3g}x its typical spread (median absolute deviation "
            f"{float(mad[column]):.3g}), driven by extreme values such as {float(x[row, column]):.3g} at row {row}; "
            "standardising by it erases this feature for the other rows (check the data, or set "
            "normalize_observations=false)",
            stacklevel=2,
        )
    return erased


def standardize_observations(episodes: TensorDict, normalizer: ObservationNormalizer) -> TensorDict:
    """A copy of ``episodes`` whose ``observation`` and ``("next", "observation")`` are standardised by
    ``normalizer`` (everything else shared, not copied); initial states come from ``observation``, so they are
    standardised too.

    Examples:
        >>> td = TensorDict({"observation": torch.tensor([[3.0]]), "next": {"observation": torch.tensor([[5.0]])}}, [1])
        >>> out = standardize_observations(td, ObservationNormalizer(torch.tensor([1.0]), torch.tensor([2.0])))
        >>> out["observation"].item(), out["next", "observation"].item(), td["observation"].item()
        (1.0, 2.0, 3.0)
    """
    out = episodes.copy()
    with torch.no_grad():
        for key in ("observation", ("next", "observation")):
            out.set(key, normalizer(episodes.get(key).float()))
    return out
