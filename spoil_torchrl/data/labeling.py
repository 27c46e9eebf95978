"""IL-SP labelling of episodes (paper appendix F.1), controlled mixes and replay subsets (F.2), corruption (G.6).

Every function works on episode ids (int64 tensors) and per-episode statistics, never on copies of the data;
:func:`~spoil_torchrl.data.select_episodes` turns ids into transitions. All random draws take a seed.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from tensordict import TensorDict

from spoil_torchrl.data.episodes import DatasetError

ROLES = ("safe", "performant", "nonpreferred", "unlabeled")
POOLS = ("safe-high", "safe-medium", "unsafe-high", "unsafe-medium")


def episode_total(episode: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """The sum of per-transition ``values`` over each episode (float64, one entry per episode id of ``episode``).

    Examples:
        >>> episode_total(torch.tensor([0, 0, 1]), torch.tensor([[1.0], [2.0], [5.0]])).tolist()
        [3.0, 5.0]
    """
    n = int(episode.max()) + 1
    return torch.zeros(n, dtype=torch.float64).index_add_(0, episode, values.reshape(-1).to(torch.float64))


def episode_stats(episodes: TensorDict) -> TensorDict:
    """Per-episode undiscounted ``return``, ``cost`` (float64) and ``length`` (int64), batch size [n_episodes].

    Examples:
        >>> td = TensorDict({"episode": torch.tensor([0, 0, 1]),
        ...                  "next": {"reward": torch.tensor([[1.0], [2.0], [5.0]]),
        ...                           "cost": torch.tensor([[0.0], [1.0], [0.0]])}}, [3])
        >>> stats = episode_stats(td)
        >>> stats["return"].tolist(), stats["cost"].tolist(), stats["length"].tolist()
        ([3.0, 5.0], [1.0, 0.0], [2, 1])
    """
    episode = episodes["episode"]
    n = int(episode.max()) + 1
    return TensorDict(
        {
            "return": episode_total(episode, episodes["next", "reward"]),
            "cost": episode_total(episode, episodes["next", "cost"]),
            "length": torch.bincount(episode, minlength=n),
        },
        batch_size=[n],
    )


def _as_stats(data: TensorDict) -> TensorDict:
    return episode_stats(data) if "episode" in data.keys() else data


def ilsp_return_threshold(stats: TensorDict, cost_threshold: float, return_quantile: float = 0.9) -> float:
    """The ``return_quantile`` quantile (linear interpolation) of the safe episodes' returns (F.1).

    Examples:
        >>> stats = TensorDict({"return": torch.tensor([1.0, 2.0, 3.0, 10.0]),
        ...                     "cost": torch.tensor([0.0, 5.0, 0.0, 50.0])}, [4])
        >>> ilsp_return_threshold(stats, cost_threshold=10, return_quantile=0.5)  # median of 1, 2, 3
        2.0
        >>> round(ilsp_return_threshold(stats, cost_threshold=10), 4)  # the default 0.9 quantile
        2.8
    """
    if not 0.0 <= return_quantile <= 1.0:
        raise ValueError(f"return_quantile must lie in [0, 1], got {return_quantile}")
    safe_returns = stats["return"][stats["cost"] <= cost_threshold]
    if safe_returns.numel() == 0:
        raise DatasetError(
            f"no episode has cost <= {cost_threshold} (lowest episode cost: {stats['cost'].min().item():.4g}); "
            "the IL-SP return threshold is defined from safe episodes"
        )
    return float(torch.quantile(safe_returns, return_quantile))


def label_ilsp(
    data: TensorDict, cost_threshold: float, return_quantile: float = 0.9
) -> dict[str, torch.Tensor]:
    """IL-SP roles of appendix F.1 as episode ids.

    safe iff episode cost <= ``cost_threshold``; the return threshold is the ``return_quantile`` quantile of the
    safe episodes' returns; performant iff return >= it; non-preferred = unsafe; unlabeled = all episodes.

    Args:
        data: transitions (with ``episode``) or the output of :func:`episode_stats`.

    Examples:
        >>> stats = TensorDict({"return": torch.tensor([1.0, 2.0, 3.0, 10.0]),
        ...                     "cost": torch.tensor([0.0, 5.0, 0.0, 50.0])}, [4])
        >>> {k: v.tolist() for k, v in label_ilsp(stats, cost_threshold=10, return_quantile=0.5).items()}
        {'safe': [0, 1, 2], 'performant': [1, 2, 3], 'nonpreferred': [3], 'unlabeled': [0, 1, 2, 3]}
    """
    stats = _as_stats(data)
    threshold = ilsp_return_threshold(stats, cost_threshold, return_quantile)
    safe = stats["cost"] <= cost_threshold
    performant = stats["return"] >= threshold
    return {
        "safe": safe.nonzero().squeeze(-1),
        "performant": performant.nonzero().squeeze(-1),
        "nonpreferred": (~safe).nonzero().squeeze(-1),
        "unlabeled": torch.arange(stats.shape[0]),
    }


def draw(ids, k: int, seed: int) -> torch.Tensor:
    """``k`` distinct ids drawn uniformly from ``ids`` with a seeded generator (e.g. the 10 trajectories of D_S).

    Examples:
        >>> draw(torch.arange(100), 3, seed=0).tolist() == draw(torch.arange(100), 3, seed=0).tolist()
        True
    """
    ids = torch.as_tensor(ids, dtype=torch.int64)
    if k < 0 or k > ids.numel():
        raise ValueError(f"cannot draw {k} trajectories from {ids.numel()}")
    generator = torch.Generator().manual_seed(seed)
    return ids[torch.randperm(ids.numel(), generator=generator)[:k]]


def stats_table(
    data: TensorDict, roles: Mapping[str, torch.Tensor], cost_threshold: float, return_threshold: float
) -> str:
    """A markdown table in the shape of the paper's Tables D-F: per role, the share of safe, performant and
    safe-and-performant trajectories, and the number of trajectories.

    Examples:
        >>> stats = TensorDict({"return": torch.tensor([1.0, 3.0]), "cost": torch.tensor([0.0, 9.0])}, [2])
        >>> print(stats_table(stats, {"unlabeled": torch.tensor([0, 1])}, 5.0, 2.0))
        | dataset | safe ratio | performant ratio | safe-performant ratio | # traj. |
        |---|---|---|---|---|
        | unlabeled | 0.50 | 0.50 | 0.00 | 2 |
    """
    stats = _as_stats(data)
    safe = stats["cost"] <= cost_threshold
    performant = stats["return"] >= return_threshold
    lines = [
        "| dataset | safe ratio | performant ratio | safe-performant ratio | # traj. |",
        "|---|---|---|---|---|",
    ]
    for role, ids in roles.items():
        ids = torch.as_tensor(ids, dtype=torch.int64)
        if ids.numel() == 0:
            lines.append(f"| {role} | - | - | - | 0 |")
            continue
        s, p = safe[ids].double(), performant[ids].double()
        lines.append(f"| {role} | {s.mean():.2f} | {p.mean():.2f} | {(s * p).mean():.2f} | {ids.numel()} |")
    return "\n".join(lines)


def _split(n: int, share: float, name: str) -> tuple[int, int]:
    if not 0.0 <= share <= 1.0:
        raise ValueError(f"{name} must lie in [0, 1], got {share}")
    high = round(share * n)
    return high, n - high


def controlled_mix(
    pools: Mapping[str, torch.Tensor],
    *,
    n_safe: int,
    performance: float,
    n_performant: int,
    safeness: float,
    n_unlabeled: int | None = None,
    seed: int = 0,
    episode_cost: torch.Tensor | None = None,
    cost_limit: float | None = None,
) -> dict[str, torch.Tensor]:
    """Controlled datasets of appendix F.2 from four typed pools of episode ids.

    ``pools`` maps ``"safe-high"``, ``"safe-medium"``, ``"unsafe-high"``, ``"unsafe-medium"`` to episode ids.
    D_S has ``n_safe`` trajectories, a share ``performance`` of them safe-high and the rest safe-medium; D_P has
    ``n_performant``, a share ``safeness`` safe-high and the rest unsafe-high (shares are rounded to whole
    trajectories). D_S and D_P never share a trajectory. D_U holds ``n_unlabeled`` trajectories drawn equally
    from the pools (the remainder from the first ones), or every pooled trajectory when ``None``. Pools beyond
    the four (e.g. demonstrators safe on one of several constraints, ``docs/several_constraints.md``) join D_U
    only, after the four, in the order given.

    With ``episode_cost`` (indexed by episode id) and ``cost_limit``, D_S and D_P take a safe type's
    trajectories only among its episodes within the limit and an unsafe type's only among those over it, so
    that D_S holds safe demonstrations (F.2: ``safe-high`` and ``safe-medium`` are the policies that satisfy
    the constraint, but a policy that does on average still has episodes over the limit) and ``safeness`` is
    the share of D_P that is safe. The pools are shuffled as without costs and the ineligible episodes
    skipped, so a seed whose draw held none selects exactly the same trajectories. D_U still draws from whole
    pools: it is the unlabeled mix of all four behaviours.

    Examples:
        >>> pools = {name: torch.arange(10) + 10 * i for i, name in enumerate(POOLS)}
        >>> mix = controlled_mix(pools, n_safe=4, performance=0.25, n_performant=4, safeness=0.5, seed=0)
        >>> [int((mix["safe"] < 10).sum()), int((mix["performant"] < 10).sum()), len(mix["unlabeled"])]
        [1, 2, 40]
        >>> cost = torch.zeros(40); cost[[0, 1]] = 99.0  # two safe-high episodes over the limit
        >>> mix = controlled_mix(pools, n_safe=8, performance=1.0, n_performant=0, safeness=0.0,
        ...                      episode_cost=cost, cost_limit=25.0)
        >>> sorted(mix["safe"].tolist())
        [2, 3, 4, 5, 6, 7, 8, 9]
    """
    missing = [p for p in POOLS if p not in pools]
    if missing:
        raise ValueError(f"controlled_mix needs the pools {POOLS}; missing {missing}")
    pools = {k: torch.as_tensor(v, dtype=torch.int64) for k, v in pools.items()}
    s_high, s_medium = _split(n_safe, performance, "performance")
    p_high, p_unsafe = _split(n_performant, safeness, "safeness")
    generator = torch.Generator().manual_seed(seed)

    if (episode_cost is None) != (cost_limit is None):
        raise ValueError("controlled_mix takes episode_cost and cost_limit together")

    def take(pool: str, k: int, offset: int = 0) -> torch.Tensor:
        ids = order[pool]
        if offset + k > ids.numel():
            within = "" if episode_cost is None else (" over" if pool.startswith("unsafe") else " within")
            limit = "" if episode_cost is None else f"{within} the cost limit {cost_limit}"
            raise ValueError(f"pool {pool!r} has {ids.numel()} trajectories{limit}, {offset + k} are needed")
        return ids[offset : offset + k]

    order = {name: ids[torch.randperm(ids.numel(), generator=generator)] for name, ids in pools.items()}
    if episode_cost is not None:
        cost = torch.as_tensor(episode_cost)
        for name in POOLS:
            over = cost[order[name]] > cost_limit
            order[name] = order[name][over if name.startswith("unsafe") else ~over]
    safe = torch.cat([take("safe-high", s_high), take("safe-medium", s_medium)])
    performant = torch.cat([take("safe-high", p_high, offset=s_high), take("unsafe-high", p_unsafe)])
    names = [*POOLS, *(p for p in pools if p not in POOLS)]
    if n_unlabeled is None:
        unlabeled = torch.cat([pools[p] for p in names])
    else:
        n = len(names)
        per_pool = [n_unlabeled // n + (i < n_unlabeled % n) for i in range(n)]
        unlabeled = torch.cat(
            [
                pools[p][torch.randperm(pools[p].numel(), generator=generator)[:k]]
                for p, k in zip(names, per_pool, strict=True)
            ]
        )
        if unlabeled.numel() != n_unlabeled:
            raise ValueError(f"the pools hold too few trajectories for n_unlabeled={n_unlabeled}")
    return {"safe": safe, "performant": performant, "unlabeled": torch.sort(unlabeled).values}


def corrupt(safe_ids, unsafe_ids, rate: float, seed: int = 0) -> torch.Tensor:
    """Noisy safe demonstrations (G.6): replace a share ``rate`` of ``safe_ids`` by ids drawn from ``unsafe_ids``.

    Examples:
        >>> noisy = corrupt(torch.arange(10), torch.arange(100, 110), rate=0.3, seed=0)
        >>> len(noisy), int((noisy >= 100).sum())
        (10, 3)
    """
    safe_ids = torch.as_tensor(safe_ids, dtype=torch.int64)
    n_bad, _ = _split(safe_ids.numel(), rate, "rate")
    generator = torch.Generator().manual_seed(seed)
    keep = safe_ids[torch.randperm(safe_ids.numel(), generator=generator)[: safe_ids.numel() - n_bad]]
    return torch.cat([keep, draw(unsafe_ids, n_bad, seed + 1)])


def replay_subsets(
    data: TensorDict, cost_threshold: float, safe_optimal_return: float, return_fraction: float = 0.9
) -> dict[str, torch.Tensor]:
    """Replay datasets of appendix G.2: D_P = trajectories with return above ``return_fraction`` of the
    safe-optimal return, D_S = trajectories within the cost bound, D_U = all.

    Examples:
        >>> stats = TensorDict({"return": torch.tensor([1.0, 9.5, 10.0]), "cost": torch.tensor([0.0, 50, 1])}, [3])
        >>> {k: v.tolist() for k, v in replay_subsets(stats, 5.0, safe_optimal_return=10.0).items()}
        {'safe': [0, 2], 'performant': [1, 2], 'unlabeled': [0, 1, 2]}
    """
    stats = _as_stats(data)
    return {
        "safe": (stats["cost"] <= cost_threshold).nonzero().squeeze(-1),
        "performant": (stats["return"] >= return_fraction * safe_optimal_return).nonzero().squeeze(-1),
        "unlabeled": torch.arange(stats.shape[0]),
    }


def replay_statistics(
    data: TensorDict, cost_threshold: float, safe_optimal_return: float, return_fraction: float = 0.9
) -> dict[str, float]:
    """The paper's Table H for a replay buffer: the shares of its trajectories that are safe (cost within the
    bound), performant (return above ``return_fraction`` of the safe-optimal return) and both, and their
    number (the subsets of :func:`replay_subsets`).

    Examples:
        >>> stats = TensorDict({"return": torch.tensor([1.0, 9.5, 10.0, 2.0]), "cost": torch.tensor([0.0, 50, 1, 0])}, [4])
        >>> replay_statistics(stats, 5.0, safe_optimal_return=10.0)
        {'safe_ratio': 0.75, 'performant_ratio': 0.5, 'safe_performant_ratio': 0.25, 'trajectories': 4}
    """
    subsets = replay_subsets(data, cost_threshold, safe_optimal_return, return_fraction)
    n = int(subsets["unlabeled"].numel())
    if n == 0:
        raise ValueError("the replay buffer holds no trajectory")
    both = int(torch.isin(subsets["safe"], subsets["performant"]).sum())
    return {
        "safe_ratio": subsets["safe"].numel() / n,
        "performant_ratio": subsets["performant"].numel() / n,
        "safe_performant_ratio": both / n,
        "trajectories": n,
    }
