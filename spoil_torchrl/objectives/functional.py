"""Pure tensor functions shared by the losses: gradient penalties, log-sum-exp weights, reductions, and the
pieces every DICE dual has in common (Bellman backup, advantage, the nu gradient penalty's points).

Each function does one thing and holds no parameters, so every loss (SpoilDICE and the DICE baselines
DemoDICE and SafeDICE) uses the same numerically careful version.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import torch

REDUCTIONS = ("none", "mean", "sum")


def check_reduction(reduction: str | None, allowed: Sequence[str] = REDUCTIONS) -> str:
    """Return ``reduction`` (``None`` means ``"mean"``) or raise a ``ValueError`` naming the allowed values.

    Examples:
        >>> check_reduction(None)
        'mean'
    """
    reduction = "mean" if reduction is None else reduction
    if reduction not in allowed:
        raise ValueError(f"reduction must be one of {tuple(allowed)}, got {reduction!r}")
    return reduction


def reduce(values: torch.Tensor, reduction: str) -> torch.Tensor:
    """Reduce per-sample values: ``"none"`` keeps them, ``"mean"`` averages, ``"sum"`` adds.

    Examples:
        >>> reduce(torch.tensor([1.0, 3.0]), "mean")
        tensor(2.)
    """
    if reduction == "none":
        return values
    if reduction == "sum":
        return values.sum()
    return values.mean()


def log_mean_exp(x: torch.Tensor) -> torch.Tensor:
    """``log E[exp(x)]`` over all elements, computed stably with log-sum-exp.

    Examples:
        >>> log_mean_exp(torch.tensor([0.0, 0.0]))
        tensor(0.)
        >>> bool(torch.isfinite(log_mean_exp(torch.tensor([1000.0, 0.0]))))
        True
    """
    x = x.reshape(-1)
    return torch.logsumexp(x, dim=0) - math.log(x.numel())


def self_normalized_weights(log_weights: torch.Tensor) -> torch.Tensor:
    """``exp(log_w) / mean(exp(log_w))`` with the max subtracted first, so nothing overflows.

    The result has batch mean 1 and is the weight a DICE method's policy extraction uses. It is invariant to
    adding a constant to ``log_weights``, which is why the ``- 1`` of ``w* = exp(A - 1)`` does not matter here.

    Examples:
        >>> self_normalized_weights(torch.tensor([1000.0, 1000.0 + torch.log(torch.tensor(3.0)).item()]))
        tensor([0.5000, 1.5000])
    """
    shifted = torch.exp(log_weights - log_weights.max())
    return shifted / shifted.mean()


def interpolate(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Random points on the segments between matching rows of ``a`` and ``b`` (one uniform draw per row).

    Examples:
        >>> x = interpolate(torch.zeros(4, 2), torch.ones(4, 2))
        >>> bool(((x >= 0) & (x <= 1)).all()), bool((x[:, 0] == x[:, 1]).all())
        (True, True)
    """
    if a.shape != b.shape:
        raise ValueError(f"cannot interpolate tensors of shapes {tuple(a.shape)} and {tuple(b.shape)}")
    alpha = torch.rand(a.shape[:-1] + (1,), dtype=a.dtype, device=a.device)
    return alpha * a + (1 - alpha) * b


def gradient_penalty(norms: torch.Tensor, target: float | None) -> torch.Tensor:
    """Mean gradient penalty: ``E[(|g| - target)^2]`` (WGAN-GP style, ``target=1``) or ``E[|g|^2]`` (``None``).

    DemoDICE's reference code uses the first for its discriminator and the second for nu; we do the same.

    Examples:
        >>> gradient_penalty(torch.tensor([1.0, 3.0]), target=1.0)
        tensor(2.)
        >>> gradient_penalty(torch.tensor([1.0, 3.0]), target=None)
        tensor(5.)
    """
    if target is None:
        return norms.pow(2).mean()
    return (norms - target).pow(2).mean()


def effective_sample_size(weights: torch.Tensor) -> torch.Tensor:
    """Kish's effective sample size of non-negative ``weights``, as a fraction of their number (1 = uniform).

    Examples:
        >>> effective_sample_size(torch.tensor([1.0, 1.0, 1.0, 1.0]))
        tensor(1.)
        >>> effective_sample_size(torch.tensor([4.0, 0.0, 0.0, 0.0]))
        tensor(0.2500)
    """
    weights = weights.reshape(-1)
    return weights.sum().pow(2) / weights.pow(2).sum() / weights.numel()


def weight_diagnostics(log_weights: torch.Tensor, weights: torch.Tensor) -> dict[str, torch.Tensor]:
    """What every KL-regularised DICE loss reports of its weights: ``log_weight_mean`` (``log E[w*]`` of the
    closed-form log weights), ``weight_max`` and ``effective_sample_size`` (of the self-normalised weights).

    Examples:
        >>> log_w = torch.zeros(4)
        >>> {k: round(v.item(), 4) for k, v in weight_diagnostics(log_w, self_normalized_weights(log_w)).items()}
        {'log_weight_mean': 0.0, 'weight_max': 1.0, 'effective_sample_size': 1.0}
    """
    return {
        "log_weight_mean": log_mean_exp(log_weights),
        "weight_max": weights.max(),
        "effective_sample_size": effective_sample_size(weights),
    }


def bellman_backup(next_nu: torch.Tensor, terminated: torch.Tensor, gamma: float) -> torch.Tensor:
    """One-sample estimate of :math:`\\gamma (T\\nu)(s, a) = \\gamma\\, \\nu(s') (1 - \\text{terminated})`.

    Only termination stops bootstrapping: a step cut by a time limit (truncated) keeps its real next state.

    Examples:
        >>> bellman_backup(torch.tensor([2.0, 2.0]), torch.tensor([0.0, 1.0]), gamma=0.5).tolist()
        [1.0, 0.0]
    """
    return gamma * next_nu * (1.0 - terminated.to(next_nu.dtype))


def dice_advantage(reward: torch.Tensor, nu: torch.Tensor, backup: torch.Tensor) -> torch.Tensor:
    """:math:`A_\\nu(s,a) = r(s,a) + \\gamma (T\\nu)(s,a) - \\nu(s)`, the advantage of a KL-regularised DICE dual.

    DemoDICE (Kim et al., 2022) uses it with :math:`r = \\log d_P / d_R` (:math:`d_R` the distribution the KL
    regulariser points to), SafeDICE (Jang et al., 2023) with :func:`~spoil_torchrl.objectives.safedice_reward`;
    SpoilDICE's Eq. (7) adds :math:`\\lambda \\mathbb 1_S` (:func:`~spoil_torchrl.objectives.spoildice_advantage`).

    Examples:
        >>> dice_advantage(torch.tensor([1.0]), torch.tensor([0.5]), torch.tensor([0.25])).item()
        0.75
    """
    return reward + backup - nu


def penalty_points(
    init: Mapping[object, torch.Tensor],
    current: Mapping[object, torch.Tensor],
    following: Mapping[object, torch.Tensor],
) -> dict[object, torch.Tensor]:
    """The states a DICE dual's gradient penalty is taken at (:func:`~spoil_torchrl.objectives.dice.state_terms`):
    the current states, then points between the first initial and current states, then points between :math:`s`
    and :math:`s'` (random, one draw per row; DemoDICE's reference form, with the dual's own role in place of
    its expert data).

    The current states come first, so nu's values on the first ``n`` rows are nu's values at :math:`s`.

    Examples:
        >>> s = {"observation": torch.zeros(3, 2)}
        >>> s0 = {"observation": torch.ones(2, 2)}
        >>> penalty_points(s0, s, s)["observation"].shape  # 3 current + 2 init-current + 3 current-next
        torch.Size([8, 2])
    """
    keys = list(current)
    n0 = min(init[keys[0]].shape[0], current[keys[0]].shape[0])
    return {
        k: torch.cat(
            [
                current[k],
                interpolate(init[k][:n0], current[k][:n0]),
                interpolate(current[k], following[k]),
            ]
        )
        for k in keys
    }
