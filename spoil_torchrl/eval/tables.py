"""Markdown tables of episode statistics, such as the paper's Table I (return, feasible return and cost of
each policy type, mean +- standard error over episodes)."""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
from tensordict import TensorDict

from spoil_torchrl.eval.metrics import feasible_return


def transition_episode_metrics(episodes: TensorDict, cost_threshold: float) -> TensorDict:
    """Per-episode ``return``, ``feasible_return`` and ``cost`` (float64, batch ``[n_episodes]``) of TED-layout
    transitions with ``episode`` ids that are contiguous (as :func:`~spoil_torchrl.data.load_episodes` gives).

    Examples:
        >>> td = TensorDict({"episode": torch.tensor([0, 0, 1]),
        ...                  "next": {"reward": torch.tensor([[1.0], [2.0], [5.0]]),
        ...                           "cost": torch.tensor([[2.0], [0.0], [0.0]])}}, [3])
        >>> m = transition_episode_metrics(td, cost_threshold=1.0)
        >>> m["return"].tolist(), m["feasible_return"].tolist(), m["cost"].tolist()
        ([3.0, 5.0], [0.0, 5.0], [2.0, 0.0])
    """
    episode = episodes["episode"].reshape(-1)
    counts = torch.bincount(episode).tolist()
    rewards = episodes["next", "reward"].reshape(-1).double().split(counts)
    costs = episodes["next", "cost"].reshape(-1).double().split(counts)
    rows = [
        (float(r.sum()), feasible_return(r, c, cost_threshold), float(c.sum()))
        for r, c in zip(rewards, costs, strict=True)
    ]
    values = torch.tensor(rows, dtype=torch.float64).reshape(len(rows), 3)
    return TensorDict(
        {"return": values[:, 0], "feasible_return": values[:, 1], "cost": values[:, 2]},
        batch_size=[len(rows)],
    )


def mean_stderr(values: torch.Tensor) -> tuple[float, float]:
    """Mean and standard error (sample std with ``n - 1`` over ``sqrt(n)``; ``nan`` for one value).

    Examples:
        >>> mean_stderr(torch.tensor([1.0, 3.0]))
        (2.0, 1.0)
    """
    values = values.double().reshape(-1)
    n = values.numel()
    if n == 0:
        raise ValueError("mean_stderr of no values")
    se = float(values.std(correction=1) / math.sqrt(n)) if n > 1 else math.nan
    return float(values.mean()), se


def format_mean_stderr(mean: float, se: float, digits: int = 2) -> str:
    """``"mean ± se"`` with ``digits`` decimals, or the mean alone where the standard error is not finite (one
    seed).

    Examples:
        >>> format_mean_stderr(2.0, 1.0), format_mean_stderr(0.5, float("nan")), format_mean_stderr(6.0, 1.0, 1)
        ('2.00 ± 1.00', '0.50', '6.0 ± 1.0')
    """
    return f"{mean:.{digits}f} ± {se:.{digits}f}" if math.isfinite(se) else f"{mean:.{digits}f}"


def policy_table(episodes: TensorDict, pools: Mapping[str, torch.Tensor], cost_threshold: float) -> str:
    """A Table-I-style markdown table: per pool (label -> episode ids), the number of episodes and the mean +-
    standard error of return, feasible return (threshold ``cost_threshold``) and cost.

    Examples:
        >>> td = TensorDict({"episode": torch.tensor([0, 0, 1, 2]),
        ...                  "next": {"reward": torch.ones(4, 1), "cost": torch.zeros(4, 1)}}, [4])
        >>> print(policy_table(td, {"a": torch.tensor([0, 1]), "b": torch.tensor([2])}, 25.0))
        | policy | episodes | return | feasible return | cost |
        |---|---|---|---|---|
        | a | 2 | 1.50 ± 0.50 | 1.50 ± 0.50 | 0.00 ± 0.00 |
        | b | 1 | 1.00 ± nan | 1.00 ± nan | 0.00 ± nan |
    """
    metrics = transition_episode_metrics(episodes, cost_threshold)
    lines = ["| policy | episodes | return | feasible return | cost |", "|---|---|---|---|---|"]
    for label, ids in pools.items():
        cells = []
        for key in ("return", "feasible_return", "cost"):
            mean, se = mean_stderr(metrics[key][torch.as_tensor(ids)])
            cells.append(f"{mean:.2f} ± {se:.2f}")
        lines.append(f"| {label} | {len(ids)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
