"""Evaluation metrics of the paper's section 5.2 (as OSRL / DSRL compute them), one function per number.

Per episode (1-D reward and cost tensors of one episode, ``[T]`` or TED-style ``[T, 1]``):

* :func:`episode_return` -- undiscounted return R = sum_t r_t;
* :func:`episode_cost` -- undiscounted episode cost C = sum_t c_t;
* :func:`feasible_return` -- the reward collected before the cumulative cost first exceeds the threshold;
* :func:`strict_feasible_return` -- the reward collected before the first step with a positive cost;
* :func:`normalized_return` -- (R - R_min) / (R_max - R_min) (DSRL's per-task constants);
* :func:`normalized_cost` -- C / threshold, DSRL's (C + 1) / (0 + 1) when the threshold is 0.

Over a padded batch of episodes: :func:`episode_metrics`. Over evaluations and seeds, the paper's aggregate
("averaged over the last 10 evaluations across multiple random seeds"): :func:`mean_of_last` per seed, then
:func:`aggregate_over_seeds` (mean and standard error over seeds).

All sums are taken in float64; a cumulative cost counts as exceeding a threshold only beyond a relative
round-off slack of 1e-9 (so 0.1 + 0.1 + 0.1 does not exceed 0.3).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple, TypeVar

import torch
from tensordict import TensorDict, TensorDictBase

Number = TypeVar("Number", float, torch.Tensor)


def _steps(values, name: str) -> torch.Tensor:
    """One episode's per-step values as a float64 ``[T]`` tensor (a trailing dim of 1 is dropped)."""
    values = torch.as_tensor(values, dtype=torch.float64)
    if values.ndim == 2 and values.shape[-1] == 1:
        values = values.squeeze(-1)
    if values.ndim != 1:
        raise ValueError(
            f"{name} must be one episode's per-step values, shape [T] or [T, 1]; got {list(values.shape)}"
        )
    return values


def _pair(reward, cost) -> tuple[torch.Tensor, torch.Tensor]:
    reward, cost = _steps(reward, "reward"), _steps(cost, "cost")
    if reward.shape != cost.shape:
        raise ValueError(
            f"reward and cost must have one value per step; got {reward.numel()} and {cost.numel()}"
        )
    if torch.isnan(cost).any():
        raise ValueError("cost contains NaN: the first violation is undefined")
    return reward, cost


#: Relative slack of threshold comparisons, against float round-off in cumulative sums.
ROUND_OFF = 1e-9


def _check_threshold(threshold: float) -> float:
    threshold = float(threshold)
    if not math.isfinite(threshold) or threshold < 0:
        raise ValueError(f"the cost threshold must be a finite number >= 0, got {threshold}")
    return threshold


def episode_return(reward) -> float:
    """Undiscounted episode return R = sum_t r_t.

    Examples:
        >>> episode_return(torch.tensor([1.0, 2.0, 3.0]))
        6.0
    """
    return float(_steps(reward, "reward").sum())


def episode_cost(cost) -> float:
    """Undiscounted episode cost C = sum_t c_t (the paper's "episode cost").

    Examples:
        >>> episode_cost(torch.tensor([[0.0], [1.0], [1.0]]))  # TED layout [T, 1] works too
        2.0
    """
    return float(_steps(cost, "cost").sum())


def feasible_return(reward, cost, threshold: float) -> float:
    """Feasible return: the reward collected before the episode's cumulative cost first exceeds ``threshold``.

    The paper (5.2, following Liu et al. 2023) defines it as "the cumulative reward up to the first cost
    violation in an episode"; a violation is read here as the cumulative cost first *exceeding* the threshold
    (``sum_{k<=t} c_k > threshold``; reaching it exactly is not a violation, as "safe iff normalised cost <= 1").
    Let t* be the first such step: the result is ``sum_{t < t*} r_t``, so **the violating step's own reward
    does not count**. Without a violation it is the episode return.

    Args:
        reward, cost: one episode's per-step values, ``[T]`` or ``[T, 1]``.
        threshold: the task's cost threshold (>= 0).

    Examples:
        >>> reward = torch.tensor([1.0, 2.0, 4.0, 8.0])
        >>> cost = torch.tensor([0.0, 1.0, 1.0, 0.0])      # cumulative cost 0, 1, 2, 2
        >>> feasible_return(reward, cost, threshold=1.0)   # exceeded at t=2: rewards of t=0, 1
        3.0
        >>> feasible_return(reward, cost, threshold=2.0)   # never exceeded: the whole return
        15.0
    """
    reward, cost = _pair(reward, cost)
    threshold = _check_threshold(threshold)
    violated = torch.cumsum(cost, 0) > threshold + ROUND_OFF * max(1.0, threshold)
    first = int(violated.to(torch.int8).argmax()) if bool(violated.any()) else reward.numel()
    return float(reward[:first].sum())


def strict_feasible_return(reward, cost) -> float:
    """Strict feasible return: the reward collected before the first step with a positive cost.

    The strict reading of "up to the first cost violation" (any cost is a violation). Let t* be the first step
    with ``c_t > 0``: the result is ``sum_{t < t*} r_t`` (the violating step's reward does not count, as in
    :func:`feasible_return`); without a positive cost it is the episode return.

    Examples:
        >>> strict_feasible_return(torch.tensor([1.0, 2.0, 4.0, 8.0]), torch.tensor([0.0, 1.0, 1.0, 0.0]))
        1.0
    """
    reward, cost = _pair(reward, cost)
    positive = cost > 0
    first = int(positive.to(torch.int8).argmax()) if bool(positive.any()) else reward.numel()
    return float(reward[:first].sum())


def normalized_return(value: Number, min_return: float, max_return: float) -> Number:
    """Normalised return (R - R_min) / (R_max - R_min); 0 is R_min, 1 is R_max.

    Takes a float or a tensor (element-wise) and returns the same kind. DSRL's constants are
    ``DSRLDataset.min_return`` / ``max_return`` in :mod:`spoil_torchrl.tasks`. Applied to a feasible return it
    gives the paper's normalised feasible return.

    Raises:
        ValueError: if ``max_return <= min_return`` (or either is not finite).

    Examples:
        >>> normalized_return(30.0, min_return=10.0, max_return=50.0)
        0.5
    """
    lo, hi = float(min_return), float(max_return)
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        raise ValueError(f"normalized_return needs finite R_max > R_min; got R_min={lo}, R_max={hi}")
    return (value - lo) / (hi - lo)


def normalized_cost(value: Number, threshold: float) -> Number:
    """Normalised cost C / threshold; an episode is safe iff it is <= 1.

    For ``threshold == 0`` the ratio is undefined; this follows DSRL's convention
    ``(C + eps) / (threshold + eps)`` with ``eps = 1`` only when the threshold is 0, i.e. ``C + 1``: an episode
    without cost then scores exactly 1 (safe) and any positive cost scores above 1 (unsafe).

    Raises:
        ValueError: for a negative or non-finite threshold.

    Examples:
        >>> normalized_cost(15.0, threshold=10.0)
        1.5
        >>> normalized_cost(0.0, threshold=0.0), normalized_cost(2.0, threshold=0.0)  # DSRL: (C + 1) / 1
        (1.0, 3.0)
    """
    threshold = _check_threshold(threshold)
    if threshold == 0:
        return (value + 1.0) / 1.0
    return value / threshold


def _mask_lengths(mask: torch.Tensor) -> torch.Tensor:
    """Episode lengths from a ``[E, T]`` validity mask whose valid steps form a prefix of each row."""
    mask = torch.as_tensor(mask, dtype=torch.bool)
    if mask.ndim == 3 and mask.shape[-1] == 1:
        mask = mask.squeeze(-1)
    if mask.ndim != 2:
        raise ValueError(f"the validity mask must have shape [episodes, steps]; got {list(mask.shape)}")
    lengths = mask.sum(-1)
    prefix = torch.arange(mask.shape[1]).expand_as(mask) < lengths.unsqueeze(-1)
    if not torch.equal(prefix, mask):
        bad = int((prefix != mask).any(-1).to(torch.int8).argmax())
        raise ValueError(
            f"the validity mask of episode row {bad} is not a prefix (valid steps, then padding)"
        )
    return lengths


def episode_metrics(
    rollouts: TensorDictBase,
    cost_threshold: float,
    *,
    return_range: tuple[float, float] | None = None,
    reward_key=("next", "reward"),
    cost_key=("next", "cost"),
    mask_key="mask",
) -> TensorDict:
    """Per-episode metrics of a padded ``[episodes, steps]`` TensorDict, e.g. from ``read_rollouts(...).steps``.

    Each episode's valid steps (``rollouts[mask_key]``, a prefix of each row) go through the per-episode
    functions of this module, so the numbers are the same ones.

    Args:
        rollouts: batch size ``[E, T]`` with reward and cost (``[E, T]`` or ``[E, T, 1]``) and the mask.
        cost_threshold: the task's cost threshold (feasible return and normalised cost).
        return_range: ``(R_min, R_max)``; adds ``normalized_return`` and ``normalized_feasible_return``.

    Returns:
        A TensorDict of batch size ``[E]``: ``return``, ``cost``, ``feasible_return``,
        ``strict_feasible_return``, ``normalized_cost`` (float64), ``length`` (int64), and with
        ``return_range`` the two normalised returns.

    Examples:
        >>> td = TensorDict({"next": {"reward": torch.tensor([[1.0, 2.0, 4.0], [5.0, 0.0, 0.0]]),
        ...                           "cost": torch.tensor([[0.0, 2.0, 0.0], [1.0, 0.0, 0.0]])},
        ...                  "mask": torch.tensor([[True, True, True], [True, False, False]])}, [2, 3])
        >>> m = episode_metrics(td, cost_threshold=1.0, return_range=(0.0, 10.0))
        >>> m["return"].tolist(), m["feasible_return"].tolist(), m["length"].tolist()
        ([7.0, 5.0], [1.0, 5.0], [3, 1])
        >>> m["normalized_cost"].tolist(), m["normalized_feasible_return"].tolist()
        ([2.0, 1.0], [0.1, 0.5])
    """
    if rollouts.batch_dims != 2:
        raise ValueError(f"rollouts must have batch size [episodes, steps]; got {list(rollouts.batch_size)}")
    lengths = _mask_lengths(rollouts.get(mask_key))
    reward = rollouts.get(reward_key).reshape(*rollouts.batch_size)
    cost = rollouts.get(cost_key).reshape(*rollouts.batch_size)
    rows = []
    for e, n in enumerate(lengths.tolist()):
        r, c = reward[e, :n], cost[e, :n]
        rows.append(
            [
                episode_return(r),
                episode_cost(c),
                feasible_return(r, c, cost_threshold),
                strict_feasible_return(r, c),
            ]
        )
    values = torch.tensor(rows, dtype=torch.float64).reshape(len(rows), 4)
    out = TensorDict(
        {
            "return": values[:, 0],
            "cost": values[:, 1],
            "feasible_return": values[:, 2],
            "strict_feasible_return": values[:, 3],
            "normalized_cost": normalized_cost(values[:, 1], cost_threshold),
            "length": lengths.to(torch.int64),
        },
        batch_size=[len(rows)],
    )
    if return_range is not None:
        lo, hi = return_range
        out["normalized_return"] = normalized_return(out["return"], lo, hi)
        out["normalized_feasible_return"] = normalized_return(out["feasible_return"], lo, hi)
    return out


def mean_of_last(evaluations: Sequence[float] | torch.Tensor, last: int = 10) -> float:
    """Mean of the last ``last`` evaluations of one seed (evaluations in chronological order).

    Raises:
        ValueError: if there are fewer than ``last`` evaluations (pass a smaller ``last`` on purpose for short
            runs) or ``last < 1``.

    Examples:
        >>> mean_of_last([0.0, 100.0, 1.0, 2.0, 3.0], last=3)
        2.0
    """
    values = torch.as_tensor(evaluations, dtype=torch.float64).reshape(-1)
    if last < 1:
        raise ValueError(f"last must be >= 1, got {last}")
    if values.numel() < last:
        raise ValueError(
            f"{values.numel()} evaluations, fewer than the last={last} to average; "
            "evaluate more often or pass a smaller `last` explicitly"
        )
    return float(values[-last:].mean())


class SeedAggregate(NamedTuple):
    """The paper's aggregate of one metric: ``mean`` +- ``stderr`` over seeds of the per-seed ``per_seed``.

    Examples:
        >>> agg = aggregate_over_seeds([[0.0, 2.0], [0.0, 4.0]], last=1)  # two seeds, two evaluations each
        >>> agg.per_seed
        (2.0, 4.0)
        >>> mean, stderr, _ = agg
        >>> f"{mean:.2f} +- {stderr:.2f} over {len(agg.per_seed)} seeds"
        '3.00 +- 1.00 over 2 seeds'
    """

    mean: float
    stderr: float
    per_seed: tuple[float, ...]


def aggregate_over_seeds(
    evaluations: Sequence[Sequence[float]] | torch.Tensor, last: int = 10
) -> SeedAggregate:
    """The paper's aggregate: per seed the mean of the last ``last`` evaluations, then mean +- SE over seeds.

    The standard error is the sample standard deviation over seeds (``n - 1`` in the denominator) divided by
    ``sqrt(n)``; with one seed it is undefined and returned as ``nan`` (a JSON writer must map it to ``null``).

    Args:
        evaluations: one sequence per seed of a metric's values at successive evaluations (each evaluation's
            value is usually the mean over its episodes), e.g. a ``[seeds, evaluations]`` tensor; seeds may
            have different numbers of evaluations.
        last: how many final evaluations to average per seed (the paper: 10).

    Raises:
        ValueError: on no seeds, or a seed with fewer than ``last`` evaluations (the message names it).

    Examples:
        >>> agg = aggregate_over_seeds([[9.0, 1.0, 2.0], [9.0, 3.0, 4.0], [9.0, 5.0, 6.0]], last=2)
        >>> agg.per_seed, agg.mean, round(agg.stderr, 4)  # seed means 1.5, 3.5, 5.5: std 2, SE 2 / sqrt(3)
        ((1.5, 3.5, 5.5), 3.5, 1.1547)
    """
    if len(evaluations) == 0:
        raise ValueError("aggregate_over_seeds got no seeds")
    per_seed = []
    for seed, values in enumerate(evaluations):
        try:
            per_seed.append(mean_of_last(values, last))
        except ValueError as err:
            raise ValueError(f"seed #{seed}: {err}") from err
    n = len(per_seed)
    means = torch.tensor(per_seed, dtype=torch.float64)
    stderr = float(means.std(correction=1) / math.sqrt(n)) if n > 1 else math.nan
    return SeedAggregate(mean=float(means.mean()), stderr=stderr, per_seed=tuple(per_seed))
