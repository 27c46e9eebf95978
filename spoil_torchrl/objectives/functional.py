"""Pure tensor functions shared by the losses: gradient penalties, log-sum-exp weights, reductions.

Each function does one thing and holds no parameters, so every loss (SpoilDICE now, the DICE baselines
later) uses the same numerically careful version.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

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


def input_gradient_norms(fn: Callable[..., torch.Tensor], inputs: Sequence[torch.Tensor]) -> torch.Tensor:
    """Per-sample norms of the gradient of ``fn(*inputs)`` with respect to the (concatenated) inputs.

    The graph is kept (``create_graph=True``) so that a penalty on these norms trains the network parameters.

    Examples:
        >>> w = torch.tensor([3.0, 4.0], requires_grad=True)
        >>> input_gradient_norms(lambda x: x @ w, [torch.randn(5, 2)])
        tensor([5., 5., 5., 5., 5.], grad_fn=<LinalgVectorNormBackward0>)
    """
    leaves = [x.detach().requires_grad_(True) for x in inputs]
    with torch.enable_grad():
        out = fn(*leaves)
        grads = torch.autograd.grad(out.sum(), leaves, create_graph=True)
    return torch.cat([g.reshape(g.shape[0], -1) for g in grads], dim=-1).norm(dim=-1)


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
