"""Per-constraint costs: a dataset whose cost has several named components, one per safety constraint
(``docs/several_constraints.md``).

A DSRL-layout file stores one ``costs`` array, the task's cost. Two forms add the constraints' own costs:

* K named arrays ``cost_<name>`` of shape ``[N]`` beside ``costs`` (what this project's collection writes, and
  what Safety-Gymnasium's ``cost_<name>`` info entries give): ``costs`` stays the task's cost as stored;
* ``costs`` itself of shape ``[N, K]``: the components, named by the metadata's ``constraints`` list (else
  ``c0``, ``c1``, ...), and the task's cost is their sum (Safety-Gymnasium's ``cost_sum``).

Loaded, the components are ``("next", "constraint_costs", <name>)`` (float32, trailing dim 1) beside the
scalar ``("next", "cost")``, so their names travel with the transitions. A dataset without components loads as
before: nothing of this module is in its transitions.

The arrays are read into transitions by :func:`~spoil_torchrl.data.episodes.episodes_from_arrays`
(:func:`~spoil_torchrl.data.episodes.split_cost_components`). An episode is safe on constraint k when its cost
on k is within k's threshold; the safe set D_S^k of a constraint is drawn from those episodes
(:func:`constraint_safe_ids`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
from tensordict import TensorDict

from spoil_torchrl.data.episodes import CONSTRAINTS_KEY, DatasetError
from spoil_torchrl.data.labeling import draw, episode_total

#: The role of constraint ``<name>``'s safe set D_S^k is ``safe_<name>``.
CONSTRAINT_ROLE_PREFIX = "safe_"


def constraint_names(episodes: TensorDict) -> list[str]:
    """The names of the constraints whose costs the transitions carry (``[]``: the task's cost only).

    Examples:
        >>> constraint_names(TensorDict({"next": {"cost": torch.zeros(2, 1)}}, [2]))
        []
    """
    parts = episodes.get(("next", CONSTRAINTS_KEY), None)
    return [] if parts is None else list(parts.keys())


def episode_constraint_costs(episodes: TensorDict) -> TensorDict:
    """Per-episode cost of each constraint (float64, batch size ``[n_episodes]``, one entry per name).

    Examples:
        >>> td = TensorDict({"episode": torch.tensor([0, 0, 1]), "next": {CONSTRAINTS_KEY: {
        ...     "x_wall": torch.tensor([[1.0], [1.0], [0.0]]), "y_wall": torch.tensor([[0.0], [0.0], [3.0]])}}}, [3])
        >>> out = episode_constraint_costs(td)
        >>> out["x_wall"].tolist(), out["y_wall"].tolist()
        ([2.0, 0.0], [0.0, 3.0])
    """
    episode = episodes["episode"]
    n = int(episode.max()) + 1
    parts = episodes.get(("next", CONSTRAINTS_KEY), None)
    out = TensorDict({}, batch_size=[n])
    for name in [] if parts is None else parts.keys():
        out[name] = episode_total(episode, parts[name])
    return out


def constraint_safe_ids(
    episodes: TensorDict,
    constraints: Sequence[str],
    thresholds: Mapping[str, float],
    *,
    source: str = "dataset",
) -> dict[str, torch.Tensor]:
    """For each constraint of ``constraints``, the ids of the episodes whose cost on it is within its threshold
    (``thresholds[name]``): the pool its safe set D_S^k is drawn from.

    Raises :class:`~spoil_torchrl.data.DatasetError` for a constraint the data do not have (naming those they
    have) and for one that no episode respects.

    Examples:
        >>> td = TensorDict({"episode": torch.tensor([0, 1, 2]), "next": {CONSTRAINTS_KEY: {
        ...     "x_wall": torch.tensor([[0.0], [9.0], [0.0]]), "y_wall": torch.tensor([[9.0], [0.0], [0.0]])}}}, [3])
        >>> {k: v.tolist() for k, v in constraint_safe_ids(td, ["x_wall", "y_wall"], {"x_wall": 1.0, "y_wall": 1.0}).items()}
        {'x_wall': [0, 2], 'y_wall': [1, 2]}
    """
    have = constraint_names(episodes)
    unknown = [name for name in constraints if name not in have]
    if unknown:
        raise DatasetError(
            f"{source}: dataset.constraints names {unknown}, but the data carry the costs of "
            f"{have or 'no constraint'} (cost_<name> arrays, or a [N, K] costs array with named columns)"
        )
    costs = episode_constraint_costs(episodes)
    out = {}
    for name in constraints:
        safe = (costs[name] <= float(thresholds[name])).nonzero().reshape(-1)
        if safe.numel() == 0:
            raise DatasetError(
                f"{source}: no episode is within constraint {name!r}'s threshold {thresholds[name]} (lowest episode "
                f"cost {float(costs[name].min()):.4g}): its safe set would be empty"
            )
        out[name] = safe
    return out


def constraint_roles(
    episodes: TensorDict,
    cfg: Mapping,
    *,
    cost_threshold: float,
    seed: int,
    safe: torch.Tensor | None = None,
    pools: Mapping[str, torch.Tensor] | None = None,
) -> dict[str, torch.Tensor]:
    """One safe set per constraint of ``cfg["constraints"]`` (``docs/several_constraints.md``): the role
    ``safe_<name>`` holds ``cfg["n_safe_per_constraint"]`` (default ``n_safe``) episodes drawn (seeded) from those
    within that constraint's threshold (``cfg["constraint_thresholds"][name]``, default the cost threshold).
    ``{}`` when ``cfg`` names no constraint. D_S stays the scheme's: the demonstrations safe on the task's cost,
    the merged label.

    ``cfg["constraint_pools"]`` (``{name: pool}``, with a collected file's typed ``pools``) models annotators who
    each certify one constraint: D_S^k is then D_S (``safe``, the demonstrations certified on every constraint,
    which must be within every threshold) together with ``n_safe_per_constraint`` other episodes of the typed
    pool ``pool`` within k's threshold.

    Examples:
        >>> td = TensorDict({"episode": torch.arange(4), "next": {CONSTRAINTS_KEY: {
        ...     "x_wall": torch.tensor([[0.0], [9.0], [0.0], [0.0]]),
        ...     "y_wall": torch.tensor([[9.0], [0.0], [0.0], [9.0]])}}}, [4])
        >>> cfg = {"constraints": ["x_wall", "y_wall"], "n_safe": 2}
        >>> roles = constraint_roles(td, cfg, cost_threshold=1.0, seed=0)
        >>> sorted(roles), sorted(roles["safe_y_wall"].tolist())
        (['safe_x_wall', 'safe_y_wall'], [1, 2])
        >>> cfg |= {"n_safe_per_constraint": 1, "constraint_pools": {"x_wall": "x", "y_wall": "y"}}
        >>> pools = {"x": torch.tensor([3]), "y": torch.tensor([1])}
        >>> roles = constraint_roles(td, cfg, cost_threshold=1.0, seed=0, safe=torch.tensor([2]), pools=pools)
        >>> roles["safe_x_wall"].tolist(), roles["safe_y_wall"].tolist()
        ([2, 3], [1, 2])
    """
    names = list(cfg.get("constraints") or [])
    if not names:
        return {}
    source = str(cfg.get("source", "dataset"))
    given = dict(cfg.get("constraint_thresholds") or {})
    unknown = sorted(set(given) - set(names))
    if unknown:
        raise DatasetError(
            f"dataset.constraint_thresholds names {unknown}, which dataset.constraints ({names}) does not have"
        )
    thresholds = {name: float(given.get(name, cost_threshold)) for name in names}
    eligible = constraint_safe_ids(episodes, names, thresholds, source=source)
    typed = dict(cfg.get("constraint_pools") or {})
    if typed:
        eligible = _typed_constraint_pools(episodes, names, typed, eligible, thresholds, safe, pools, source)
    k = int(cfg.get("n_safe_per_constraint") or cfg["n_safe"])
    roles = {}
    for i, name in enumerate(names):
        if eligible[name].numel() < k:
            where = f"of pool {typed[name]!r} " if typed else ""
            raise DatasetError(
                f"{source}: {eligible[name].numel()} episodes {where}are within constraint {name!r}'s threshold "
                f"{thresholds[name]}, fewer than n_safe_per_constraint={k}; lower it"
            )
        drawn = draw(eligible[name], k, seed=seed + 10 + i)
        roles[f"{CONSTRAINT_ROLE_PREFIX}{name}"] = (
            drawn if not typed else torch.sort(torch.cat([safe, drawn])).values
        )
    return roles


def _typed_constraint_pools(episodes, names, typed, eligible, thresholds, safe, pools, source):
    """Each constraint's eligible episodes restricted to its typed pool (``cfg["constraint_pools"]``), after
    checking the mapping, the pools and that the merged D_S ``safe`` is within every threshold."""
    if sorted(typed) != sorted(names):
        raise DatasetError(
            f"dataset.constraint_pools names {sorted(typed)}; it needs one typed pool for each of dataset.constraints "
            f"{names}"
        )
    if pools is None or safe is None:
        raise DatasetError(
            f"{source}: dataset.constraint_pools needs a collected file's typed pools (scheme=controlled)"
        )
    missing = sorted({p for p in typed.values() if p not in pools})
    if missing:
        raise DatasetError(
            f"{source}: dataset.constraint_pools names the pools {missing}; the file has {sorted(pools)}"
        )
    costs = episode_constraint_costs(episodes)
    for name in names:
        over = safe[costs[name][safe] > thresholds[name]]
        if over.numel():
            raise DatasetError(
                f"{source}: D_S's episodes {over.tolist()} exceed constraint {name!r}'s threshold "
                f"{thresholds[name]}, so they cannot join its safe set"
            )
    inside = {name: torch.isin(eligible[name], pools[typed[name]]) for name in names}
    return {name: eligible[name][inside[name] & ~torch.isin(eligible[name], safe)] for name in names}
